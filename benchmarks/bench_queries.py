"""Speed of one query attack's query: the evaluated target against the replica that answers for it
(``Target.exact_replica``, docs/performance.md, section 8).

Run: ``python -m pytest benchmarks/bench_queries.py --benchmark-enable
--benchmark-timer=time.process_time`` (about two minutes on 2 cores).

The case is an attack's query: lidar-sim test scan 0 (10,000 points against its submap, λ = 1 m)
translated rigidly by λ in a heading drawn afresh for every round (the ``uniform`` attack's
corruption), registered from the scan's initial guess. Phases, each on the same stream of scans:

* ``kiss``: KISS-ICP itself (500-iteration cap); ``kiss-replica``: its PyTorch replica;
  ``kiss-compiled``: the replica's compiled forward pass (what answers KISS's queries);
* ``p2point``: the PyTorch point-to-point ICP; ``p2point-compiled``: its compiled forward pass
  (what answers its queries);
* ``open3d-point``: Open3D's point-to-point ICP (the ``open3d-p2point`` variant's settings);
  ``open3d-point-replay``: its compiled replay (what answers its queries).

Every round gets a new scan, so nothing measured is a cache hit (the forward-pass cache is off as
well: ``benchmarks/conftest.py``). Each phase prints its ratio to the fixed Open3D reference
measured in the same run (``reference.py``) and, in ``extra_info``, to the phase it stands in for;
it must land on that phase's pose (checked on every round's scan). Wall time is never asserted.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import torch
from reference import open3d_icp  # benchmarks/reference.py (pytest puts benchmarks/ on the path)

from icpbench.core import registry
from icpbench.core.types import Batch
from icpbench.targets.kiss import KissICPTarget
from icpbench.targets.open3d_icp import Open3DICP
from icpbench.targets.p2point import PointToPointICP

#: The query's budget (metres) and the timed rounds per phase.
BUDGET_M, ROUNDS = 1.0, 7
#: phase -> the phase whose poses it must reproduce (None: a target itself)
PHASES = {"kiss": None, "kiss-replica": "kiss", "kiss-compiled": "kiss",
          "p2point": None, "p2point-compiled": "p2point",
          "open3d-point": None, "open3d-point-replay": "open3d-point"}
_MEDIAN: dict[str, float] = {}  # phase -> median seconds in this run


@functools.cache
def _problem() -> dict[str, object]:
    """The scan, its batch, every phase's registration function with its maps built (once per
    map, as in a run) and the poses each phase returned (keyed by the query's first coordinate)."""
    sample = registry.datasets.get("lidar-sim")(seed=0, split="test")[0]
    batch = Batch.from_samples([sample])
    kiss, p2point = KissICPTarget("lidar"), PointToPointICP("lidar")
    kiss_compiled, p2point_compiled = kiss.exact_replica(), p2point.exact_replica()
    kiss_compiled.of.kiss_map(batch.maps[0])
    open3d = Open3DICP("lidar", mode="point")
    own_maps = {"kiss": (kiss, kiss.prepare(sample.map, sample.map_normals)),
                "open3d-point": (open3d, open3d.prepare(sample.map, sample.map_normals))}
    on_batch = {"kiss-replica": kiss_compiled.of, "kiss-compiled": kiss_compiled,
                "p2point": p2point, "p2point-compiled": p2point_compiled,
                "open3d-point-replay": open3d.exact_replica()}

    def register(phase: str, scans: torch.Tensor):
        if phase in own_maps:
            target, prepared = own_maps[phase]
            return target.register(scans, [prepared], batch.T_init)
        with torch.no_grad():
            return on_batch[phase].register(scans, batch.maps, batch.T_init)

    return {"sample": sample, "batch": batch, "register": register, "poses": {}}


def _scans(seed: int = 0):
    """The stream of queries: the scan translated by lambda in a fresh heading (sensor frame)."""
    batch = _problem()["batch"]
    rng = np.random.default_rng(seed)
    R = batch.T_gt[0, :3, :3].to(batch.scans.dtype)

    def fresh() -> tuple[tuple[torch.Tensor], dict]:
        h = float(rng.uniform(0.0, 2 * math.pi))
        shift = torch.tensor([math.cos(h), math.sin(h), 0.0], dtype=batch.scans.dtype) * BUDGET_M
        return (batch.scans + shift @ R,), {}  # R^T shift per point

    return fresh


def _record(benchmark, ratios, phase: str) -> None:
    stats = getattr(benchmark, "stats", None)
    if stats is None:
        return
    med = float(stats.stats.median)
    _MEDIAN[phase] = med
    if "open3d" not in _MEDIAN:
        return
    benchmark.extra_info["ratio_vs_open3d"] = med / _MEDIAN["open3d"]
    of = PHASES.get(phase)
    if of in _MEDIAN:
        benchmark.extra_info[f"ratio_vs_{of}"] = med / _MEDIAN[of]
    ratios[(f"{phase} query, lidar-sim scan 0", phase)] = {
        "ours_s": med, "open3d_s": _MEDIAN["open3d"], "ratio": med / _MEDIAN["open3d"]}


def test_open3d_reference(benchmark, ratios):
    st = _problem()
    out = benchmark.pedantic(open3d_icp(st["sample"]), rounds=ROUNDS, iterations=1,
                             warmup_rounds=1)
    assert out.fitness > 0.5
    _record(benchmark, ratios, "open3d")


@pytest.mark.parametrize("phase", list(PHASES))
def test_query(benchmark, ratios, phase):
    st = _problem()
    poses = st["poses"].setdefault(phase, {})
    st["register"](phase, _scans(seed=99)()[0][0])  # compile / build outside the timed rounds
    gaps = []

    def query(scans: torch.Tensor):
        reg = st["register"](phase, scans)
        key = round(float(scans[0, 0, 0]), 12)
        poses[key] = reg.T[0].double()
        mine = st["poses"].get(PHASES[phase], {}).get(key)
        if mine is not None:
            gaps.append(float(torch.linalg.norm(reg.T[0, :3, 3].double() - mine[:3, 3])))
        return reg

    out = benchmark.pedantic(query, setup=_scans(), rounds=ROUNDS, iterations=1)
    assert out.status[0] == "ok"
    if PHASES[phase] is not None:
        assert gaps and max(gaps) < 1e-6  # the same pose as the target on every shared scan
    _record(benchmark, ratios, phase)
