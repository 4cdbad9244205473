"""Speed of the nearest-neighbour lookups of one ``valley`` plan: small_gicp's tree alone against
``MapIndex.query``, which sends queries outside the map's box to SciPy's tree
(``icpbench/core/mapindex.py``; docs/performance.md, section 2).

Run: ``python -m pytest benchmarks/bench_plan_lookups.py --benchmark-enable
--benchmark-timer=time.process_time`` (about a minute on 2 cores).

The case is the lookup of a point-to-plane plan (``attacks/valley.py``, ``line_climbs``): every
candidate displacement of every scan point at every step of the line to D (the standard
protocol's 4-step plans: 14 candidates, 5 steps, 10,000 points, 700,000 queries) for one scan of
each standard domain: the ``unseen`` town's 64-beam scan 6 (half its queries lie metres from the
map, beyond its crop) and the default town's scan 0. D is a fresh heading at 2 λ every round,
so no round repeats another's queries. Phases:

* ``small-gicp``: small_gicp's ``KdTree`` on every query (before 2026-11-30);
* ``split``: ``MapIndex.query``; it must return the same indices and distances, to the bit
  (checked on two plans of other headings before the timed rounds).

Each phase prints its ratio to the fixed Open3D reference measured in the same run
(``reference.py``) and, in ``extra_info``, to ``small-gicp``. Wall time is never asserted.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from reference import open3d_icp  # benchmarks/reference.py (pytest puts benchmarks/ on the path)

from icpbench.attacks.ensemble import VALLEY_LINE_STEPS
from icpbench.attacks.valley import candidates
from icpbench.core import registry
from icpbench.core.mapindex import MapIndex

#: The plan's budget (metres), |D| / budget and the timed rounds per phase.
BUDGET_M, REACH, ROUNDS = 1.0, 2.0, 5
#: case -> (dataset settings, scan index)
CASES = {"unseen scan 6": ({"sensor": "hdl64", "town_seed": 101}, 6), "town scan 0": ({}, 0)}
_MEDIAN: dict[tuple[str, str], float] = {}  # (case, phase) -> median seconds in this run
_LAST: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # case -> small-gicp's last answer


@functools.cache
def _problem(case: str) -> dict[str, object]:
    """The sample, its scan at the true pose (map frame) and its map index (trees built)."""
    params, i = CASES[case]
    sample = registry.datasets.get("lidar-sim").create(seed=0, split="test", **params)[i]
    T = np.asarray(sample.T_gt, dtype=np.float64)
    p = np.asarray(sample.scan, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
    index = MapIndex(np.asarray(sample.map), np.asarray(sample.map_normals))
    index.query(p[:10])  # build both trees outside the timed rounds
    return {"sample": sample, "points": p[np.isfinite(p).all(axis=1)], "index": index}


def _plans(case: str, seed: int = 0):
    """The stream of inputs: one plan's queries (C (K+1) N, 3) for a fresh heading."""
    st = _problem(case)
    p, index = st["points"], st["index"]
    rng = np.random.default_rng(seed)
    a = np.arange(VALLEY_LINE_STEPS + 1) / VALLEY_LINE_STEPS

    def fresh() -> tuple[tuple[np.ndarray], dict]:
        h = float(rng.uniform(0.0, 2 * math.pi))
        D = REACH * BUDGET_M * np.array([math.cos(h), math.sin(h), 0.0])
        cand = candidates(p, D, index, BUDGET_M)
        q = p[None, None] + cand[:, None] + a[None, :, None, None] * D
        return (np.ascontiguousarray(q.reshape(-1, 3)),), {}

    return fresh


def _small_gicp(index: MapIndex, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows, d2 = index.tree.batch_knn_search(q, 1, num_threads=1)
    return np.sqrt(np.asarray(d2)[:, 0]), np.asarray(rows).astype(np.int64)[:, 0]


def _record(benchmark, ratios, case: str, phase: str) -> None:
    stats = getattr(benchmark, "stats", None)
    if stats is None:
        return
    med = float(stats.stats.median)
    _MEDIAN[(case, phase)] = med
    ref = _MEDIAN.get((case, "open3d"))
    if ref is None:
        return
    benchmark.extra_info["ratio_vs_open3d"] = med / ref
    if (case, "small-gicp") in _MEDIAN:
        benchmark.extra_info["ratio_vs_small-gicp"] = med / _MEDIAN[(case, "small-gicp")]
    ratios[(f"plan lookups, {case}", phase)] = {"ours_s": med, "open3d_s": ref,
                                                "ratio": med / ref}


@pytest.mark.parametrize("case", list(CASES))
def test_open3d_reference(benchmark, ratios, case):
    out = benchmark.pedantic(open3d_icp(_problem(case)["sample"]), rounds=ROUNDS, iterations=1,
                             warmup_rounds=1)
    assert out.fitness > 0.5
    _record(benchmark, ratios, case, "open3d")


@pytest.mark.parametrize("phase", ["small-gicp", "split"])
@pytest.mark.parametrize("case", list(CASES))
def test_plan_lookups(benchmark, ratios, case, phase):
    index = _problem(case)["index"]
    if phase == "split":  # the same answer as small_gicp's tree, to the bit (untimed plans)
        fresh = _plans(case, seed=99)
        for _ in range(2):
            q = fresh()[0][0]
            d, i = index.query(q)
            ref_d, ref_i = _small_gicp(index, q)
            assert np.array_equal(d, ref_d) and np.array_equal(i, ref_i)
    lookup = functools.partial(_small_gicp, index) if phase == "small-gicp" else index.query
    benchmark.pedantic(lookup, setup=_plans(case), rounds=ROUNDS, iterations=1)
    _record(benchmark, ratios, case, phase)
