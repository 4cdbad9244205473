""""Attack your own map" end to end on files: a tiny KITTI-layout sequence (ray-cast from a lidar-sim
town with a 64-beam sensor into .bin / calib.txt / poses.txt), then the commands a user runs on
their own recordings: ``icpbench train --dataset kitti --dataset-param root=...``, ``icpbench run``
and ``icpbench map`` on the same folder, and fine-tuning the shipped lidar-sim generator on it
(``--init``). Sizes are tiny (10 sweeps, 4 samples of 4096 points, one epoch of two steps).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch
from typer.testing import CliRunner

from icpbench.attacks.generator import shipped_checkpoint_dir
from icpbench.cli import app
from icpbench.datasets.kitti import KittiDataset, read_kitti_bin
from icpbench.datasets.kitti_export import write_kitti_sequence
from icpbench.datasets.lidar_sim import LidarSimDataset
from icpbench.learning.checkpoint import load_checkpoint

torch.set_num_threads(1)
pytestmark = pytest.mark.slow

#: --dataset-param settings of the tiny sequence: a sample every 3rd sweep, submaps of +-3 sweeps.
KITTI = ["--dataset", "kitti", "--dataset-param", "stride=3", "--dataset-param", "window=3",
         "--dataset-param", "n_points=4096"]
runner = CliRunner()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The KITTI-layout folder and the cache folder (ICPBENCH_CACHE) of the module."""
    root = tmp_path_factory.mktemp("my-recording")
    cache = tmp_path_factory.mktemp("cache")
    town = LidarSimDataset(town_seed=3, sensor="hdl64", route_scale=0.3, cache_dir=cache,
                           lidar={"h_res_deg": 0.35})
    s0 = next(a for a, _, p in town.route.intervals() if p == "suburb") + 10.0
    write_kitti_sequence(town, root, s_start_m=s0, n_frames=10, spacing_m=2.0)
    return root, cache


def _cli(args: list[str], cache, monkeypatch) -> str:
    monkeypatch.setenv("ICPBENCH_CACHE", str(cache))
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output + repr(res.exception)
    return res.output


def test_the_files_follow_the_kitti_layout_and_localise(recording):
    from icpbench.core.se3 import pose_error_components
    from icpbench.core.types import Batch
    from icpbench.targets.p2plane import PointToPlaneICP

    root, cache = recording
    bins = sorted((root / "sequences" / "00" / "velodyne").glob("*.bin"))
    assert [b.name for b in bins[:2]] == ["000000.bin", "000001.bin"] and len(bins) == 10
    assert bins[0].stat().st_size % 16 == 0 and len(read_kitti_bin(bins[0])) > 50_000  # 64 beams
    assert (root / "sequences" / "00" / "calib.txt").read_text().count("Tr:") == 1
    assert len((root / "poses" / "00.txt").read_text().splitlines()) == 10
    ds = KittiDataset(root, stride=3, window=3, n_points=4096, cache_dir=cache)
    assert len(ds) == 4
    # the loader recovers the drive: 2 m per sweep along the lidar's x axis
    step = np.linalg.norm(np.diff(ds.T_velo[:, :3, 3], axis=0), axis=1)
    assert np.allclose(step, 2.0, atol=0.05)
    batch = Batch.from_samples(ds.take(4))
    reg = PointToPlaneICP("lidar").register(batch.scans, batch.maps, batch.T_init)
    err = pose_error_components(reg.T, batch.T_gt)["trans_err"]
    assert bool(reg.converged.all()) and float(err.median()) < 0.05


def test_train_run_map_and_fine_tune_on_the_recording(recording, tmp_path, monkeypatch):
    root, cache = recording
    data = [*KITTI, "--dataset-param", f"root={root}"]
    small = ["--train-samples", "4", "--eval-samples", "2", "--epochs", "1", "--batch-size", "2",
             "--quiet"]
    # 1. train a generator for this map
    out = _cli(["train", "--preset", "quick-lidar", *data, *small, "--budgets", "1",
                "--out", str(tmp_path / "train")], cache, monkeypatch)
    ckpt = tmp_path / "train" / "generator.pt"
    assert ckpt.is_file() and "held-out λ=1" in out
    card = load_checkpoint(ckpt).card
    assert card["data"]["dataset"] == "kitti" and card["heldout_eval"]["1"]["samples"] == 2
    history = pd.read_csv(tmp_path / "train" / "history.csv")
    assert len(history) == 1 and np.isfinite(history["loss"]).all()
    # 2. Table 1 on the recording with that generator
    _cli(["run", *data, "--attacks", "none,uniform,generator", "--budgets", "1",
          "--attack-param", f"generator.checkpoint={ckpt}", "--out", str(tmp_path / "run"),
          "--quiet"], cache, monkeypatch)
    df = pd.read_csv(tmp_path / "run" / "results.csv")
    assert set(df["attack"]) == {"none", "uniform", "generator"}
    assert (df.groupby("attack")["sample_id"].nunique() == 4).all()
    clean = df[df["attack"] == "none"]
    assert clean["converged"].all() and clean["trans_err"].median() < 0.05
    uni = df[(df["attack"] == "uniform") & df["converged"]]["trans_err_xy"]
    assert abs(uni.mean() - 1.0) < 0.1  # the pipeline follows a 1 m shift of the whole scan
    gen = df[df["attack"] == "generator"]
    assert len(gen) == 4 and (gen["disp_max"] <= 1.0 + 1e-6).all()  # bounded output: within λ
    # 3. the danger map of the recording
    _cli(["map", *data, "--attack", "generator", "--budget", "1",
          "--attack-param", f"generator.checkpoint={ckpt}", "--out", str(tmp_path / "map"),
          "--quiet"], cache, monkeypatch)
    summary = json.loads((tmp_path / "map" / "summary.json").read_text())
    assert summary["generator"]["locations"] == 4
    assert (tmp_path / "map" / "generator_map.png").stat().st_size > 10_000
    # 4. fine-tune the shipped lidar-sim generator on the recording
    shipped = shipped_checkpoint_dir("lidar-sim") / "generator.pt"
    _cli(["train", "--preset", "quick-lidar", *data, *small, "--budgets", "1,3",
          "--init", str(shipped), "--out", str(tmp_path / "tuned")], cache, monkeypatch)
    tuned = load_checkpoint(tmp_path / "tuned" / "generator.pt")
    assert tuned.card["init_checkpoint"] == str(shipped)
    before = load_checkpoint(shipped).model.state_dict()
    moved = [k for k, v in tuned.model.state_dict().items()
             if v.dtype.is_floating_point and not torch.equal(v, before[k])]
    assert moved, "fine-tuning did not change the weights"
