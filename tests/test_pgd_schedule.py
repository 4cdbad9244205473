"""PGD cost control (attacks/pgd.py): step schedule, early stopping, implicit surrogate gradient,
and the original oracle reachable by parameters."""

from __future__ import annotations

import math

import pytest
import torch

from icpbench.attacks.base import SampleGenerators, project_to_ball
from icpbench.attacks.pgd import PGDAttack
from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.learning.losses import weighted_pose_error
from icpbench.targets.p2plane import PointToPlaneICP


@pytest.fixture(scope="module")
def batch():
    return Batch.from_samples([scene_sample(600, 6_000, seed=s, noise_m=0.02) for s in range(2)])


class _Counting(PointToPlaneICP):
    """p2plane that counts how many scans it registered."""

    calls: list[int] = []

    def register(self, scans, maps, T_init):
        _Counting.calls.append(int(scans.shape[0]))
        return super().register(scans, maps, T_init)


def test_step_sizes():
    const = PGDAttack(steps=30, step_size=0.1).step_sizes(2.0)
    assert const == [pytest.approx(0.2)] * 30
    cos = PGDAttack(steps=11, step_size=0.5, schedule="cosine", final_step_size=0.02).step_sizes(2.0)
    assert cos[0] == pytest.approx(1.0) and cos[-1] == pytest.approx(0.04)
    assert cos[5] == pytest.approx(0.5 * (1.0 + 0.04))
    assert all(a > b for a, b in zip(cos, cos[1:], strict=False))
    for bad in ({"schedule": "linear"}, {"patience": 0}, {"final_step_size": 0.0},
                {"backprop": "exact"}):
        with pytest.raises(InputError):
            PGDAttack(**bad)


def _old_pgd(batch, budget, icp, w, steps, alpha, gens):
    """The oracle as it was before the schedule (30-step loop, full batch every step)."""
    clean = batch.scans.to(torch.float64)

    def obj(adv):
        reg = icp.register(adv, batch.maps, batch.T_init)
        return weighted_pose_error(pose_error(reg.T, batch.T_gt.to(adv.dtype)), w)

    with torch.no_grad():
        best, best_val = clean.clone(), obj(clean)
    d = gens.randn(*clean.shape[1:], dtype=torch.float64)
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    r = gens.rand(clean.shape[1], 1, dtype=torch.float64)
    adv = clean + d * budget * r ** (1.0 / 3.0)
    for _ in range(steps):
        adv = adv.detach().requires_grad_(True)
        val = obj(adv)
        (g,) = torch.autograd.grad(val.sum(), adv)
        with torch.no_grad():
            better = val > best_val
            best = torch.where(better[:, None, None], adv, best)
            best_val = torch.where(better, val, best_val)
            gn = torch.linalg.norm(torch.nan_to_num(g), dim=-1, keepdim=True)
            adv = project_to_ball(clean, adv + alpha * torch.nan_to_num(g) / gn.clamp(min=1e-12),
                                  budget)
    with torch.no_grad():
        val = obj(adv)
        best = torch.where((val > best_val)[:, None, None], adv, best)
    return best.to(batch.scans.dtype)


def test_constant_schedule_without_patience_is_the_original_oracle(batch):
    sur = PointToPlaneICP("lidar")
    atk = PGDAttack(steps=4, step_size=0.1, icp_iterations=10, schedule="constant", patience=None)
    got = atk.run(batch, 1.0, surrogate=sur, generator=7).scans
    gens = SampleGenerators.for_batch(batch, 7, "pgd", 1.0)
    want = _old_pgd(batch, 1.0, atk._surrogate(sur), atk.w, 4, 0.1, gens)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_patience_stops_scans_and_keeps_the_best(batch):
    sur = _Counting("lidar")
    _Counting.calls = []
    full = PGDAttack(steps=12, step_size=0.5, schedule="cosine", icp_iterations=8)
    out_full = full.run(batch, 1.0, surrogate=sur, generator=1)
    n_full = sum(_Counting.calls)
    _Counting.calls = []
    early = PGDAttack(steps=12, step_size=0.5, schedule="cosine", icp_iterations=8, patience=1)
    out = early.run(batch, 1.0, surrogate=sur, generator=1)
    assert sum(_Counting.calls) < n_full  # fewer scans registered
    assert min(_Counting.calls) >= 1 and 1 in _Counting.calls[1:]  # a stopped scan left the batch
    assert float(out.stats["disp_max"].max()) <= 1.0 + 1e-9
    tgt = PointToPlaneICP("lidar", max_iterations=8)
    with torch.no_grad():
        clean = weighted_pose_error(pose_error(
            tgt.register(batch.scans, batch.maps, batch.T_init).T, batch.T_gt), early.w)
        got = weighted_pose_error(pose_error(
            tgt.register(out.scans, batch.maps, batch.T_init).T, batch.T_gt), early.w)
    assert (got >= clean - 1e-9).all()  # the best iterate, never below the start
    assert out_full.scans.shape == out.scans.shape


def test_implicit_surrogate_gradient_is_used(batch):
    atk = PGDAttack(steps=2, backprop="implicit")
    icp = atk._surrogate(PointToPlaneICP("lidar"))
    assert icp.config.backprop == "implicit" and icp.config.max_iterations == 25
    out = atk.run(batch, 0.5, surrogate=PointToPlaneICP("lidar"), generator=0)
    assert math.isfinite(float(out.scans.sum()))
    assert float(out.stats["disp_max"].max()) <= 0.5 + 1e-9


def test_sector_warm_start_never_below_the_sector_attack(batch):
    """init="sector" starts the ascent from the analytic attack's output: its surrogate objective
    is never below the sector attack's, the budget holds, and a bad init is refused."""
    from icpbench.attacks.sector import SectorAttack

    icp = PointToPlaneICP().with_max_iterations(25)
    budget = 0.3
    w = PGDAttack().w

    def objective(adv):
        with torch.no_grad():
            reg = icp.register(adv.to(torch.float64), batch.maps, batch.T_init)
            return weighted_pose_error(pose_error(reg.T, batch.T_gt.to(torch.float64)), w)

    sec = SectorAttack(d_max=5.0).run(batch, budget, generator=0).scans
    out = PGDAttack(steps=3, init="sector", icp_iterations=25).run(
        batch, budget, surrogate=icp, generator=0)
    assert out.stats["disp_max"].max() <= budget + 1e-9
    assert torch.all(objective(out.scans) >= objective(sec) - 1e-9)
    # the sector start is deterministic: no random stream enters it
    again = PGDAttack(steps=3, init="sector", icp_iterations=25).run(
        batch, budget, surrogate=icp, generator=123)
    assert torch.allclose(out.scans, again.scans)
    with pytest.raises(InputError):
        PGDAttack(init="gradient")


def test_icp_nn_reuse_reaches_the_surrogate(batch, reuse_radii):
    """``icp_nn_reuse``: every surrogate ICP of the ascent runs with the radius, together with the
    other surrogate settings; the budget holds; recorded only when set; negative refused."""
    atk = PGDAttack(steps=2, backprop="implicit", icp_nn_reuse=0.05)
    icp = atk._surrogate(PointToPlaneICP("lidar"))
    assert icp.config.nn_reuse_m == 0.05 and icp.config.backprop == "implicit"
    assert icp.config.max_iterations == 25
    out = atk.run(batch, 0.5, surrogate=PointToPlaneICP("lidar"), generator=0)
    assert reuse_radii and set(reuse_radii) == {0.05}
    assert float(out.stats["disp_max"].max()) <= 0.5 + 1e-9
    assert atk.params["icp_nn_reuse"] == 0.05 and "icp_nn_reuse" not in PGDAttack().params
    with pytest.raises(InputError, match="icp_nn_reuse"):
        PGDAttack(icp_nn_reuse=-0.1)


def test_pgd_warm_is_pgd_with_the_cheaper_oracles_settings(batch):
    """``pgd-warm`` is registered, equals ``pgd`` run with its settings (sector-iter start, 2
    steps, 100-iteration surrogate with 5 cm reuse, implicit gradient), keeps the budget and
    records its start; another start drops the default start settings."""
    from icpbench.attacks.pgd_warm import WARM_START, WarmPGDAttack
    from icpbench.core import registry

    assert registry.attacks.get("pgd-warm") is WarmPGDAttack
    assert WarmPGDAttack().params["init_params"] == WARM_START
    small = {"iterations": 1, "icp_iterations": 3}
    warm = WarmPGDAttack(init_params=small, icp_iterations=3)
    assert warm.steps == 2 and warm.backprop == "implicit" and warm.icp_nn_reuse == 0.05
    plain = PGDAttack(steps=2, init="sector-iter", init_params=small, icp_iterations=3,
                      icp_nn_reuse=0.05, backprop="implicit")
    surrogate = PointToPlaneICP("lidar")
    out = warm.run(batch, 0.5, surrogate=surrogate, generator=0)
    ref = plain.run(batch, 0.5, surrogate=surrogate, generator=0)
    assert torch.equal(out.scans, ref.scans)
    assert float(out.stats["disp_max"].max()) <= 0.5 + 1e-9
    assert "init_params" not in WarmPGDAttack(init="sector").params
