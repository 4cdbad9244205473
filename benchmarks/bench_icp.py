"""Speed of our differentiable point-to-plane ICP beside Open3D's ``registration_icp``.

Run: ``python -m pytest benchmarks/bench_icp.py --benchmark-enable`` (about 1-2 minutes on 2 cores).

Two cases, each with exactly 30 iterations on both sides (ours: ``tol`` = 1e-300 so it never stops
early, checked; Open3D: ``relative_fitness = relative_rmse = 0``) and the lidar preset's settings
(d_max = 5 m, Cauchy c = 1 m), on the synthetic lidar-like scene with 2 cm scan noise:

* ``b8-n2048-m10k``: B = 8 scans of N = 2,048 points, each against a 10,000-point map;
* ``b1-n10k-m100k``: B = 1 scan of N = 10,000 points against a 100,000-point map (the issue's case).

Each case runs twice: with the scan points in the order ``scene_sample`` gives them (random, the
worst case for the cache behaviour of KD-tree queries; also what random subsampling produces) and
sorted by 1 m voxel (x, then y, then z), which is closer to a spinning lidar's ring/azimuth order.
ICP does not depend on the order, both libraries get the same input, and the results are identical.

Phases: ``forward`` (``torch.no_grad``), ``forward+backward`` (graph through all 30 iterations, then
the gradient of the summed pose entries w.r.t. every scan point). Open3D is looped over the batch;
its time includes the KD-tree build of the map that it performs inside every call (its legacy API
cannot take a prebuilt tree), while our map KD-trees are built once outside the timed region, as in
real use. Threads: torch 1, Open3D 1 (recorded in ``extra_info``). Ratios (ours / Open3D, medians)
are stored in ``extra_info["ratio_vs_open3d"]`` and printed in the terminal summary. Wall time is
never asserted. On a busy machine add ``--benchmark-timer=time.process_time`` (both sides are
single-threaded, so CPU time is comparable and far less sensitive to other load).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
import torch

from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.p2plane import PointToPlaneICP

o3d = pytest.importorskip("open3d")
reg = o3d.pipelines.registration

ITERS = 30
OPEN3D_THREADS = 1
ROUNDS = 5
SIZES = {  # name: (B, N, M)
    "b8-n2048-m10k": (8, 2_048, 10_000),
    "b1-n10k-m100k": (1, 10_000, 100_000),
}
CASES = [f"{size}-{order}" for size in SIZES for order in ("random", "sorted")]
_PROBLEMS: dict[str, tuple[Batch, list, list]] = {}
_OPEN3D_MEDIAN: dict[str, float] = {}


def _problem(case: str) -> tuple[Batch, list, list]:
    """Batch (float64 scans, cached MapIndex list), Open3D sources and targets (with normals)."""
    if case not in _PROBLEMS:
        size, order = case.rsplit("-", 1)
        B, N, M = SIZES[size]
        samples = [scene_sample(n_scan=N, n_map=M, seed=k, noise_m=0.02) for k in range(B)]
        if order == "sorted":
            samples = [replace(s, scan=s.scan[_voxel_order(s.scan)]) for s in samples]
        batch = Batch.from_samples(samples)
        _ = batch.maps  # build the KD-trees now, outside the timed region
        targets, sources = [], []
        for s in samples:
            t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s.map.astype(np.float64)))
            t.normals = o3d.utility.Vector3dVector(s.map_normals.astype(np.float64))
            targets.append(t)
            sources.append(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
                s.scan.astype(np.float64))))
        _PROBLEMS[case] = (batch, sources, targets)
    return _PROBLEMS[case]


def _voxel_order(points: np.ndarray, voxel_m: float = 1.0) -> np.ndarray:
    """Permutation sorting (N, 3) points by their voxel index (x, then y, then z)."""
    key = np.floor(points / voxel_m).astype(np.int64)
    return np.lexsort((key[:, 2], key[:, 1], key[:, 0]))


def _ours() -> PointToPlaneICP:
    return PointToPlaneICP("lidar", max_iterations=ITERS, tol=1e-300)


def _info(benchmark, case: str) -> None:
    B, N, M = SIZES[case.rsplit("-", 1)[0]]
    benchmark.extra_info.update({
        "B": B, "N": N, "M": M, "scan_order": case.rsplit("-", 1)[1], "iterations": ITERS,
        "torch_threads": torch.get_num_threads(),
        "open3d_threads": OPEN3D_THREADS, "open3d_version": o3d.__version__,
    })


def _run(benchmark, fn: Callable[[], object]) -> object:
    return benchmark.pedantic(fn, rounds=ROUNDS, iterations=1, warmup_rounds=1)


def _median(benchmark) -> float | None:
    stats = getattr(benchmark, "stats", None)
    return None if stats is None else float(stats.stats.median)


@pytest.mark.parametrize("case", CASES)
def test_open3d_point_to_plane(benchmark, case):
    batch, sources, targets = _problem(case)
    est = reg.TransformationEstimationPointToPlane(reg.CauchyLoss(k=1.0))
    crit = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=ITERS)
    T0 = batch.T_init.numpy()
    o3d.utility.set_max_threads(OPEN3D_THREADS)

    def run():
        return [reg.registration_icp(src, tgt, 5.0, T0[b], est, crit)
                for b, (src, tgt) in enumerate(zip(sources, targets, strict=True))]

    _info(benchmark, case)
    results = _run(benchmark, run)
    assert all(r.fitness > 0.9 for r in results)
    med = _median(benchmark)
    if med is not None:
        _OPEN3D_MEDIAN[case] = med


def _record_ratio(benchmark, ratios, case: str, phase: str) -> None:
    med = _median(benchmark)
    if med is None or case not in _OPEN3D_MEDIAN:
        return
    ratio = med / _OPEN3D_MEDIAN[case]
    benchmark.extra_info["open3d_median_s"] = _OPEN3D_MEDIAN[case]
    benchmark.extra_info["ratio_vs_open3d"] = ratio
    ratios[(case, phase)] = {"ours_s": med, "open3d_s": _OPEN3D_MEDIAN[case], "ratio": ratio}


@pytest.mark.parametrize("case", CASES)
def test_p2plane_forward(benchmark, ratios, case):
    batch, _, _ = _problem(case)
    tgt = _ours()

    def run():
        with torch.no_grad():
            return tgt.register(batch.scans, batch.maps, batch.T_init)

    _info(benchmark, case)
    out = _run(benchmark, run)
    assert bool((out.iterations == ITERS).all())  # the setup really runs 30 iterations
    _record_ratio(benchmark, ratios, case, "forward")


@pytest.mark.parametrize("case", CASES)
def test_p2plane_forward_backward(benchmark, ratios, case):
    batch, _, _ = _problem(case)
    tgt = _ours()

    def run():
        scans = batch.scans.clone().requires_grad_(True)
        out = tgt.register(scans, batch.maps, batch.T_init)
        out.T[:, :3, :].sum().backward()
        return out, scans.grad

    _info(benchmark, case)
    out, grad = _run(benchmark, run)
    assert bool((out.iterations == ITERS).all())
    assert grad is not None and bool(torch.isfinite(grad).all())
    _record_ratio(benchmark, ratios, case, "forward+backward")
