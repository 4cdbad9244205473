"""Regression tests of the reliability guarantees in docs/reliability.md (data loss, wrong results
without a word, paths built from user text, tracebacks, messages naming the wrong problem). Each
test failed before the change it covers."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core.errors import InputError
from icpbench.harness.results import RESULTS_FILE
from icpbench.harness.runner import RunConfig, run

torch.set_num_threads(1)
cli = CliRunner()
SYN = dict(dataset="synthetic", targets=["p2plane"], dataset_params={"n_samples": 3, "n_scan": 200,
                                                                      "n_map": 2000})


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run")
    run(RunConfig(**SYN, attacks=["none", "uniform"], budgets=[0.5], samples=2), out,
        progress=False)
    return out


# -- data loss: `table --out` ---------------------------------------------------------------------
def _table(run_dir: Path, out: Path):
    return cli.invoke(app, ["table", str(run_dir), "--reference", "uniform", "--out", str(out)])


def test_table_out_never_overwrites_a_file_it_did_not_write(tiny_run, tmp_path, user_error):
    victim = tmp_path / "generator.pt"
    victim.write_bytes(b"\x80\x02weights")
    user_error(_table(tiny_run, victim), "not a table written by `icpbench table`")
    assert victim.read_bytes() == b"\x80\x02weights"
    new = tmp_path / "t.md"  # a new file, then the table it wrote, may be written
    for _ in range(2):
        res = _table(tiny_run, new)
        assert res.exit_code == 0, res.output
    assert new.read_text().startswith("| Method")


def test_table_out_never_writes_through_a_link(tiny_run, tmp_path, user_error):
    run_dir = tmp_path / "r"
    shutil.copytree(tiny_run, run_dir)
    before = (run_dir / RESULTS_FILE).read_bytes()
    link = tmp_path / "t.md"
    os.symlink(run_dir / RESULTS_FILE, link)
    user_error(_table(run_dir, link), "through the link")
    linked_dir = tmp_path / "alias"
    os.symlink(run_dir, linked_dir)
    user_error(_table(run_dir, linked_dir / RESULTS_FILE), "file of the results folder")
    assert (run_dir / RESULTS_FILE).read_bytes() == before


# -- config files are checked as the flags are ------------------------------------------------------
SMALL_CONFIG = ("dataset: synthetic\ndataset_params: {n_samples: 1, n_scan: 100, n_map: 1000}\n"
                "attacks: none\nbudgets: [1]\n")


@pytest.mark.parametrize(("text", "needle"), [
    ("", "is empty; give at least one setting"),
    ("# nothing but a comment\n", "is empty"),
    ("budgets: [1, '5']\n", "setting 'budgets' must be"),
    ("strict: 'no'\n", "setting 'strict' must be true or false, got 'no'"),
    ("strict_files: 1\n", "setting 'strict_files' must be true or false"),
    ("seeds: 1.5\n", "setting 'seeds' must be"),
    ("dataset_params: abc\n", "setting 'dataset_params' must be a mapping"),
    ("attack_params: [1, 2]\n", "setting 'attack_params' must be a mapping of plugin names"),
    ("dataset_seed: -1\n", "setting 'dataset_seed' must be an integer >= 0, got -1"),
    ("samples: 0\n", "setting 'samples' must be an integer >= 1 or null, got 0"),
    ("threads: '2'\n", "setting 'threads' must be an integer"),
    ("attacks: 5\n", "setting 'attacks' must be"),
])
def test_config_file_fields_are_type_and_range_checked(tmp_path, text, needle, user_error):
    cfg = tmp_path / "c.yaml"
    # a small valid run first (PyYAML lets the later line of a key win), so that a bad value that is
    # not refused runs in a second instead of starting the default grid
    cfg.write_text((SMALL_CONFIG if text.strip() and not text.startswith("#") else "") + text)
    out = tmp_path / "out"
    res = cli.invoke(app, ["run", "--config", str(cfg), "--out", str(out), "--quiet"])
    user_error(res, needle)
    assert str(cfg) in res.output
    assert not out.exists()


def test_config_file_spellings_of_the_flags_mean_what_the_flags_mean(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("budgets: '15'\nseeds: 5\n")
    got = RunConfig.from_file(cfg)
    assert got.budgets == [15.0] and got.seeds == [5]
    cfg.write_text("budgets: 2\nseeds: '0,1'\n")
    got = RunConfig.from_file(cfg)
    assert got.budgets == [2.0] and got.seeds == [0, 1]


def test_a_seed_beyond_64_bits_is_refused_before_any_row(tmp_path, user_error):
    out = tmp_path / "out"
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--dataset-param", "n_samples=1",
                           "--attacks", "none", "--budgets", "1", "--seed", str(2**64),
                           "--out", str(out), "--quiet"])
    user_error(res, "seeds (--seed) must be a non-empty list of integers from")
    assert not (out / RESULTS_FILE).exists()


def test_a_results_file_with_an_unreadable_seed_is_reported(tiny_run, tmp_path):
    from icpbench.harness.results import load_results

    run_dir = tmp_path / "r"
    shutil.copytree(tiny_run, run_dir)
    csv = run_dir / RESULTS_FILE
    lines = csv.read_text().splitlines(keepends=True)
    first = lines[1].split(",")
    first[4] = str(2**64)
    csv.write_text("".join([lines[0], ",".join(first), *lines[2:]]))
    with pytest.raises(InputError, match=r"line 2, column 'seed': \S*18446744073709551616\S* is not a "
                                         "64-bit integer seed"):
        load_results(run_dir)


# -- train: checked before anything is written, locked, never a NaN checkpoint ---------------------
TRAIN = ["train", "--preset", "quick-objects", "--train-samples", "2", "--eval-samples", "1",
         "--batch-size", "2", "--pretrain-epochs", "0", "--epochs", "1", "--quiet",
         "--dataset-param", "n_samples=4"]


@pytest.mark.parametrize(("extra", "needle"), [
    (["--budgets", ""], "(--budgets) must be a non-empty list"),
    (["--budgets", "1e300"], "budget must be a positive finite number of metres <="),
    (["--eval-samples", "0"], "--eval-samples must be an integer >= 1"),
    (["--epochs", "0"], "--epochs + --pretrain-epochs must be >= 1"),
    (["--lr", "1e30"], "--lr must be a number >= 0 and <= 1"),
    (["--generator-param", "bogus=1"], "unknown generator setting(s) 'bogus' (--generator-param); "
                                        "valid: "),
])
def test_train_refuses_up_front_and_writes_nothing(tmp_path, extra, needle, user_error):
    out = tmp_path / "gen"
    user_error(cli.invoke(app, [*TRAIN, "--out", str(out), *extra]), needle)
    assert not out.exists() or not any(out.iterdir())


def test_object_study_refuses_zero_figure_objects(user_error):
    user_error(cli.invoke(app, ["object-study", "--model", "a=x.pt", "--figure-objects", "0"]),
               "--figure-objects must be an integer >= 1")


def test_train_refused_by_its_data_leaves_no_configuration_behind(tmp_path, user_error):
    out = tmp_path / "gen"
    user_error(cli.invoke(app, [*TRAIN, "--out", str(out), "--dataset-param", "n_scan_points=3"]),
               "n_scan_points")
    assert not (out / "train_config.json").exists()


def test_a_second_training_run_into_one_folder_is_refused(tmp_path):
    from icpbench.harness.results import lock_results_dir
    from icpbench.learning.training import train, train_config

    cfg = train_config("quick-objects", train_samples=2, eval_samples=1, batch_size=2,
                       pretrain_epochs=0, epochs=1, dataset_params={"n_samples": 4})
    tmp_path.mkdir(exist_ok=True)
    with lock_results_dir(tmp_path), pytest.raises(InputError, match="in use by another"):
        train(cfg, tmp_path, progress=False)
    assert not (tmp_path / "history.csv").exists()


def test_diverging_training_says_so_and_keeps_no_nan_checkpoint(tmp_path, monkeypatch):
    import icpbench.learning.training as tr

    cfg = tr.train_config("quick-objects", train_samples=2, eval_samples=1, batch_size=2,
                          pretrain_epochs=0, epochs=1, dataset_params={"n_samples": 4})
    monkeypatch.setattr(tr, "reconstruction_loss", lambda *a: torch.tensor([float("nan")],
                                                                           requires_grad=True))
    with pytest.raises(InputError, match="training diverged in epoch 1 .*lower --lr"):
        tr.train(cfg, tmp_path, progress=False)
    assert not (tmp_path / "generator.pt").exists()


def test_a_refused_run_leaves_no_manifest_so_the_corrected_command_runs(tmp_path, user_error):
    out = tmp_path / "out"
    base = ["run", "--dataset", "synthetic", "--attacks", "none", "--budgets", "1", "--out",
            str(out), "--quiet", "--dataset-param", "n_scan=100", "--dataset-param", "n_map=1000"]
    user_error(cli.invoke(app, [*base, "--dataset-param", "n_samples=0"]), "has no samples")
    assert not (out / "manifest.json").exists()
    res = cli.invoke(app, [*base, "--dataset-param", "n_samples=1"])
    assert res.exit_code == 0, res.output


# -- ICPBENCH_PLUGINS ------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["no_such_icpbench_module", " , ", "icpbench_raising_plugin"])
def test_bad_plugin_modules_are_reported_not_raised(tmp_path, monkeypatch, value):
    from icpbench.core import registry

    (tmp_path / "icpbench_raising_plugin.py").write_text("raise RuntimeError('broken plugin')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("ICPBENCH_PLUGINS", value)
    for reg in (registry.attacks, registry.targets, registry.datasets, registry.corruptions):
        monkeypatch.setattr(reg, "_discovered", False)
    res = cli.invoke(app, ["list"])
    assert res.exit_code == 0, res.output
    assert "p2plane" in res.output
    if value.strip(", "):
        assert "ICPBENCH_PLUGINS that do not load" in res.output and value in res.output
        with pytest.raises(InputError, match=f"unknown attack 'mine'.*ICPBENCH_PLUGINS module "
                                             f"'{value}' did not load"):
            registry.attacks.get("mine")
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--dataset-param", "n_samples=1",
                           "--dataset-param", "n_scan=100", "--dataset-param", "n_map=1000",
                           "--attacks", "none", "--budgets", "1", "--quiet",
                           "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output


# -- user text in paths ------------------------------------------------------------------------------
def test_user_text_never_leaves_its_folder(tmp_path):
    from icpbench.analysis.danger_map import write_maps
    from icpbench.core.filenames import safe_component
    from icpbench.harness.results import load_results

    out = tmp_path / "a" / "b" / "maps"
    df = load_results(_run_with_hostile_pass(tmp_path))
    write_maps(df, "none", 1.0, out)
    written = {p.resolve() for p in tmp_path.rglob("*") if p.is_file()}
    assert not any("ESCAPED" in str(p) and out.resolve() not in p.parents for p in written)
    assert any("ESCAPED" in p.name for p in out.iterdir())
    for bad in ("../../x", "a/b", "..", ".hidden"):
        name = safe_component(bad)
        assert "/" not in name and not name.startswith(".")


def _run_with_hostile_pass(tmp_path: Path) -> Path:
    """A results folder whose rows carry route metadata with a hostile pass name."""
    run_dir = tmp_path / "run"
    run(RunConfig(**SYN, attacks=["none"], budgets=[1.0], samples=2), run_dir, progress=False)
    csv = run_dir / RESULTS_FILE
    import pandas as pd

    df = pd.read_csv(csv, keep_default_na=False)
    df["meta"] = [json.dumps({"frame": i, "x": float(i), "y": 0.0, "pass": "../../../ESCAPED"})
                  for i in range(len(df))]
    df.to_csv(csv, index=False)
    return run_dir


@pytest.mark.parametrize("seq", ["../../../ESCAPED", "a/b", ".."])
def test_kitti_sequence_must_be_a_plain_name(tmp_path, seq):
    from icpbench.datasets.kitti import KittiDataset

    with pytest.raises(InputError, match="KITTI setting sequence must be a plain name"):
        KittiDataset(tmp_path, sequence=seq)


# -- numeric plugin settings have ranges --------------------------------------------------------------
@pytest.mark.parametrize(("params", "needle"), [
    (["--target-param", "p2plane.tol=inf"], "setting 'tol' of target 'p2plane' must be a finite"),
    (["--target-param", "p2plane.tol=0.5e1"], "setting 'tol' of target 'p2plane' must be > 0 and"),
    (["--target-param", "p2plane.damping=-1"], "setting 'damping' of target 'p2plane' must be"),
    (["--target-param", "p2plane.kdtree_workers=0"], "setting 'kdtree_workers'"),
    (["--dataset-param", "noise_m=1e300"], "'noise_m' of dataset 'synthetic' must be >= 0 and <= 10"),
])
def test_numeric_plugin_settings_are_range_checked_up_front(tmp_path, params, needle, user_error):
    out = tmp_path / "out"
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--dataset-param", "n_samples=1",
                           "--attacks", "none", "--budgets", "1", "--quiet", "--out", str(out),
                           *params])
    user_error(res, needle)
    assert not out.exists()


# -- KITTI: rigid poses, content-keyed cache, ranges, implausible coordinates ----------------------
@pytest.fixture(scope="module")
def kitti_root(tmp_path_factory) -> Path:
    from test_kitti_boreas import _sensor_poses, _write_kitti

    root = tmp_path_factory.mktemp("kitti")
    _write_kitti(root, _sensor_poses(0.3))
    return root


def _kitti_copy(kitti_root: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "k"
    shutil.copytree(kitti_root, dst)
    return dst


def test_kitti_refuses_poses_and_calibration_that_are_not_rigid(kitti_root, tmp_path):
    from icpbench.datasets.kitti import KittiDataset

    root = _kitti_copy(kitti_root, tmp_path)
    poses = root / "poses" / "00.txt"
    lines = poses.read_text().splitlines()
    vals = [float(v) for v in lines[2].split()]
    for i in (0, 1, 2, 4, 5, 6, 8, 9, 10):  # the rotation block, scaled by 2
        vals[i] *= 2
    poses.write_text("\n".join([*lines[:2], " ".join(map(str, vals)), *lines[3:]]) + "\n")
    with pytest.raises(InputError, match=r"00.txt:3: pose is not a rigid transform"):
        KittiDataset(root, "00")
    poses.write_text("\n".join(lines) + "\n")
    calib = root / "sequences" / "00" / "calib.txt"
    calib.write_text("Tr: " + " ".join(["0"] * 12) + "\n")
    with pytest.raises(InputError, match=r"calib.txt:1: Tr is not a rigid transform"):
        KittiDataset(root, "00")


def test_kitti_cache_is_keyed_on_file_contents(kitti_root, tmp_path):
    from icpbench.datasets.kitti import KittiDataset

    root = _kitti_copy(kitti_root, tmp_path)
    kw = dict(stride=5, window=1, n_points=500, cache_dir=tmp_path / "cache")
    before = KittiDataset(root, "00", **kw)[0]
    scan = root / "sequences" / "00" / "velodyne" / "000000.bin"
    st = scan.stat()
    data = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
    data[:, :3] += np.float32(0.5)  # same size; the old modification time is put back (cp -p)
    data.tofile(scan)
    os.utime(scan, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = KittiDataset(root, "00", **kw)[0]
    assert not np.array_equal(before.scan, after.scan)


@pytest.mark.parametrize(("param", "needle"), [
    ({"offset_trans_m": float("nan")}, "setting 'offset_trans_m' of dataset 'kitti' must be a finite"),
    ({"offset_rot_deg": float("inf")}, "setting 'offset_rot_deg' of dataset 'kitti' must be a finite"),
    ({"n_points": 0}, "setting 'n_points' of dataset 'kitti' must be >= 6, got 0"),
    ({"n_points": -5}, "setting 'n_points' of dataset 'kitti' must be >= 6, got -5"),
    ({"map_voxel_m": 0.0}, "setting 'map_voxel_m' of dataset 'kitti' must be > 0"),
])
def test_kitti_settings_are_range_checked(kitti_root, param, needle):
    from icpbench.datasets.kitti import KittiDataset

    with pytest.raises(InputError, match=re.escape(needle)):
        KittiDataset(kitti_root, "00", **param)


def test_kitti_scan_with_absurd_coordinates_names_the_file(kitti_root, tmp_path):
    from icpbench.datasets.kitti import KittiDataset

    root = _kitti_copy(kitti_root, tmp_path)
    scan = root / "sequences" / "00" / "velodyne" / "000000.bin"
    data = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
    data[:10, :3] = np.float32(1e30)
    data.tofile(scan)
    ds = KittiDataset(root, "00", stride=5, window=1, cache_dir=tmp_path / "cache")
    with pytest.raises(InputError, match=r"000000.bin is corrupt: 10 point\(s\) have a coordinate"):
        ds[0]


# -- resumed runs keep each row's software; partial grids are announced --------------------------------
def test_a_resume_with_other_software_keeps_the_old_rows_provenance(tmp_path, monkeypatch):
    import icpbench.harness.runner as runner
    from icpbench.harness.report import table1
    from icpbench.harness.results import load_results, read_manifest

    cfg = dict(SYN, attacks=["none"], budgets=[0.5])
    run(RunConfig(**cfg, samples=1), tmp_path, progress=False)
    first = read_manifest(tmp_path)
    real = runner.package_versions
    monkeypatch.setattr(runner, "package_versions", lambda: {**real(), "torch": "0.0-other"})
    run(RunConfig(**cfg, samples=2), tmp_path, progress=False)
    m = read_manifest(tmp_path)
    assert m["versions"] == first["versions"] and m["git"] == first["git"]
    assert [e["rows_from"] for e in m["provenance"]] == [0, 1]
    assert m["provenance"][1]["versions"]["torch"] == "0.0-other"
    text = table1(load_results(tmp_path), reference="none")
    assert "written by 2 different software versions or commits" in text


def test_a_resume_that_computes_nothing_leaves_the_manifest_as_it_was(tmp_path):
    """Rewriting a board resumes every run folder; one that appends no row must keep the
    execution settings and provenance of the runs that made its rows."""
    from icpbench.harness.results import read_manifest

    cfg = dict(SYN, attacks=["none"], budgets=[0.5], samples=2)
    run(RunConfig(**cfg, executor="processes"), tmp_path, progress=False)
    made = (tmp_path / "manifest.json").read_text()
    run(RunConfig(**cfg), tmp_path, progress=False)  # local executor, nothing to compute
    assert (tmp_path / "manifest.json").read_text() == made
    run(RunConfig(**{**cfg, "samples": 3}), tmp_path, progress=False)  # one more scan
    m = read_manifest(tmp_path)
    assert m["config"]["executor"] == "local" and [e["rows_from"] for e in m["provenance"]] == [0, 2]


def test_a_script_resuming_its_row_log_keeps_the_commit_that_made_the_old_rows(tmp_path):
    """The row logs of ``scripts/`` (e.g. the replica agreement) resume: a later commit appending
    rows must not relabel the earlier ones, and rows without a manifest are refused."""
    from icpbench.harness.outputs import write_json
    from icpbench.harness.report import provenance_notes
    from icpbench.harness.results import commits_of, resume_provenance, row_makers

    def made_by(commit):
        return {"versions": {"torch": "2"}, "git": {"commit": commit, "dirty": False},
                "platform": {"machine": "x86_64"}}

    # a fresh folder (or one whose log is empty) is labelled with the code that runs now
    assert resume_provenance(tmp_path, "rows.csv", made_by("bbb"))["git"]["commit"] == "bbb"
    (tmp_path / "rows.csv").write_text("a,b\n1,2\n3,4\n")
    with pytest.raises(InputError, match="holds 2 rows but .* no manifest.json"):
        resume_provenance(tmp_path, "rows.csv", made_by("bbb"))
    # a manifest written before provenance was kept (only ``git``): its rows keep that commit
    write_json(tmp_path / "manifest.json", {"git": {"commit": "aaa", "dirty": False},
                                            "versions": {"torch": "2"}})
    m = resume_provenance(tmp_path, "rows.csv", made_by("bbb"))
    assert m["git"]["commit"] == "aaa"
    assert [(e["rows_from"], e["git"]["commit"]) for e in m["provenance"]] == [(0, "aaa"),
                                                                              (2, "bbb")]
    write_json(tmp_path / "manifest.json", m)
    (tmp_path / "rows.csv").write_text("a,b\n1,2\n3,4\n5,6\n")
    m = resume_provenance(tmp_path, "rows.csv", made_by("ccc"))
    assert [e["rows_from"] for e in m["provenance"]] == [0, 2, 3] and m["git"]["commit"] == "aaa"
    write_json(tmp_path / "manifest.json", m)  # ccc appended nothing: it made no row
    assert commits_of(row_makers(tmp_path, "rows.csv")) == ["aaa", "bbb"]
    rows = pd.DataFrame({"a": [1, 3, 5]})
    rows.attrs["provenance"] = m["provenance"]
    assert "written by 3 different software versions or commits" in provenance_notes(rows)[0]
    rows.attrs["provenance"] = m["provenance"][:1]
    assert provenance_notes(rows) == []


def test_the_scripts_with_row_logs_record_provenance_instead_of_the_current_commit():
    """No results script labels rows with ``git_commit()`` of the tree that merely resumed them."""
    root = Path(__file__).resolve().parent.parent
    for name in ("replica_agreement.py", "clean_convergence.py"):
        text = (root / "scripts" / name).read_text()
        assert "git_commit" not in text and "provenance" in text, name


def test_table_of_an_interrupted_or_running_run_says_the_grid_is_incomplete(tmp_path, tiny_run):
    from icpbench.harness.report import table1
    from icpbench.harness.results import load_results, lock_results_dir

    def stop(done: int) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(RunConfig(**SYN, attacks=["none", "uniform"], budgets=[0.5, 1.0], samples=2,
                      batch_size=1), tmp_path, progress=False, on_unit=stop)
    text = table1(load_results(tmp_path), reference="uniform")
    assert "did not finish" in text and "the grid is incomplete: 3 of 4 rows" in text
    done = tmp_path / "done"
    shutil.copytree(tiny_run, done)
    assert "warning: the grid" not in table1(load_results(done), reference="uniform")
    with lock_results_dir(done):
        assert "a run is still writing to this folder" in table1(load_results(done),
                                                                 reference="uniform")


def test_a_corrupt_manifest_is_not_answered_with_delete_it(tiny_run, tmp_path, user_error):
    run_dir = tmp_path / "r"
    shutil.copytree(tiny_run, run_dir)
    (run_dir / "manifest.json").write_text("{not json")
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--attacks", "none", "--budgets", "1",
                           "--out", str(run_dir), "--quiet"])
    user_error(res, "use a new --out")
    assert "delete it" not in res.output


def test_ctrl_c_before_any_result_does_not_claim_saved_work(tmp_path, monkeypatch):
    import icpbench.harness.runner as runner

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "run", interrupted)
    out = tmp_path / "never"
    res = cli.invoke(app, ["run", "--dataset", "synthetic", "--attacks", "none", "--budgets", "1",
                           "--out", str(out), "--quiet"])
    assert res.exit_code == 130 and "Traceback" not in res.output
    assert "interrupted before any result was saved" in res.output
    assert "saved in" not in res.output and not out.exists()


def test_an_attack_without_a_checkpoint_fails_the_command_and_is_retried(tmp_path):
    from icpbench.harness.results import ResultsStore, load_results

    out = tmp_path / "out"
    args = ["run", "--dataset", "synthetic", "--dataset-param", "n_samples=1", "--dataset-param",
            "n_scan=100", "--dataset-param", "n_map=1000", "--attacks", "none,generator",
            "--budgets", "1", "--out", str(out), "--quiet"]
    res = cli.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "error: attack generator did not run on any sample: CheckpointError: no shipped " \
           "generator checkpoint for dataset 'synthetic'" in res.output
    row = load_results(out).query("attack == 'generator'").iloc[0]
    key = (row["sample_id"], "generator", row["target"], 1.0, 0)
    assert not ResultsStore(out).has(key)  # not final: the next run computes it again


@pytest.mark.parametrize("content", [b"", b"v 0 0 0\nv 1 0"])  # empty, truncated
def test_an_empty_mesh_file_is_skipped_like_a_truncated_one(tmp_path, content):
    from test_defects import _write_meshes

    from icpbench.harness.results import load_results

    folder = tmp_path / "meshes"
    _write_meshes(folder, 3)
    (folder / "box1.obj").write_bytes(content)
    cfg = RunConfig(dataset="meshes", attacks=["none"], targets=["p2plane"], budgets=[0.05],
                    dataset_params={"root": str(folder), "test_fraction": 1.0,
                                    "n_map_points": 2000, "n_scan_points": 300})
    run(cfg, tmp_path / "o", progress=False)
    df = load_results(tmp_path / "o")
    assert list(df.loc[df["status"] == "error", "sample_id"]) == ["meshes/box1"]
    assert len(df) == 3


# -- checkpoint messages name the real problem -----------------------------------------------------------
def test_checkpoint_messages_name_the_device_and_the_refused_pickle(tmp_path):
    import pickle

    from icpbench.core.errors import CheckpointError
    from icpbench.learning.checkpoint import load_checkpoint, save_checkpoint
    from icpbench.learning.network import Generator, generator_config

    good = tmp_path / "g.pt"
    save_checkpoint(Generator(generator_config("objects")), good)
    if not torch.cuda.is_available():
        with pytest.raises(CheckpointError, match="CUDA is not available on this machine"):
            load_checkpoint(good, map_location="cuda")
    evil = tmp_path / "evil.pt"
    evil.write_bytes(pickle.dumps(print))  # a plain pickle that names a callable
    shutil.copy(tmp_path / "g.json", tmp_path / "evil.json")
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(evil)
    msg = str(info.value)
    assert "it may be a pickle that carries code" in msg and "weights_only=False" not in msg


@pytest.mark.parametrize("kind", ["targets", "attacks", "datasets"])
def test_every_plugin_declares_a_range_for_each_numeric_setting(kind):
    """Every numeric setting of every target, attack and dataset has a declared range, so an
    out-of-range number is refused up front, naming it (e.g. ``--dataset-param car_change=2``)."""
    import typing

    from icpbench.core import registry

    reg = getattr(registry, kind)
    for name in reg.names():
        if not reg.available(name)[0]:
            continue
        cls = reg.get(name)
        ranges = getattr(cls, "param_ranges", {}) or {}
        for key, hint in cls.param_types().items():
            if (set(typing.get_args(hint)) | {hint}) & {int, float}:
                assert key in ranges, (name, key)


@pytest.mark.parametrize("kind,name,params,needle", [
    ("attacks", "search", {"queries": 0}, "queries"),
    ("datasets", "lidar-sim", {"car_change": 2.0}, "car_change"),
    ("targets", "p2plane", {"tol": float("inf")}, "tol"),
])
def test_an_out_of_range_setting_is_refused_naming_it(kind, name, params, needle):
    from icpbench.core import registry

    with pytest.raises(InputError, match=needle):
        getattr(registry, kind).check_params(name, params)

