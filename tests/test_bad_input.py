"""Bad input gets a clear error (an ``InputError``/``CheckpointError`` whose message names the
problem) or a flagged row, never a traceback or a silent NaN: at the library boundary (samples,
maps, targets, attacks, files, registry, run configs) and in the CLI (exit status 2, one line).

One test per kind of bad input; the last test drives every kind through the CLI.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from icpbench.attacks.base import Attack, validate_budget
from icpbench.attacks.generator import GeneratorAttack
from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.cli import app
from icpbench.core import registry
from icpbench.core.errors import CheckpointError, InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Batch, Sample
from icpbench.datasets.base import Dataset
from icpbench.datasets.kitti import read_kitti_bin
from icpbench.datasets.meshes import read_mesh
from icpbench.harness.report import table1
from icpbench.harness.results import load_results
from icpbench.harness.runner import RunConfig, run
from icpbench.learning.checkpoint import load_checkpoint, save_checkpoint
from icpbench.learning.network import Generator, generator_config
from icpbench.targets.open3d_icp import Open3DICP
from icpbench.targets.p2plane import PointToPlaneICP
from icpbench.targets.p2point import PointToPointICP

torch.set_num_threads(1)
RNG = np.random.default_rng(0)
P2PLANE = PointToPlaneICP("lidar", max_iterations=20)


def _unit(m: int) -> np.ndarray:
    n = RNG.normal(size=(m, 3))
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _sample(scan=None, map_=None, normals="unit", sid="s0") -> Sample:
    map_ = RNG.normal(size=(200, 3)) if map_ is None else map_
    normals = _unit(len(map_)) if isinstance(normals, str) else normals
    scan = RNG.normal(size=(100, 3)) if scan is None else scan
    return Sample(sid, scan, map_, normals, np.eye(4))


def _register(target, scan: np.ndarray, map_: np.ndarray, normals: np.ndarray | None):
    maps = [MapIndex(map_, normals)] if target.differentiable else [target.prepare(map_, normals)]
    return target.register(torch.as_tensor(scan[None]), maps, torch.eye(4, dtype=torch.float64)[None])


def _assert_flagged(reg, *statuses: str) -> None:
    """A registration that did not crash, has a finite pose, and says why it is not trustworthy."""
    assert bool(torch.isfinite(reg.T).all())
    assert reg.status[0] in statuses, reg.status
    assert not bool(reg.converged[0])


PLANE = np.c_[RNG.uniform(-5, 5, (400, 2)), np.zeros(400)]
PLANE_NORMALS = np.tile([0.0, 0.0, 1.0], (400, 1))


# -- scans and maps -------------------------------------------------------------------------------
def test_empty_scan():
    with pytest.raises(InputError, match=r"sample 's0': scan is empty \(0 points\)"):
        _sample(scan=np.zeros((0, 3))).validate()
    with pytest.raises(InputError, match="map must be a non-empty"):
        MapIndex(np.zeros((0, 3)))
    _assert_flagged(_register(P2PLANE, np.zeros((0, 3)), PLANE, PLANE_NORMALS),
                    "too_few_correspondences")


def test_fewer_than_six_points():
    with pytest.raises(InputError, match="scan has 5 points; at least 6 are needed"):
        _sample(scan=RNG.normal(size=(5, 3))).validate()
    with pytest.raises(InputError, match="map has 3 points; at least 6"):
        Open3DICP("lidar").prepare(RNG.normal(size=(3, 3)), _unit(3))
    _assert_flagged(_register(P2PLANE, PLANE[:3] + 0.1, PLANE, PLANE_NORMALS),
                    "too_few_correspondences", "singular")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_coordinates(bad, tmp_path):
    scan = RNG.normal(size=(100, 3))
    scan[[3, 7], 1] = bad
    with pytest.raises(InputError, match=r"scan has 2 point\(s\) with NaN or Inf coordinates"):
        _sample(scan=scan).validate()
    map_ = RNG.normal(size=(50, 3))
    map_[0, 0] = bad
    with pytest.raises(InputError, match=r"map has 1 point\(s\) with NaN or Inf"):
        _sample(map_=map_).validate()
    with pytest.raises(InputError, match="map has NaN or Inf coordinates"):
        MapIndex(map_)
    # at the target: non-finite scan points are ignored, never spread into the pose
    scan = PLANE[:100] + [0.2, 0.1, 0.0]
    scan[:5] = bad
    reg = _register(PointToPointICP("lidar"), scan, PLANE, None)
    assert bool(torch.isfinite(reg.T).all()) and abs(float(reg.inlier_fraction[0]) - 0.95) < 1e-9
    _assert_flagged(_register(P2PLANE, np.full((50, 3), bad), PLANE, PLANE_NORMALS),
                    "too_few_correspondences")


class _NaNAttack(Attack):
    name = "nan-test-attack"

    def _perturb(self, batch, budget_m, *, surrogate, generator):
        out = batch.scans.clone()
        out[:, 0] = float("nan")
        return out


def test_an_attack_returning_nan_gives_error_rows_not_nan_rows(tmp_path):
    registry.attacks.register("nan-test-attack", _NaNAttack)
    try:
        run(RunConfig(dataset="synthetic", attacks=["nan-test-attack", "none"], targets=["p2plane"],
                      budgets=[1.0], samples=2, dataset_params={"n_samples": 2}), tmp_path,
            progress=False)
    finally:
        registry.attacks.unregister("nan-test-attack")
    df = load_results(tmp_path)
    bad = df[df["attack"] == "nan-test-attack"]
    assert (bad["status"] == "error").all() and not bad["converged"].any()
    assert bad["error"].str.contains(r"returned 2 point\(s\) with NaN or Inf coordinates").all()
    ok = df[df["attack"] == "none"]
    assert ok[["trans_err_xy", "disp_max"]].notna().all().all()


def test_duplicated_points():
    one = np.repeat(RNG.normal(size=(1, 3)), 50, axis=0)
    with pytest.raises(InputError, match=r"scan has only 1 distinct point\(s\) among 50"):
        _sample(scan=one).validate()
    five = np.repeat(RNG.normal(size=(5, 3)), 40, axis=0)
    with pytest.raises(InputError, match=r"map has only 5 distinct point\(s\) among 200"):
        _sample(map_=five).validate()
    six = np.repeat(RNG.normal(size=(6, 3)), 20, axis=0)  # duplicates are fine beyond that
    _sample(scan=six).validate()
    _assert_flagged(_register(P2PLANE, np.repeat(PLANE[:1], 50, 0), PLANE, PLANE_NORMALS),
                    "singular")


@pytest.mark.parametrize("geometry", ["planar", "collinear"])
def test_planar_and_collinear_geometry_is_regularised_and_flagged(geometry):
    if geometry == "planar":
        map_, normals = PLANE, PLANE_NORMALS
    else:
        t = RNG.uniform(-5, 5, 300)
        map_ = np.c_[t, 0.3 * t, np.zeros_like(t)]
        normals = np.tile([0.0, 0.0, 1.0], (300, 1))
    scan = map_[:150] + [0.3, -0.2, 0.05]
    targets = [P2PLANE, Open3DICP("lidar", max_iterations=20)]
    if geometry == "collinear":
        # point-to-point's own system is full rank for planar clouds (fixed correspondences pin
        # every in-plane direction), so only a line is singular for it
        targets.append(PointToPointICP("lidar", max_iterations=20))
    for target in targets:
        _assert_flagged(_register(target, scan, map_, normals), "singular")


class _PlanarDataset(Dataset):
    """Flat ground only: x, y and yaw are unobservable for point-to-plane ICP."""

    name = "planar-test"
    icp_preset = "lidar"

    def __len__(self) -> int:
        return 3

    def __getitem__(self, i: int) -> Sample:
        rng = np.random.default_rng(i)
        ground = np.c_[rng.uniform(-20, 20, (3000, 2)), rng.normal(0, 0.01, 3000)]
        return Sample(f"planar/{i}", ground[:1000] + [0.2, 0.1, 0.0], ground,
                      np.tile([0.0, 0.0, 1.0], (3000, 1)), np.eye(4))


def test_singular_samples_become_flagged_rows_and_a_table_warning(tmp_path):
    registry.datasets.register("planar-test", _PlanarDataset)
    try:
        run(RunConfig(dataset="planar-test", attacks=["none", "uniform"], targets=["p2plane"],
                      budgets=[1.0], samples=3), tmp_path, progress=False)
    finally:
        registry.datasets.unregister("planar-test")
    df = load_results(tmp_path)
    assert len(df) == 6 and (df["status"] == "singular").all() and not df["converged"].any()
    assert df[["trans_err_xy", "rot_err"]].notna().all().all()  # numbers kept, flagged
    text = table1(df, "md", reference="uniform")
    assert "warning: none on p2plane at λ=1: 100% of 3 samples not converged/failed (singular: 3)" in text


def test_mismatched_dtype_or_shape():
    with pytest.raises(InputError, match="scan must be a floating-point array, got dtype int64"):
        _sample(scan=np.ones((100, 3), dtype=np.int64)).validate()
    with pytest.raises(InputError, match=r"map must have shape \(K, 3\), got \(200, 2\)"):
        _sample(map_=RNG.normal(size=(200, 2)), normals=_unit(200)).validate()
    with pytest.raises(InputError, match=r"map_normals has shape \(199, 3\), expected \(200, 3\)"):
        _sample(normals=_unit(199)).validate()
    with pytest.raises(InputError, match=r"share the scan size N, got \[90, 100\]"):
        Batch.from_samples([_sample(), _sample(scan=RNG.normal(size=(90, 3)))])
    mi = MapIndex(PLANE, PLANE_NORMALS)
    eye = torch.eye(4, dtype=torch.float64)[None]
    with pytest.raises(InputError, match=r"scans must have shape \(B, N, 3\), got \(1, 100, 2\)"):
        P2PLANE.register(torch.zeros(1, 100, 2, dtype=torch.float64), [mi], eye)
    with pytest.raises(InputError, match="got 2 maps for a batch of 1 scans"):
        P2PLANE.register(torch.zeros(1, 100, 3, dtype=torch.float64), [mi, mi], eye)
    with pytest.raises(InputError, match=r"T_init must have shape \(1, 4, 4\), got \(1, 3, 3\)"):
        P2PLANE.register(torch.zeros(1, 100, 3, dtype=torch.float64), [mi], eye[:, :3, :3])
    with pytest.raises(InputError, match="scans must be floating point, got torch.int64"):
        P2PLANE.register(torch.zeros(1, 100, 3, dtype=torch.int64), [mi], eye)
    # float32 scan + float64 map is not an error: it is converted, with the same answer
    s = _sample()
    s32 = Sample("s32", s.scan.astype(np.float32), s.map, s.map_normals, s.T_gt)
    s32.validate()
    T64 = P2PLANE.register(Batch.from_samples([s]).scans, [MapIndex(s.map, s.map_normals)], eye).T
    T32 = P2PLANE.register(torch.as_tensor(s32.scan[None]), [MapIndex(s.map, s.map_normals)], eye).T
    assert T32.dtype == torch.float32 and float((T32.double() - T64).abs().max()) < 1e-4


def test_map_without_usable_normals():
    with pytest.raises(InputError, match="sample 's0': map has no normals; estimate them"):
        Sample("s0", RNG.normal(size=(50, 3)), RNG.normal(size=(80, 3)), None, np.eye(4)).validate()
    with pytest.raises(InputError, match="map has no usable normals .*estimate_normals"):
        _sample(normals=np.zeros((200, 3))).validate()
    with pytest.raises(InputError, match="point-to-plane ICP needs map normals"):
        _register(P2PLANE, PLANE[:100], PLANE, None)
    with pytest.raises(InputError, match="Open3D point-to-plane needs map normals"):
        Open3DICP("lidar").prepare(PLANE, None)
    # zero normals that bypass validation give an all-zero system: flagged, not NaN
    _assert_flagged(_register(P2PLANE, PLANE[:100] + 0.1, PLANE, np.zeros_like(PLANE)), "singular")


# -- files ----------------------------------------------------------------------------------------
def _obj(path: Path) -> Path:
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    return path


@pytest.mark.parametrize("problem, needle", [
    ("missing", "does not exist"), ("empty", r"is empty \(0 bytes\)"),
    ("truncated", "truncated or corrupt"), ("corrupt", "gave no triangles"),
])
def test_missing_empty_truncated_or_corrupt_mesh_file(tmp_path, problem, needle):
    path = _obj(tmp_path / "m.obj")
    assert read_mesh(path)[1].shape == (4, 3)
    if problem == "missing":
        path.unlink()
    elif problem == "empty":
        path.write_bytes(b"")
    elif problem == "truncated":
        path.write_bytes(path.read_bytes()[:-5])  # cut inside the last face line
    else:
        path.write_bytes(b"\x00\x17\xff garbage \x01" * 20)
    with pytest.raises(InputError, match=rf"m\.obj.*{needle}|{needle}.*m\.obj"):
        read_mesh(path)


@pytest.mark.parametrize("problem, needle", [
    ("missing", "missing KITTI scan"), ("empty", r"is empty \(0 bytes\)"),
    ("truncated", "not a multiple of 16 .*truncated"), ("corrupt", r"corrupt: 1 point\(s\) have NaN"),
])
def test_missing_empty_truncated_or_corrupt_point_cloud_file(tmp_path, problem, needle):
    path = tmp_path / "000000.bin"
    pts = np.c_[RNG.normal(size=(10, 3)), np.ones(10)].astype("<f4")
    pts.tofile(path)
    assert read_kitti_bin(path).shape == (10, 3)
    if problem == "missing":
        path.unlink()
    elif problem == "empty":
        path.write_bytes(b"")
    elif problem == "truncated":
        path.write_bytes(path.read_bytes()[:-6])
    else:
        pts[4, 2] = np.nan
        pts.tofile(path)
    with pytest.raises(InputError, match=needle):
        read_kitti_bin(path)


# -- names, budgets, checkpoints ------------------------------------------------------------------
@pytest.mark.parametrize("kind, field", [("attack", "attacks"), ("target", "targets"),
                                         ("dataset", "dataset"), ("target", "surrogate")])
def test_unknown_names_list_the_valid_ones(kind, field):
    value = "nope" if field in ("dataset", "surrogate") else ["nope"]
    cfg = RunConfig(**{"dataset": "synthetic", field: value})
    with pytest.raises(InputError, match=rf"unknown {kind} 'nope'; valid {kind}s: .*"):
        cfg.validate()
    valid = getattr(registry, f"{kind}s").names()
    with pytest.raises(InputError) as err:
        cfg.validate()
    assert all(name in str(err.value) for name in valid)


@pytest.mark.parametrize("budget", [-1.0, 0.0, float("nan"), float("inf"), "abc", None])
def test_negative_zero_or_nan_budget(budget):
    with pytest.raises(InputError, match="budget must be a"):
        validate_budget(budget)
    with pytest.raises(InputError, match="budget must be a"):
        UniformTranslationAttack().run(Batch.from_samples([_sample()]), budget)
    with pytest.raises(InputError, match="budget must be a"):
        RunConfig(dataset="synthetic", budgets=[1.0, budget]).validate()


class _Evil:
    """Any custom class: a pickle holding it is refused by weights_only loading."""


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    d = tmp_path_factory.mktemp("ckpt")
    good = save_checkpoint(Generator(generator_config("objects")), d / "good.pt")
    meta = json.loads(good.with_suffix(".json").read_text())
    out = {"good": good}
    out["truncated"] = d / "truncated.pt"
    out["truncated"].write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    other = save_checkpoint(Generator(generator_config("objects", conditioned=True)), d / "o.pt")
    out["architecture"] = d / "architecture.pt"
    out["architecture"].write_bytes(other.read_bytes())  # conditioned weights, unconditioned JSON
    out["pickle"] = d / "pickle.pt"
    torch.save({"weights": torch.zeros(3), "payload": _Evil()}, out["pickle"])
    for k in ("truncated", "architecture", "pickle"):
        out[k].with_suffix(".json").write_text(json.dumps(meta))
    out["missing"] = d / "missing.pt"
    return out


CHECKPOINT_ERRORS = [
    ("missing", "generator checkpoint not found: .*missing.pt"),
    ("truncated", "truncated.pt is truncated or corrupt"),
    ("architecture", "different architecture or config"),
    ("pickle", r"pickle.pt holds Python objects that safe loading \(torch.load weights_only=True\) "
               r"refuses .*_Evil"),
]


@pytest.mark.parametrize("which, needle", CHECKPOINT_ERRORS)
def test_bad_checkpoint(checkpoints, which, needle):
    assert load_checkpoint(checkpoints["good"]).config.conditioned is False
    with pytest.raises(CheckpointError, match=needle):
        load_checkpoint(checkpoints[which])
    # the attack checks an explicit checkpoint when it is built, i.e. before a run starts
    with pytest.raises(CheckpointError, match=needle):
        GeneratorAttack(checkpoint=str(checkpoints[which]))


# -- the CLI: exit status 2 and one readable line --------------------------------------------------
cli = CliRunner()
RUN = ["run", "--dataset", "synthetic", "--samples", "1", "--quiet"]


def _cli_cases(tmp: Path, ckpt: dict) -> list[tuple[list[str], str]]:
    meshes = tmp / "meshes"
    meshes.mkdir()
    (meshes / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2")
    (tmp / "a-file").write_text("x")
    (tmp / "empty.csv").write_text("")
    generator = ["run", "--dataset", "objects", "--attacks", "generator", "--budgets", "0.05",
                 "--samples", "1", "--quiet", "--attack-param"]
    return [
        (RUN + ["--attacks", "nope"], "unknown attack 'nope'; valid attacks: "),
        (RUN + ["--targets", "nope"], "unknown target 'nope'; valid targets: "),
        (["run", "--dataset", "nope"], "unknown dataset 'nope'; valid datasets: "),
        (RUN + ["--surrogate", "nope"], "unknown target 'nope'; valid targets: "),
        (RUN + ["--executor", "nope"], "unknown executor 'nope'; valid executors: local, processes, ray"),
        (RUN + ["--budgets", "-1"], "budget must be a positive finite number"),
        (RUN + ["--budgets", "0"], "budget must be a positive finite number"),
        (RUN + ["--budgets", "nan"], "budget must be a positive finite number"),
        (RUN + ["--budgets", "1,x"], "budget must be a number, got 'x'"),
        (RUN + ["--seed", "x"], "seed must be an integer, got 'x'"),
        (RUN + ["--threads", "0"], "--threads must be an integer >= 1 and <= 1024, got 0"),
        (RUN + ["--target-param", "p2plane.bogus=1"],
         "unknown setting(s) 'bogus' for target 'p2plane'; valid: backprop, cauchy_c, "),
        (["run", "--dataset", "kitti"],
         "bad parameters for KittiDataset: missing 1 required positional argument: 'root'"),
        (["run", "--dataset", "objects", "--dataset-param", "bogus=1"],
         "unknown setting(s) 'bogus' for dataset 'objects'; valid: categories, "),
        (RUN + ["--out", str(tmp / "a-file")], "a-file"),
        (["run", "--dataset", "meshes", "--dataset-param", f"root={meshes}", "--dataset-param",
          "test_fraction=1", "--quiet", "--strict-files", "--out", str(tmp / "m")],
         "broken.obj is truncated"),
        (["run", "--dataset", "meshes", "--dataset-param", f"root={tmp / 'nowhere'}"],
         "mesh folder .* does not exist"),
        (["table", str(tmp / "empty.csv")], "empty.csv is empty or not a results CSV"),
        (["table", str(tmp / "nowhere")], "no results at"),
        *[(generator + [f"generator.checkpoint={ckpt[k]}", "--out", str(tmp / k)], needle)
          for k, needle in CHECKPOINT_ERRORS],
        (["train", "--icp-backprop", "bogus", "--out", str(tmp / "tb")],
         "--icp-backprop must be one of unrolled, implicit"),
        (["train", "--icp-preset", "bogus", "--out", str(tmp / "tp")], "unknown ICP preset 'bogus'"),
    ] + ([] if torch.cuda.is_available() else
         [(["train", "--device", "cuda", "--out", str(tmp / "t")], "sees no CUDA GPU")])


def test_cli_user_errors_exit_2_with_one_line(tmp_path, checkpoints):
    import re

    for args, needle in _cli_cases(tmp_path, checkpoints):
        res = cli.invoke(app, args)
        lines = [ln for ln in res.output.splitlines() if ln.strip()]
        assert res.exit_code == 2, (args, res.output, res.exception)
        assert len(lines) == 1 and lines[0].startswith("error: "), (args, res.output)
        assert re.search(needle, lines[0]) or needle in lines[0], (needle, lines[0])
