"""The README's third-party plugin example installs and runs through `icpbench run`."""

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.slow  # pip-installs the example and runs the CLI in subprocesses

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "icpbench-plugin-example"


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory):
    target = tmp_path_factory.mktemp("plugin-site")
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps",
                    "--no-build-isolation", "--target", str(target), str(EXAMPLE)],
                   check=True, capture_output=True)
    return target


def _env(plugin_path):
    return {**os.environ, "PYTHONPATH": f"{plugin_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def test_plugin_listed(plugin_path):
    out = subprocess.run([sys.executable, "-m", "icpbench.cli", "list"], capture_output=True,
                         text=True, env=_env(plugin_path), check=True).stdout
    assert "jitter" in out and "kabsch-icp" in out and "spread" in out


def test_plugin_monitor_scores_alike_in_numpy_and_torch_and_joins_a_monitored_run(plugin_path,
                                                                                 tmp_path):
    """The example monitor's differentiable score equals its score, and `icpbench run
    --monitors spread --monitor-aware` calibrates it and reports its alarms."""
    code = (
        "import numpy as np, torch\n"
        "from icpbench.core import registry\n"
        "from icpbench.core.mapindex import MapIndex\n"
        "from icpbench.monitors.base import MonitorInput\n"
        "from icpbench.monitors.differentiable import DiffInput\n"
        "m = registry.monitors.get('spread')()\n"
        "rng = np.random.default_rng(0)\n"
        "pts = rng.uniform(-5, 5, (2000, 3)); scan = pts[:500] + rng.normal(0, 0.05, (500, 3))\n"
        "T = np.eye(4); T[:3, 3] = [0.2, -0.1, 0.0]\n"
        "a = m.score(MonitorInput(scan=scan, map=MapIndex(pts), T_hat=T))\n"
        "b = float(m.differentiable_score(DiffInput(torch.tensor(scan), torch.tensor(T),"
        " MapIndex(pts))))\n"
        "assert abs(a - b) < 1e-12 and a > 0.05, (a, b)\n"
        "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=_env(plugin_path))
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr
    out = subprocess.run(
        [sys.executable, "-m", "icpbench.cli", "run", "--dataset", "synthetic", "--attacks",
         "none,uniform", "--targets", "p2plane", "--budgets", "0.5", "--samples", "3",
         "--monitors", "spread,odometry", "--false-alarm-rate", "0.1",
         "--calibration-samples", "10", "--monitor-aware", "--out", str(tmp_path), "--quiet"],
        capture_output=True, text=True, env=_env(plugin_path))
    assert out.returncode == 0, out.stderr
    df = pd.read_csv(tmp_path / "results.csv")
    assert df["extra"].str.contains("monitor_score.spread").all()


def test_plugin_runs_through_icpbench_run(plugin_path, tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "icpbench.cli", "run", "--dataset", "synthetic", "--attacks",
         "none,jitter,uniform", "--targets", "kabsch-icp,p2plane", "--budgets", "0.5",
         "--samples", "3", "--reference", "uniform", "--out", str(tmp_path), "--quiet"],
        capture_output=True, text=True, env=_env(plugin_path))
    assert out.returncode == 0, out.stderr
    assert "Table 1 (synthetic, target kabsch-icp)" in out.stdout
    df = pd.read_csv(tmp_path / "results.csv")
    assert set(df["attack"]) == {"none", "jitter", "uniform"}
    assert set(df["target"]) == {"kabsch-icp", "p2plane"}
    k = df[(df["target"] == "kabsch-icp") & (df["attack"] == "uniform")]
    # a whole-scan shift of 0.5 is recovered as a 0.5 error by any working ICP
    assert (k["trans_err_xy"] - 0.5).abs().max() < 0.1
    j = df[df["attack"] == "jitter"]
    assert (j["disp_max"] - 0.5).abs().max() < 1e-9


def test_plugin_target_joins_the_leaderboard(plugin_path, tmp_path):
    """README, "Put your ICP on the leaderboard": a third-party target is ranked beside p2plane;
    it has no replica, so the ensemble's PGD member is skipped on it (NaN), not faked."""
    out = subprocess.run(
        [sys.executable, "-m", "icpbench.cli", "leaderboard", "--add-target", "kabsch-icp",
         "--variants", "p2plane (Cauchy)", "--samples", "2", "--dataset", "synthetic",
         "--dataset-param", "n_scan=600", "--dataset-param", "n_map=6000", "--budgets", "0.5",
         "--ensemble-param", "queries=2", "--ensemble-param", "pgd_steps=1",
         "--ensemble-param", "sector_iterations=1", "--ensemble-param", "spoof_queries=2",
         "--ensemble-param", "valley_queries=2", "--out", str(tmp_path), "--quiet"],
        capture_output=True, text=True, env=_env(plugin_path))
    assert out.returncode == 0, out.stderr
    board = pd.read_csv(tmp_path / "leaderboard.csv")
    assert set(board["variant"]) == {"kabsch-icp", "p2plane (Cauchy)"}
    rows = pd.read_csv(tmp_path / "runs" / "kabsch-icp" / "results.csv")
    ens = rows[rows["attack"] == "ensemble"]
    assert ens["extra"].str.contains('"err_pgd": NaN').all()
    assert (ens["trans_err_xy"] >= 0.5 * 0.5).all()
