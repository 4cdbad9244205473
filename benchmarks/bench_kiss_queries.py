"""Speed of one query against KISS-ICP: the library itself and its exact replica, which answers the
query attacks' queries in its place (``Target.exact_replica``, docs/performance.md, section 8).

Run: ``python -m pytest benchmarks/bench_kiss_queries.py --benchmark-enable
--benchmark-timer=time.process_time`` (about a minute on 2 cores).

The case is an attack's query: lidar-sim test scan 0 (10,000 points against its submap, λ = 1 m)
translated rigidly by λ in a heading drawn afresh for every round (the ``uniform`` attack's
corruption), registered from the scan's initial guess with KISS-ICP's registered lidar settings
(500-iteration cap), once by ``kiss-icp`` and once by ``kiss-icp-replica``. Every round gets a new
scan, so nothing measured is a cache hit (the forward-pass cache is off as well:
``benchmarks/conftest.py``). Both print their ratio to the fixed Open3D reference measured in the
same run (``reference.py``), and the replica's ratio to KISS-ICP is in its ``extra_info``. The
two must land on the same pose (checked on every round's scan). Wall time is never asserted.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch
from reference import open3d_icp  # benchmarks/reference.py (pytest puts benchmarks/ on the path)

from icpbench.core import registry
from icpbench.core.types import Batch
from icpbench.targets.kiss import KissICPTarget

#: The query's budget (metres), the timed rounds per case and the case's name in the summary.
BUDGET_M, ROUNDS, CASE = 1.0, 7, "kiss query, lidar-sim scan 0"
_MEDIAN: dict[str, float] = {}  # phase -> median seconds in this run


@functools.cache
def _problem() -> dict[str, object]:
    """The scan, its batch, both targets with their maps built (once per map, as in a run), the
    heading stream and the poses KISS returned (keyed by the query's first coordinate)."""
    sample = registry.datasets.get("lidar-sim")(seed=0, split="test")[0]
    batch = Batch.from_samples([sample])
    kiss = KissICPTarget("lidar")
    replica = kiss.exact_replica()
    replica.kiss_map(batch.maps[0])
    return {"sample": sample, "batch": batch, "kiss": kiss, "replica": replica,
            "kiss_map": kiss.prepare(sample.map, sample.map_normals),
            "rng": np.random.default_rng(0), "poses": {}}


def _fresh_scan() -> tuple[tuple[torch.Tensor], dict]:
    """A new query: the scan translated by lambda in a fresh heading (sensor frame)."""
    st = _problem()
    batch = st["batch"]
    h = float(st["rng"].uniform(0.0, 2 * math.pi))
    shift_map = torch.tensor([math.cos(h), math.sin(h), 0.0], dtype=batch.scans.dtype) * BUDGET_M
    R = batch.T_gt[0, :3, :3].to(batch.scans.dtype)
    return (batch.scans + shift_map @ R,), {}  # R^T shift per point


def _record(benchmark, ratios, phase: str) -> None:
    stats = getattr(benchmark, "stats", None)
    if stats is None:
        return
    med = float(stats.stats.median)
    _MEDIAN[phase] = med
    if "open3d" not in _MEDIAN:
        return
    benchmark.extra_info["ratio_vs_open3d"] = med / _MEDIAN["open3d"]
    if phase == "replica" and "kiss" in _MEDIAN:
        benchmark.extra_info["ratio_vs_kiss"] = med / _MEDIAN["kiss"]
    ratios[(CASE, phase)] = {"ours_s": med, "open3d_s": _MEDIAN["open3d"],
                             "ratio": med / _MEDIAN["open3d"]}


def test_open3d_reference(benchmark, ratios):
    st = _problem()
    out = benchmark.pedantic(open3d_icp(st["sample"]), rounds=ROUNDS, iterations=1,
                             warmup_rounds=1)
    assert out.fitness > 0.5
    _record(benchmark, ratios, "open3d")


def test_kiss_icp_query(benchmark, ratios):
    st = _problem()
    batch = st["batch"]

    def query(scans: torch.Tensor):
        reg = st["kiss"].register(scans, [st["kiss_map"]], batch.T_init)
        st["poses"][round(float(scans[0, 0, 0]), 12)] = reg.T[0].double()
        return reg

    out = benchmark.pedantic(query, setup=_fresh_scan, rounds=ROUNDS, iterations=1)
    assert out.status[0] == "ok"
    _record(benchmark, ratios, "kiss")


def test_kiss_replica_query(benchmark, ratios):
    st = _problem()
    batch = st["batch"]
    st["rng"] = np.random.default_rng(0)  # the same scans as the KISS rounds, in order
    gaps = []

    def query(scans: torch.Tensor):
        with torch.no_grad():
            reg = st["replica"].register(scans, batch.maps, batch.T_init)
        mine = st["poses"].get(round(float(scans[0, 0, 0]), 12))
        if mine is not None:
            gaps.append(float(torch.linalg.norm(reg.T[0, :3, 3].double() - mine[:3, 3])))
        return reg

    benchmark.pedantic(query, setup=_fresh_scan, rounds=ROUNDS, iterations=1)
    assert gaps and max(gaps) < 1e-6  # the same pose as KISS on every shared scan
    _record(benchmark, ratios, "replica")
