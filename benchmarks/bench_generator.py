"""Per-scan cost of the learned attack on a 10,000-point lidar scan, beside the PGD oracle.

Run: ``python -m pytest benchmarks/bench_generator.py --benchmark-enable`` (about 3 minutes on
2 cores; add ``--benchmark-timer=time.process_time`` on a busy machine).

The paper reports 1.67 s per scan for generator + ICP evaluation on a V100 (Zhang et al. 2025,
§IV-B). Cases, on one ``lidar-sim`` test scan (N = 10,000 points, its submap, lidar ICP preset,
1 torch thread):

* ``precompute``: FPS, kNN groups and 3-NN interpolation weights of the clean scan (no gradient);
* ``generator``: one forward pass of the shipped lidar-sim generator;
* ``icp``: the p2plane ICP (lidar preset, up to 100 iterations) on the adversarial scan;
* ``attack+icp``: the three together, what ``icpbench run --attacks generator`` pays per scan;
* ``pgd``: the PGD oracle (default 30 steps through a 25-iteration surrogate) on the same scan,
  one round only (it takes tens of seconds).

``extra_info`` records the ratio PGD / (generator attack + ICP) and the ratio to the paper's 1.67 s.
"""

from __future__ import annotations

import torch

from icpbench import registry
from icpbench.types import Batch

PAPER_V100_S = 1.67
BUDGET_M = 1.0
_STATE: dict[str, object] = {}
_MEDIANS: dict[str, float] = {}


def _problem() -> dict[str, object]:
    if "batch" not in _STATE:
        from icpbench.attacks.generator import resolve_checkpoint
        from icpbench.generator.checkpoint import load_checkpoint
        from icpbench.targets.p2plane import PointToPlaneICP

        ds = registry.datasets.get("lidar-sim")(seed=0, split="test")
        batch = Batch.from_samples([ds[0]])
        _ = batch.maps  # KD-tree of the submap, built once as in a real run
        ckpt = resolve_checkpoint("lidar-sim", BUDGET_M)  # the shipped checkpoint
        _STATE.update(batch=batch, model=load_checkpoint(ckpt).model, source=ckpt.name,
                      icp=PointToPlaneICP("lidar"),
                      budget=torch.full((1,), BUDGET_M))
    return _STATE


def _forward(st: dict[str, object], geo=None) -> torch.Tensor:
    model, batch = st["model"], st["batch"]
    x = batch.scans.to(torch.float32)
    with torch.no_grad():
        geo = model.precompute(x) if geo is None else geo
        return model(x, geo, st["budget"] if model.needs_budget else None).double()


def _info(benchmark, st) -> None:
    benchmark.extra_info.update({"N": int(st["batch"].scans.shape[1]), "budget_m": BUDGET_M,
                                 "torch_threads": torch.get_num_threads(),
                                 "weights": st["source"], "paper_v100_s": PAPER_V100_S})


def _median(benchmark, key: str) -> None:
    stats = getattr(benchmark, "stats", None)
    if stats is not None:
        _MEDIANS[key] = float(stats.stats.median)


def test_precompute(benchmark):
    st = _problem()
    _info(benchmark, st)
    geo = benchmark.pedantic(lambda: st["model"].precompute(st["batch"].scans.to(torch.float32)),
                             rounds=5, iterations=1, warmup_rounds=1)
    assert geo.sizes[0] == st["batch"].scans.shape[1]


def test_generator_forward(benchmark):
    st = _problem()
    geo = st["model"].precompute(st["batch"].scans.to(torch.float32))
    _info(benchmark, st)
    adv = benchmark.pedantic(lambda: _forward(st, geo), rounds=5, iterations=1, warmup_rounds=1)
    assert adv.shape == st["batch"].scans.shape and torch.isfinite(adv).all()


def test_icp_on_adversarial_scan(benchmark):
    st = _problem()
    adv, batch = _forward(st), st["batch"]
    _info(benchmark, st)
    reg = benchmark.pedantic(lambda: st["icp"].register(adv, batch.maps, batch.T_init),
                             rounds=5, iterations=1, warmup_rounds=1)
    assert torch.isfinite(reg.T).all()


def test_attack_plus_icp(benchmark):
    st = _problem()
    batch = st["batch"]

    def run():
        adv = _forward(st)
        with torch.no_grad():
            return st["icp"].register(adv, batch.maps, batch.T_init)

    _info(benchmark, st)
    reg = benchmark.pedantic(run, rounds=5, iterations=1, warmup_rounds=1)
    assert torch.isfinite(reg.T).all()
    _median(benchmark, "generator")
    if "generator" in _MEDIANS:
        benchmark.extra_info["ratio_vs_paper_v100"] = _MEDIANS["generator"] / PAPER_V100_S


def test_pgd_oracle(benchmark):
    st = _problem()
    batch = st["batch"]
    pgd = registry.attacks.get("pgd")()
    from icpbench.targets.p2plane import PointToPlaneICP

    surrogate = PointToPlaneICP("lidar-train")

    def run():
        adv = pgd.run(batch, BUDGET_M, surrogate=surrogate,
                      generator=torch.Generator().manual_seed(0)).scans
        with torch.no_grad():
            return st["icp"].register(adv, batch.maps, batch.T_init)

    _info(benchmark, st)
    reg = benchmark.pedantic(run, rounds=1, iterations=1)
    assert torch.isfinite(reg.T).all()
    _median(benchmark, "pgd")
    if "pgd" in _MEDIANS and "generator" in _MEDIANS:
        benchmark.extra_info["ratio_pgd_vs_generator"] = _MEDIANS["pgd"] / _MEDIANS["generator"]
