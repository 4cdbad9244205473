"""Per-scan cost of the learned attack and of the PGD oracle on a lidar-sim scan, as ratios to Open3D.

Run: ``python -m pytest benchmarks/bench_generator.py --benchmark-enable`` (about 3 minutes on
2 cores; add ``--benchmark-timer=time.process_time`` on a busy machine: everything is 1 thread).

Cases, on one ``lidar-sim`` test scan (N = 10,000 points, its submap, 1 torch thread), each printed
as a ratio to the fixed reference (``reference.py``: one 30-iteration Open3D point-to-plane ICP of
the same scan against the same map, measured in the same run):

* ``open3d-icp-30``: the reference itself;
* ``precompute``: FPS, kNN groups and 3-NN interpolation weights of the clean scan (no gradient);
* ``prior``: the prior input channels of the shipped model (``icpbench.learning.prior``): for the
  one-step sector prior one nearest-neighbour query of the scan in the map and a 6x6 solve; for the
  iterated prior (``prior="sector-iter"``) also the surrogate ICPs of the iterated analytic attack
  with the generator attack's settings (``GeneratorAttack.prior_settings``);
* ``generator-forward``: one forward pass of the shipped lidar-sim generator (prior given);
* ``generator-attack``: the registered ``generator`` attack's ``run`` on the scan: precompute +
  prior + forward + projection, what the attack costs per scan;
* ``attack+icp``: the attack plus our p2plane ICP (lidar preset, up to 100 iterations) on its
  output, what ``icpbench run --attacks generator`` pays per scan;
* ``pgd-step``: one PGD step (25-iteration surrogate, forward + backward);
* ``pgd-30``: the original oracle, ``pgd`` with its defaults (30 steps of 0.1 lambda from a random
  start; one round);
* ``pgd-warm``: the cheaper oracle, ``pgd-warm`` with its defaults (the iterated analytic attack
  with 8 re-linearisations and 5 cm correspondence reuse, then 2 PGD steps of 0.1 lambda through
  the 100-iteration surrogate with 5 cm correspondence reuse and the implicit gradient; one round).

The iterated analytic attack keeps its result in the batch's memo (so that in one run the
generator's prior, ``sector-iter`` and ``pgd-warm`` share it); every timed call here starts from an
empty memo, so each case pays for its own computation.

The paper reports 1.67 s per scan for generator + ICP evaluation on a V100 (Zhang et al. 2025,
§IV-B); ``extra_info`` keeps that ratio too.
"""

from __future__ import annotations

import pytest
import torch
from reference import open3d_icp  # benchmarks/reference.py (pytest puts benchmarks/ on the path)

from icpbench.core import registry
from icpbench.core.types import Batch

PAPER_V100_S = 1.67
BUDGET_M = 1.0
CASE = "lidar-sim test scan 0"
_STATE: dict[str, object] = {}
_REF: dict[str, float] = {}


def _problem() -> dict[str, object]:
    if "batch" not in _STATE:
        from icpbench.attacks.generator import resolve_checkpoint
        from icpbench.learning.checkpoint import load_checkpoint
        from icpbench.targets.p2plane import PointToPlaneICP

        sample = registry.datasets.get("lidar-sim")(seed=0, split="test")[0]
        batch = Batch.from_samples([sample])
        _ = batch.maps  # KD-tree of the submap, built once as in a real run
        ckpt = resolve_checkpoint("lidar-sim", BUDGET_M)  # the shipped checkpoint
        _STATE.update(sample=sample, batch=batch, model=load_checkpoint(ckpt).model.eval(),
                      source=ckpt.name, icp=PointToPlaneICP("lidar"),
                      surrogate=PointToPlaneICP("lidar"), budget=torch.full((1,), BUDGET_M),
                      attack=registry.attacks.get("generator")(dataset="lidar-sim"))
    return _STATE


def _batch(st: dict[str, object]) -> Batch:
    """The problem's batch with an empty memo (its map's KD-tree kept): nothing computed by an
    earlier call is reused."""
    batch = st["batch"]
    batch.memo.clear()
    return batch


def _prior(st: dict[str, object]) -> torch.Tensor | None:
    """The model's analytic input channels (B, N, 8) of the clean scan, None for models without.

    The channels of the model's own ``prior`` setting: the one-step sector prior, or for
    ``prior="sector-iter"`` the iterated analytic attack with the registered attack's settings
    (its surrogate ICP runs included), as the registered attack computes them.
    """
    model = st["model"]
    if not getattr(model, "needs_prior", False):
        return None
    from icpbench.learning.prior import prior_channels

    return prior_channels(model.config, _batch(st), st["budget"], st["surrogate"],
                          st["attack"].prior_settings)


def _forward(st: dict[str, object], geo, prior) -> torch.Tensor:
    model, batch = st["model"], st["batch"]
    x = batch.scans.to(torch.float32)
    args = (prior,) if prior is not None else ()
    with torch.no_grad():
        return model(x, geo, st["budget"] if model.needs_budget else None, *args).double()


def _attack(st: dict[str, object]) -> torch.Tensor:
    """The registered generator attack on the scan with the run's surrogate (what a run pays per
    scan)."""
    return st["attack"].run(_batch(st), BUDGET_M, surrogate=st["surrogate"], generator=0).scans


def _median(benchmark) -> float | None:
    stats = getattr(benchmark, "stats", None)
    return None if stats is None else float(stats.stats.median)


def _record(benchmark, ratios, phase: str) -> None:
    """Record the case's settings and its ratio to the Open3D reference."""
    st = _problem()
    benchmark.extra_info.update({"N": int(st["batch"].scans.shape[1]), "budget_m": BUDGET_M,
                                 "torch_threads": torch.get_num_threads(),
                                 "weights": st["source"], "paper_v100_s": PAPER_V100_S})
    med = _median(benchmark)
    if med is None or "open3d" not in _REF:
        return
    benchmark.extra_info["open3d_median_s"] = _REF["open3d"]
    benchmark.extra_info["ratio_vs_open3d"] = med / _REF["open3d"]
    ratios[(CASE, phase)] = {"ours_s": med, "open3d_s": _REF["open3d"],
                             "ratio": med / _REF["open3d"]}


def test_open3d_reference(benchmark, ratios):
    st = _problem()
    out = benchmark.pedantic(open3d_icp(st["sample"]), rounds=11, iterations=1, warmup_rounds=1)
    assert out.fitness > 0.5
    med = _median(benchmark)
    if med is not None:
        _REF["open3d"] = med
    _record(benchmark, ratios, "open3d-icp-30")


def test_precompute(benchmark, ratios):
    st = _problem()
    x = st["batch"].scans.to(torch.float32)
    geo = benchmark.pedantic(lambda: st["model"].precompute(x), rounds=5, iterations=1,
                             warmup_rounds=1)
    assert geo.sizes[0] == x.shape[1]
    _record(benchmark, ratios, "precompute")


def test_prior(benchmark, ratios):
    st = _problem()
    if _prior(st) is None:
        pytest.skip("the shipped model takes no prior channels")
    pr = benchmark.pedantic(lambda: _prior(st), rounds=5, iterations=1, warmup_rounds=1)
    assert pr.shape == (*st["batch"].scans.shape[:2], 8) and float(pr.abs().sum()) > 0
    _record(benchmark, ratios, "prior")


def test_generator_forward(benchmark, ratios):
    st = _problem()
    geo = st["model"].precompute(st["batch"].scans.to(torch.float32))
    prior = _prior(st)
    adv = benchmark.pedantic(lambda: _forward(st, geo, prior), rounds=7, iterations=1,
                             warmup_rounds=1)
    assert adv.shape == st["batch"].scans.shape and torch.isfinite(adv).all()
    _record(benchmark, ratios, "generator-forward")


def test_generator_attack(benchmark, ratios):
    st = _problem()
    adv = benchmark.pedantic(lambda: _attack(st), rounds=9, iterations=1, warmup_rounds=1)
    disp = torch.linalg.norm(adv - st["batch"].scans, dim=-1)
    assert float(disp.max()) <= BUDGET_M + 1e-4 and float(disp.mean()) > 0.01
    _record(benchmark, ratios, "generator-attack")


def test_attack_plus_icp(benchmark, ratios):
    st = _problem()
    batch = st["batch"]

    def run():
        adv = _attack(st)
        with torch.no_grad():
            return st["icp"].register(adv, batch.maps, batch.T_init)

    out = benchmark.pedantic(run, rounds=5, iterations=1, warmup_rounds=1)
    assert torch.isfinite(out.T).all()
    _record(benchmark, ratios, "attack+icp")
    med = _median(benchmark)
    if med is not None:
        benchmark.extra_info["ratio_vs_paper_v100"] = med / PAPER_V100_S


def test_pgd_step(benchmark, ratios):
    st = _problem()
    batch = st["batch"]
    pgd = registry.attacks.get("pgd")()
    icp = pgd._surrogate(st["surrogate"])

    def run():
        x = batch.scans.clone().requires_grad_(True)
        val = pgd._objective(icp, batch, x)
        return torch.autograd.grad(val.sum(), x)[0]

    g = benchmark.pedantic(run, rounds=5, iterations=1, warmup_rounds=1)
    assert torch.isfinite(g).all() and float(g.abs().sum()) > 0
    _record(benchmark, ratios, "pgd-step")


def _pgd_case(benchmark, ratios, phase: str, attack: str = "pgd", **params) -> dict:
    """Time one round of ``attack`` with ``params`` on the scan; returns its recorded settings."""
    st = _problem()
    pgd = registry.attacks.get(attack)(**params)

    def run():
        return pgd.run(_batch(st), BUDGET_M, surrogate=st["surrogate"], generator=0).scans

    adv = benchmark.pedantic(run, rounds=1, iterations=1)
    assert float(torch.linalg.norm(adv - st["batch"].scans, dim=-1).max()) <= BUDGET_M + 1e-6
    _record(benchmark, ratios, phase)
    return pgd.params


def test_pgd_oracle_30(benchmark, ratios):
    params = _pgd_case(benchmark, ratios, "pgd-30", steps=30, step_size=0.1, init="random")
    assert params["icp_iterations"] == 25 and params["icp_nn_reuse"] == 0.0


def test_pgd_warm(benchmark, ratios):
    from icpbench.core.iterated_sector import SectorIterSettings

    params = _pgd_case(benchmark, ratios, "pgd-warm", attack="pgd-warm")
    assert (params["steps"], params["step_size"], params["icp_iterations"]) == (2, 0.1, 100)
    assert params["init"] == "sector-iter" and params["icp_nn_reuse"] == 0.05
    assert params["sector_iter"] == SectorIterSettings(iterations=8, icp_nn_reuse=0.05).as_dict()
