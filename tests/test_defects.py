"""Regression tests for the defects a hostile new user found: data loss or duplication,
wrong results without a word, accepted nonsense, tracebacks, messages that name the wrong problem,
and one bad file killing a whole run. Each test failed before its fix."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core.errors import CheckpointError, InputError
from icpbench.harness.report import table1, table1_counts
from icpbench.harness.results import RESULTS_FILE, load_results, read_manifest
from icpbench.harness.runner import RunConfig, run

torch.set_num_threads(1)
cli = CliRunner()
SYN = dict(dataset="synthetic", targets=["p2plane"], dataset_params={"n_samples": 4, "n_scan": 300,
                                                                      "n_map": 3000})


def _one_line_error(res, needle: str) -> None:
    assert res.exit_code == 2, res.output
    assert needle in res.output, res.output
    assert "Traceback" not in res.output


def _rows(df: pd.DataFrame) -> pd.DataFrame:
    keep = [c for c in df.columns if c not in ("attack_time_s", "icp_time_s")]
    return df[keep].sort_values(["sample_id", "attack", "target", "budget", "seed"]).reset_index(
        drop=True)


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    run(RunConfig(**SYN, attacks=["none", "uniform"], budgets=[0.5], samples=3), out,
        progress=False)
    return out


# -- 1. `table --out` over the raw rows or the manifest ---------------------------------------------
@pytest.mark.parametrize("name", ["results.csv", "manifest.json", "notes.txt"])
def test_table_refuses_to_overwrite_a_results_folders_own_files(small_run, tmp_path, name):
    run_dir = tmp_path / "r"
    shutil.copytree(small_run, run_dir)
    (run_dir / "notes.txt").write_text("my notes\n")
    before = (run_dir / name).read_bytes()
    res = cli.invoke(app, ["table", str(run_dir), "--format", "csv", "--reference", "uniform",
                           "--out", str(run_dir / name)])
    _one_line_error(res, "refusing to")
    assert (run_dir / name).read_bytes() == before
    # a table of ours beside the rows may be written and rewritten
    for _ in range(2):
        res = cli.invoke(app, ["table", str(run_dir), "--format", "md", "--reference", "uniform",
                               "--out", str(run_dir / "table1.md")])
        assert res.exit_code == 0, res.output
    assert (run_dir / "table1.md").read_text().startswith("| Method")


# -- 2. `train --out` over a checkpoint it did not write ---------------------------------------------
def test_train_refuses_to_overwrite_a_checkpoint_it_did_not_write(tmp_path):
    from icpbench.learning.checkpoint import save_checkpoint
    from icpbench.learning.network import Generator, generator_config

    save_checkpoint(Generator(generator_config("objects")), tmp_path / "generator.pt")
    before = (tmp_path / "generator.pt").read_bytes()
    res = cli.invoke(app, ["train", "--preset", "quick-objects", "--out", str(tmp_path),
                           "--epochs", "1", "--quiet"])
    _one_line_error(res, "already holds a generator.pt/.json that no training run")
    assert (tmp_path / "generator.pt").read_bytes() == before


# -- 3. two runs on one folder; duplicated rows --------------------------------------------------
def test_a_second_run_on_a_locked_folder_is_refused(tmp_path):
    from icpbench.harness.results import lock_results_dir

    cfg = RunConfig(**SYN, attacks=["none"], budgets=[0.5], samples=1)
    tmp_path.mkdir(exist_ok=True)
    with lock_results_dir(tmp_path):
        with pytest.raises(InputError, match=r"is in use by another icpbench run \(pid \d+"):
            run(cfg, tmp_path, progress=False)
    run(cfg, tmp_path, progress=False)  # released: runs


def test_duplicated_rows_are_read_once(small_run, tmp_path):
    run_dir = tmp_path / "r"
    shutil.copytree(small_run, run_dir)
    csv = run_dir / RESULTS_FILE
    lines = csv.read_text().splitlines(keepends=True)
    csv.write_text("".join(lines + lines[1:]))  # what two concurrent runs used to write
    df = load_results(run_dir)
    assert len(df) == 6 and df.attrs["duplicate_rows"] == 6
    counts = table1_counts(df, reference="uniform")
    assert set(counts["n"]) == {3}  # not 6
    assert "6 row(s) stored twice" in table1(df, reference="uniform")
    # resuming does not add rows either
    run(RunConfig(**SYN, attacks=["none", "uniform"], budgets=[0.5], samples=3), run_dir,
        progress=False)
    assert len(load_results(run_dir)) == 6


# -- 4. results depend on the batch size ---------------------------------------------------------
def test_rows_do_not_depend_on_the_batch_size(tmp_path):
    base = dict(**SYN, attacks=["uniform", "normal", "pgd"], budgets=[0.5, 1.0], samples=4,
                attack_params={"pgd": {"steps": 1, "icp_iterations": 3}})
    run(RunConfig(**base, batch_size=1), tmp_path / "b1", progress=False)
    run(RunConfig(**base, batch_size=4), tmp_path / "b4", progress=False)
    a, b = load_results(tmp_path / "b1"), load_results(tmp_path / "b4")
    assert len(a) == 4 * 3 * 2
    pd.testing.assert_frame_equal(_rows(a), _rows(b))
    # and different samples do get different random directions
    u = a[(a["attack"] == "uniform") & (a["budget"] == 1.0)]
    assert u["rho_x"].round(3).nunique() == 4


# -- 5. the KITTI cache ignores the scan files' contents -----------------------------------------
@pytest.fixture()
def kitti_root(tmp_path):
    from test_kitti_boreas import _sensor_poses, _write_kitti

    root = tmp_path / "kitti"
    root.mkdir()
    _write_kitti(root, _sensor_poses(0.3))
    return root


def _kitti(root, cache, **kw):
    from icpbench.datasets.kitti import KittiDataset

    return KittiDataset(root, "00", stride=2, window=1, n_points=500, cache_dir=cache, **kw)


def test_kitti_cache_notices_a_replaced_scan_file(kitti_root, tmp_path):
    vel = kitti_root / "sequences" / "00" / "velodyne"
    first = _kitti(kitti_root, tmp_path / "cache")[2]  # frame 4
    shutil.copy(vel / "000006.bin", vel / "000004.bin")  # another frame under the same name
    second = _kitti(kitti_root, tmp_path / "cache")[2]
    assert not np.array_equal(first.scan, second.scan)
    np.full((100, 4), np.nan, dtype="<f4").tofile(vel / "000004.bin")
    with pytest.raises(InputError, match="000004.bin is corrupt: 100 point"):
        _kitti(kitti_root, tmp_path / "cache")[2]


# -- 6. a folder with rows but no manifest ----------------------------------------------------------
def test_rows_without_a_manifest_are_not_adopted(small_run, tmp_path):
    run_dir = tmp_path / "r"
    shutil.copytree(small_run, run_dir)
    (run_dir / "manifest.json").unlink()
    with pytest.raises(InputError, match="holds a results.csv but no manifest.json"):
        run(RunConfig(**SYN, attacks=["none", "uniform"], budgets=[2.0], samples=3), run_dir,
            progress=False)


# -- 7 and 11: unknown and non-numeric plugin settings (library: test_plugin_contract.py) ---------
@pytest.mark.parametrize("args, needle", [
    (["--attacks", "pgd", "--attack-param", "pgd.step=5"], "unknown setting(s) 'step' for attack"),
    (["--attacks", "uniform", "--attack-param", "bogus.steps=3"],
     "settings given for attack(s) 'bogus' that are not in this run"),
    (["--attacks", "pgd", "--attack-param", "pgd.steps=abc"],
     "setting 'steps' of attack 'pgd' must be an integer, got 'abc'"),
    (["--attacks", "none", "--target-param", "p2plane.max_iterations=abc"],
     "setting 'max_iterations' of target 'p2plane' must be an integer, got 'abc'"),
    (["--attacks", "none", "--dataset-param", "n_scan=-5"],
     "setting 'n_scan' of dataset 'synthetic' must be >= 6"),
])
def test_bad_plugin_settings_on_the_command_line(args, needle, tmp_path):
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--budgets", "1", "--samples", "1",
                           "--out", str(tmp_path / "o"), "--quiet", *args])
    _one_line_error(res, needle)


def test_non_numeric_kitti_setting_is_a_clean_error(kitti_root, tmp_path):
    res = cli.invoke(app, ["run", "--dataset", "kitti", "--dataset-param", f"root={kitti_root}",
                           "--dataset-param", "window=abc", "--attacks", "none", "--out",
                           str(tmp_path / "o")])
    _one_line_error(res, "setting 'window' of dataset 'kitti' must be an integer, got 'abc'")


# -- 8. an edited generator JSON -----------------------------------------------------------------
def test_an_edited_generator_json_is_refused(tmp_path):
    from icpbench.learning.checkpoint import CONFIG_HASH_KEY, load_checkpoint, save_checkpoint
    from icpbench.learning.network import Generator, generator_config

    path = save_checkpoint(Generator(generator_config("objects")), tmp_path / "g.pt")
    load_checkpoint(path)
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["config"]["scale_m"] = meta["config"].get("scale_m", 1.0) * 2 + 1  # same tensor shapes
    path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="was edited after g.pt was saved"):
        load_checkpoint(path)
    # a checkpoint from before the hash existed still loads
    state = torch.load(path, weights_only=True)
    state.pop(CONFIG_HASH_KEY)
    torch.save(state, path)
    assert load_checkpoint(path).config.scale_m == meta["config"]["scale_m"]


# -- 9. half-written and NaN rows in `table` --------------------------------------------------------
def test_half_written_rows_are_ignored_and_nan_rows_are_not_converged(small_run, tmp_path):
    run_dir = tmp_path / "r"
    shutil.copytree(small_run, run_dir)
    csv = run_dir / RESULTS_FILE
    df0 = pd.read_csv(csv, keep_default_na=False)
    lines = csv.read_text().splitlines(keepends=True)
    # a half-written row of a fourth sample (a line cut in the middle, then a newline)
    half = lines[1].replace("synthetic/test/000000", "synthetic/test/000009")
    cut = half.split(",")[:8]
    csv.write_text("".join(lines) + ",".join(cut) + "\n")
    df = load_results(run_dir)
    assert df.attrs["incomplete_rows"] == 1 and "synthetic/test/000009" not in set(df["sample_id"])
    text = table1(df, reference="uniform")
    assert "1 incomplete (half-written) row(s) ignored" in text
    # a row whose errors are NaN is not converged
    i = int(np.flatnonzero((df0["attack"] == "uniform").to_numpy())[0])
    df0.loc[i, ["trans_err_xy", "trans_err", "rot_err"]] = np.nan
    df0.to_csv(csv, index=False)
    df = load_results(run_dir)
    bad = df[df["sample_id"].eq(df0.loc[i, "sample_id"]) & df["attack"].eq("uniform")]
    assert not bad["converged"].any()
    counts = table1_counts(df, reference="uniform")
    assert counts.set_index("attack").loc["uniform", "n"] == 2
    assert "nan ± nan" not in table1(df, reference="uniform")


# -- 10. accepted nonsense -----------------------------------------------------------------------
@pytest.mark.parametrize("args, needle", [
    (["run", "--dataset", "synthetic", "--budgets", ""], "(--budgets) must be a non-empty list"),
    (["run", "--dataset", "synthetic", "--out", ""], "--out must be a non-empty text, got ''"),
    (["run", "--dataset", "synthetic", "--attacks", "none", "--reference", "bogus"],
     "--reference 'bogus' is not an attack"),
    (["run", "--dataset", "synthetic", "--attacks", "generator", "--attack-param",
      "generator.checkpoint="], "'generator.checkpoint=' has no value"),
    (["run", "--dataset", "synthetic", "--budgets", "1e300"], "budget must be a positive finite"),
    (["train", "--max-minutes", "-1"], "--max-minutes must be a number > 0 and <= 10000000 or null, got -1"),
    (["train", "--epochs", "-1"], "--epochs must be an integer >= 0 or null, got -1"),
    (["object-study", "--model", "a=x.pt", "--figure-objects", "-1"],
     "--figure-objects must be an integer >= 1"),
])
def test_nonsense_inputs_are_refused(args, needle, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a command that wrongly ran would write here, not in the repo
    res = cli.invoke(app, args)
    _one_line_error(res, needle)
    assert not (tmp_path / "results.csv").exists() and not (tmp_path / "runs").exists()


def test_table_reference_must_be_an_attack(small_run):
    _one_line_error(cli.invoke(app, ["table", str(small_run), "--reference", "bogus"]),
                    "--reference 'bogus' is not an attack")


# -- 12. show-dataset --sample out of range ------------------------------------------------------
@pytest.mark.parametrize("index", ["999", "-5"])
def test_show_dataset_sample_out_of_range(index, tmp_path):
    res = cli.invoke(app, ["show-dataset", "synthetic", "--sample", index, "--out", str(tmp_path),
                           "--dataset-param", "n_samples=3"])
    _one_line_error(res, f"sample index {index} is out of range: dataset 'synthetic' has 3 samples")


# -- messages that named the wrong problem --------------------------------------------------------
def test_truncated_train_state_is_named(tmp_path):
    from dataclasses import asdict

    from icpbench.learning.checkpoint import save_checkpoint
    from icpbench.learning.network import Generator, generator_config
    from icpbench.learning.training import train, train_config

    cfg = train_config("quick-objects", epochs=1, pretrain_epochs=0, train_samples=1,
                       eval_samples=1, dataset_params={"n_samples": 2})
    (tmp_path / "train_config.json").write_text(json.dumps(asdict(cfg)))
    save_checkpoint(Generator(generator_config("objects", conditioned=False)),
                    tmp_path / "generator.pt")
    (tmp_path / "train_state.pt").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(CheckpointError, match="train_state.pt is truncated or corrupt"):
        train(cfg, tmp_path, progress=False)


def test_nan_in_kitti_poses_is_named(tmp_path):
    from icpbench.datasets.kitti import read_kitti_poses

    p = tmp_path / "00.txt"
    p.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 nan 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"00.txt:2: the pose line has 1 NaN or Inf value"):
        read_kitti_poses(p)


def test_all_zero_kitti_scan_is_named(kitti_root, tmp_path):
    vel = kitti_root / "sequences" / "00" / "velodyne"
    np.zeros((500, 4), dtype="<f4").tofile(vel / "000004.bin")
    with pytest.raises(InputError, match=r"000004.bin has 0 point\(s\) farther than min_range_m"):
        _kitti(kitti_root, tmp_path / "cache")[2]


def _write_meshes(folder: Path, n: int) -> None:
    import open3d as o3d

    folder.mkdir(parents=True)
    for k in range(n):
        m = o3d.geometry.TriangleMesh.create_box(1.0 + 0.1 * k, 1.0, 0.5 + 0.05 * k)
        o3d.io.write_triangle_mesh(str(folder / f"box{k}.obj"), m)


def test_degenerate_mesh_is_named(tmp_path):
    from icpbench.datasets.meshes import MeshFolderDataset

    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")  # zero area
    ds = MeshFolderDataset(folder, split="all")
    with pytest.raises(InputError, match=r"mesh file .*flat.obj: mesh has zero surface area"):
        ds[0]


def test_config_mismatch_names_the_setting(tmp_path):
    run(RunConfig(**SYN, attacks=["none"], budgets=[0.5], samples=1), tmp_path, progress=False)
    with pytest.raises(InputError, match=r"different configuration \(budgets: stored \[0.5\], "
                                         r"now \[1.0\]\)"):
        run(RunConfig(**SYN, attacks=["none"], budgets=[1.0], samples=1), tmp_path, progress=False)


def test_ctrl_c_says_that_the_same_command_resumes(tmp_path, monkeypatch):
    import icpbench.harness.runner as runner

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "run", interrupted)
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--attacks", "none", "--budgets", "1",
                           "--out", str(tmp_path / "o")])
    assert res.exit_code == 130  # nothing was saved yet: the same command starts again
    assert "re-running the same command starts from the beginning" in res.output
    assert "Aborted" not in res.output


# -- one bad file no longer kills the whole run -----------------------------------------------------
def test_a_truncated_kitti_scan_skips_only_the_samples_that_read_it(kitti_root, tmp_path):
    vel = kitti_root / "sequences" / "00" / "velodyne"
    with open(vel / "000008.bin", "r+b") as f:  # frame 8: sample 4 (frames 0, 2, ..., 8)
        f.truncate(1000 * 16 + 7)
    params = {"root": str(kitti_root), "stride": 2, "window": 1, "n_points": 500,
              "cache_dir": str(tmp_path / "cache")}
    res = cli.invoke(app, ["run", "--dataset", "kitti", "--attacks", "none", "--budgets", "1",
                           "--out", str(tmp_path / "o"), "--quiet",
                           *[a for k, v in params.items() for a in ("--dataset-param", f"{k}={v}")]])
    assert res.exit_code == 0, res.output
    assert res.output.count("warning: skipped sample") == 1
    assert "000008.bin has" in res.output and "truncated" in res.output
    df = load_results(tmp_path / "o")
    bad = df[df["status"] == "error"]
    assert list(bad["sample_id"]) == ["kitti/00/000008"]
    assert bad["error"].str.startswith("bad input: ").all()
    assert (df["status"] != "error").sum() == 4
    assert read_manifest(tmp_path / "o")["skipped_samples"].keys() == {"kitti/00/000008"}
    # with strict_files the run stops instead
    res = cli.invoke(app, ["run", "--dataset", "kitti", "--attacks", "none", "--budgets", "1",
                           "--out", str(tmp_path / "o2"), "--quiet", "--strict-files",
                           *[a for k, v in params.items() for a in ("--dataset-param", f"{k}={v}")]])
    _one_line_error(res, "000008.bin has")
    # fixing the file and re-running computes the skipped sample (its new rows replace the error)
    from test_kitti_boreas import _sensor_poses, _write_kitti

    fresh = tmp_path / "fresh"
    fresh.mkdir()
    _write_kitti(fresh, _sensor_poses(0.3))
    shutil.copy(fresh / "sequences" / "00" / "velodyne" / "000008.bin", vel / "000008.bin")
    res = cli.invoke(app, ["run", "--dataset", "kitti", "--attacks", "none", "--budgets", "1",
                           "--out", str(tmp_path / "o"), "--quiet",
                           *[a for k, v in params.items() for a in ("--dataset-param", f"{k}={v}")]])
    assert res.exit_code == 0, res.output
    df = load_results(tmp_path / "o")
    assert len(df) == 5 and (df["status"] != "error").all()
    # the replaced error row is a retry, not a key "stored twice"
    assert df.attrs["retried_rows"] == 1 and df.attrs["duplicate_rows"] == 0
    assert "stored twice" not in res.output


def test_one_garbage_mesh_among_several_skips_one_sample(tmp_path):
    folder = tmp_path / "meshes"
    _write_meshes(folder, 4)
    (folder / "box2.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")  # bad index
    cfg = RunConfig(dataset="meshes", attacks=["none"], targets=["p2plane"], budgets=[0.05],
                    dataset_params={"root": str(folder), "test_fraction": 1.0,
                                    "n_map_points": 2000, "n_scan_points": 300})
    run(cfg, tmp_path / "o", progress=False)
    df = load_results(tmp_path / "o")
    assert len(df) == 4 and list(df.loc[df["status"] == "error", "sample_id"]) == ["meshes/box2"]
    assert df.loc[df["status"] == "error", "error"].str.contains("box2.obj").all()
    cfg.strict_files = True
    with pytest.raises(InputError, match="box2.obj"):
        run(cfg, tmp_path / "o-strict", progress=False)
    # a run in which no sample at all can be read is an error, not a table of error rows
    only_bad = tmp_path / "only-bad"
    only_bad.mkdir()
    shutil.copy(folder / "box2.obj", only_bad / "box2.obj")
    cfg = RunConfig(**{**cfg.__dict__, "dataset_params": {**cfg.dataset_params,
                                                         "root": str(only_bad)},
                       "strict_files": False})
    with pytest.raises(InputError, match=r"no sample of dataset 'meshes' could be read \(1 "
                                         r"skipped\); the first, meshes/box2: mesh file .*box2.obj"):
        run(cfg, tmp_path / "o-only-bad", progress=False)


# -- a KITTI sequence name with a leading zero stays text -------------------------------------------
def test_dataset_param_sequence_05_stays_the_text_05(kitti_root, tmp_path):
    from icpbench.cli import _kv

    # YAML reads 05 as the number 5 (and 010 as the octal 8); a leading zero keeps the text
    assert _kv("sequence=05", "--dataset-param") == ("sequence", "05")
    assert _kv("sequence=00", "--dataset-param") == ("sequence", "00")
    assert _kv("x=010", "--dataset-param") == ("x", "010")
    assert _kv("x=0", "--dataset-param") == ("x", 0) and _kv("x=5", "--dataset-param") == ("x", 5)
    assert _kv("town_seed=[1,2]", "--dataset-param") == ("town_seed", [1, 2])
    (kitti_root / "sequences" / "00").rename(kitti_root / "sequences" / "05")
    (kitti_root / "poses" / "00.txt").rename(kitti_root / "poses" / "05.txt")
    params = {"root": str(kitti_root), "sequence": "05", "stride": 2, "window": 1, "n_points": 500,
              "cache_dir": str(tmp_path / "cache")}
    res = cli.invoke(app, ["run", "--dataset", "kitti", "--attacks", "none", "--budgets", "1",
                           "--samples", "2", "--out", str(tmp_path / "o"), "--quiet",
                           *[a for k, v in params.items() for a in ("--dataset-param", f"{k}={v}")]])
    assert res.exit_code == 0, res.output  # before the fix: no folder sequences/5/velodyne
    df = load_results(tmp_path / "o")
    assert sorted(df["sample_id"]) == ["kitti/05/000000", "kitti/05/000002"]
    assert read_manifest(tmp_path / "o")["dataset"]["sequence"] == "05"
