"""The PGD oracle (attacks/pgd.py): the ascent equals a reference loop, its starts, the implicit
surrogate gradient, approximate correspondences, and the ``pgd-warm`` preset."""

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


def test_bad_settings_are_refused():
    for bad in ({"steps": 0}, {"step_size": 0.0}, {"backprop": "exact"}, {"init": "gradient"},
                {"init": "sector", "sector_iter": {"iterations": 2}},
                {"init": "sector-iter", "sector_iter": {"icp_iters": 3}}):
        with pytest.raises(InputError):
            PGDAttack(**bad)


def _old_pgd(batch, budget, icp, w, steps, alpha, gens):
    """A plain reference of the oracle: random start, ``steps`` normalised-gradient steps of
    ``alpha`` metres, projection, best iterate (the clean scan included)."""
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


def test_pgd_is_the_reference_ascent(batch):
    sur = PointToPlaneICP("lidar")
    atk = PGDAttack(steps=4, step_size=0.1, icp_iterations=10)
    got = atk.run(batch, 1.0, surrogate=sur, generator=7).scans
    gens = SampleGenerators.for_batch(batch, 7, "pgd", 1.0)
    want = _old_pgd(batch, 1.0, atk._surrogate(sur), atk.w, 4, 0.1, gens)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


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
    assert atk.params["icp_nn_reuse"] == 0.05 and PGDAttack().params["icp_nn_reuse"] == 0.0
    with pytest.raises(InputError, match="icp_nn_reuse"):
        PGDAttack(icp_nn_reuse=-0.1)


def test_pgd_warm_is_a_preset_of_pgd(batch):
    """``pgd-warm`` is registered, has pgd's settings, equals ``pgd`` run with its preset
    (sector-iter start, 2 steps, 100-iteration surrogate with 5 cm reuse, implicit gradient),
    keeps the budget and records its start settings."""
    from icpbench.attacks.pgd_warm import WarmPGDAttack
    from icpbench.core import registry
    from icpbench.core.iterated_sector import SectorIterSettings

    assert registry.attacks.get("pgd-warm") is WarmPGDAttack
    assert WarmPGDAttack.param_types() == PGDAttack.param_types()
    default = WarmPGDAttack()
    assert default.params["sector_iter"] == SectorIterSettings(iterations=8, icp_nn_reuse=0.05).as_dict()
    assert default.steps == 2 and default.backprop == "implicit" and default.icp_nn_reuse == 0.05
    small = {"iterations": 1, "icp_iterations": 3}
    warm = WarmPGDAttack(sector_iter=small, icp_iterations=3)
    plain = PGDAttack(steps=2, init="sector-iter", sector_iter=small, icp_iterations=3,
                      icp_nn_reuse=0.05, backprop="implicit")
    surrogate = PointToPlaneICP("lidar")
    out = warm.run(batch, 0.5, surrogate=surrogate, generator=0)
    ref = plain.run(batch, 0.5, surrogate=surrogate, generator=0)
    assert torch.equal(out.scans, ref.scans)
    assert float(out.stats["disp_max"].max()) <= 0.5 + 1e-9
    assert WarmPGDAttack(init="sector", sector_iter=None).params["sector_iter"] is None
    with pytest.raises(InputError, match="sector_iter"):  # the preset's start settings need its start
        WarmPGDAttack(init="sector")
