"""The iterated analytic attack (attacks/sector_iter.py): its start is the sector attack, it never
returns less than that start on the surrogate, it finds more on scenes where ICP moves, the budget
holds exactly, and it is deterministic."""

from __future__ import annotations

import pytest
import torch

from icpbench.attacks.sector import SectorAttack
from icpbench.attacks.sector_iter import SectorIterAttack
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.p2plane import PointToPlaneICP


@pytest.fixture(scope="module")
def batch():
    return Batch.from_samples([scene_sample(600, 6_000, seed=s, noise_m=0.02) for s in range(3)])


@pytest.fixture(scope="module")
def icp():
    return PointToPlaneICP().with_max_iterations(25)


def _xy_error(icp, batch, scans):
    with torch.no_grad():
        reg = icp.register(scans.to(torch.float64), batch.maps, batch.T_init)
        xi = pose_error(reg.T, batch.T_gt.to(torch.float64))
    return torch.linalg.norm(xi[:, :2], dim=-1)


def test_zero_iterations_is_the_sector_attack(batch, icp):
    out = SectorIterAttack(iterations=0).run(batch, 0.3, surrogate=icp, generator=0)
    sec = SectorAttack(d_max=5.0).run(batch, 0.3, generator=0)
    torch.testing.assert_close(out.scans, sec.scans, atol=1e-12, rtol=0)
    assert torch.all(out.extra["sector_iter_best"] == 0)


def test_iterations_raise_the_surrogate_error_within_budget(batch, icp):
    """Never below the sector start on the surrogate; above it on average (on these scenes four
    re-linearised steps add 15-25% of surrogate error); every point within lambda; the extra
    column reports the surrogate error of the returned scan."""
    budget = 0.3
    sec = SectorAttack(d_max=5.0).run(batch, budget, generator=0).scans
    out = SectorIterAttack(iterations=4).run(batch, budget, surrogate=icp, generator=0)
    e_sec, e_it = _xy_error(icp, batch, sec), _xy_error(icp, batch, out.scans)
    assert torch.all(e_it >= e_sec - 1e-9)
    assert e_it.mean() > 1.1 * e_sec.mean()
    torch.testing.assert_close(out.extra["sector_iter_surrogate_xy"].to(torch.float64), e_it,
                               atol=1e-9, rtol=0)
    assert out.stats["disp_max"].max() <= budget + 1e-9
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    again = SectorIterAttack(iterations=4).run(batch, budget, surrogate=icp, generator=99)
    assert torch.equal(out.scans, again.scans)  # no random stream enters it


def test_registered_and_checked(icp, batch):
    assert registry.attacks.get("sector-iter") is SectorIterAttack
    for bad in ({"iterations": -1}, {"step_size": 0.0}, {"step_size": 3.0},
                {"icp_iterations": 0}, {"d_max": -1.0}):
        with pytest.raises(InputError):
            SectorIterAttack(**bad)
    with pytest.raises(InputError, match="surrogate"):
        SectorIterAttack().run(batch, 0.3, generator=0)


def test_ball_generator_with_iterated_prior_starts_as_the_attack(batch, icp):
    """A 'ball' generator with the sector-iter prior, gain 1 and its zero-initialised head returns
    the iterated attack's scans (to float32 rounding); a trained head moves no point beyond lambda
    and the prior needs its budget and surrogate."""
    from icpbench.learning.network import Generator, generator_config
    from icpbench.learning.prior import prior_channels

    cfg = generator_config("objects", output="ball", prior="sector-iter", prior_dmax=5.0,
                           prior_iterations=3, prior_gain=1.0)
    g = Generator(cfg).eval()
    lam = torch.tensor([0.3, 0.3, 0.5])
    x = batch.scans.float()
    pr = prior_channels(cfg, batch, lam, icp)
    with torch.no_grad():
        out = g(x, g.precompute(x), lam, pr).double()
    for value in (0.3, 0.5):
        k = (lam == value).nonzero()[:, 0]
        sub = Batch.from_samples([batch.samples[i] for i in k.tolist()])
        ref = SectorIterAttack(iterations=3).run(sub, value, surrogate=icp, generator=0).scans
        torch.testing.assert_close(out[k] - batch.scans[k], ref - sub.scans, atol=1e-5, rtol=0)
    with torch.no_grad():
        g.head[-1].weight.normal_(0, 0.5)
        moved = g(x, g.precompute(x), lam, pr).double() - batch.scans
    assert (torch.linalg.norm(moved, dim=-1) <= lam[:, None] * (1 + 1e-5)).all()
    with pytest.raises(InputError, match="surrogate"):
        prior_channels(cfg, batch, lam, None)


def test_pgd_from_the_iterated_attack_never_falls_below_it(batch, icp):
    from icpbench.attacks.pgd import PGDAttack

    start = SectorIterAttack().run(batch, 0.3, surrogate=icp, generator=0).scans
    out = PGDAttack(steps=2, init="sector-iter").run(batch, 0.3, surrogate=icp, generator=0)
    assert torch.all(_xy_error(icp, batch, out.scans) >= _xy_error(icp, batch, start) - 1e-9)
    assert out.stats["disp_max"].max() <= 0.3 + 1e-9


def test_pgd_init_params_set_the_iterated_start(batch, icp):
    """``init_params`` configure the sector-iter start: the ascent never ends below that
    configured attack's objective, the start is not the default one on these scenes, the settings
    are recorded, and unknown settings or settings without ``init="sector-iter"`` are refused."""
    from icpbench.attacks.pgd import PGDAttack

    settings = {"iterations": 1, "icp_iterations": 3}
    start = SectorIterAttack(**settings).run(batch, 0.3, surrogate=icp, generator=0).scans
    default = SectorIterAttack().run(batch, 0.3, surrogate=icp, generator=0).scans
    assert not torch.allclose(start, default, atol=1e-3)
    atk = PGDAttack(steps=1, init="sector-iter", init_params=settings, icp_iterations=3)
    out = atk.run(batch, 0.3, surrogate=icp, generator=0)
    surrogate = icp.with_max_iterations(3)
    assert torch.all(_xy_error(surrogate, batch, out.scans)
                     >= _xy_error(surrogate, batch, start) - 1e-9)
    assert out.stats["disp_max"].max() <= 0.3 + 1e-9
    assert atk.params["init_params"] == settings and "init_params" not in PGDAttack().params
    with pytest.raises(InputError, match="icp_iters"):
        PGDAttack(init="sector-iter", init_params={"icp_iters": 3})
    with pytest.raises(InputError, match="init_params"):
        PGDAttack(init="sector", init_params=settings)


def test_prior_icp_iterations_reach_the_prior(batch):
    """``GeneratorConfig.prior_icp_iterations`` is the cap of the prior's surrogate ICPs: the
    channels equal the attack run with that cap, differ from the default cap's on these scenes
    (the capped ICP has not converged after 2 iterations), and a cap below 1 is refused; configs
    written before the field load with the old cap, 25."""
    from icpbench.learning.network import GeneratorConfig, generator_config
    from icpbench.learning.prior import prior_channels

    surrogate = PointToPlaneICP()
    lam = torch.full((3,), 0.3)
    cfg = generator_config("objects", output="ball", prior="sector-iter", prior_dmax=5.0,
                           prior_iterations=2, prior_gain=1.0, prior_icp_iterations=2)
    ch = prior_channels(cfg, batch, lam, surrogate)[..., 0:3].double() * 0.3
    ref = SectorIterAttack(iterations=2, icp_iterations=2).run(batch, 0.3, surrogate=surrogate,
                                                                generator=0).scans - batch.scans
    torch.testing.assert_close(ch, ref, atol=1e-6, rtol=0)
    default = prior_channels(cfg.with_(prior_icp_iterations=25), batch, lam, surrogate)
    assert not torch.allclose(default[..., 0:3].double() * 0.3, ch, atol=1e-3)
    with pytest.raises(InputError, match="prior_icp_iterations"):
        cfg.with_(prior_icp_iterations=0)
    old = cfg.to_dict()
    del old["prior_icp_iterations"]
    assert GeneratorConfig.from_dict(old).prior_icp_iterations == 25


def test_icp_stride_subsamples_the_surrogate_only(batch, icp):
    """``icp_stride=k`` runs the surrogate on every k-th point: the reported surrogate error is
    that of the strided scan, the returned displacement still covers every point within lambda,
    and on these scenes the full-scan ICP error of the result stays close to the unstrided
    attack's (the attacked pose of a coherent field barely depends on the subsample).
    ``GeneratorConfig.prior_icp_stride`` reaches the prior; configs written before it load as 1."""
    from icpbench.learning.network import GeneratorConfig, generator_config
    from icpbench.learning.prior import prior_channels

    budget = 0.3
    full = SectorIterAttack(iterations=3).run(batch, budget, surrogate=icp, generator=0)
    out = SectorIterAttack(iterations=3, icp_stride=2).run(batch, budget, surrogate=icp, generator=0)
    with torch.no_grad():
        reg = icp.register(out.scans.to(torch.float64)[:, ::2], batch.maps, batch.T_init)
        e_strided = torch.linalg.norm(pose_error(reg.T, batch.T_gt)[:, :2], dim=-1)
    torch.testing.assert_close(out.extra["sector_iter_surrogate_xy"].to(torch.float64), e_strided,
                               atol=1e-9, rtol=0)
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    assert (torch.linalg.norm(out.scans - batch.scans, dim=-1) > 0.5 * budget).float().mean() > 0.5
    e_full, e_out = _xy_error(icp, batch, full.scans), _xy_error(icp, batch, out.scans)
    assert e_out.mean() > 0.95 * e_full.mean()  # the sector start alone reaches 0.86x
    with pytest.raises(InputError, match="icp_stride"):
        SectorIterAttack(icp_stride=0)

    lam = torch.full((3,), budget)
    cfg = generator_config("objects", output="ball", prior="sector-iter", prior_dmax=5.0,
                           prior_iterations=3, prior_gain=1.0, prior_icp_stride=2)
    ch = prior_channels(cfg, batch, lam, icp)[..., 0:3].double() * budget
    torch.testing.assert_close(ch, out.scans - batch.scans, atol=1e-6, rtol=0)
    with pytest.raises(InputError, match="prior_icp_stride"):
        cfg.with_(prior_icp_stride=0)
    old = cfg.to_dict()
    del old["prior_icp_stride"]
    assert GeneratorConfig.from_dict(old).prior_icp_stride == 1


def test_icp_nn_reuse_reaches_the_surrogate_and_keeps_the_budget(batch, icp, reuse_radii):
    """``icp_nn_reuse`` builds the surrogate with ``nn_reuse_m``: the attack still holds the
    budget exactly and stays close to the exact surrogate's attack on the exact ICP; the setting
    is recorded only when set, and a negative radius is refused."""
    budget = 0.3
    exact = SectorIterAttack(iterations=3).run(batch, budget, surrogate=icp, generator=0)
    assert reuse_radii and set(reuse_radii) == {0.0}
    reuse_radii.clear()
    att = SectorIterAttack(iterations=3, icp_nn_reuse=0.02)
    out = att.run(batch, budget, surrogate=icp, generator=0)
    assert reuse_radii and set(reuse_radii) == {0.02}
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    e_exact, e_out = _xy_error(icp, batch, exact.scans), _xy_error(icp, batch, out.scans)
    assert e_out.mean() > 0.9 * e_exact.mean()
    assert att.params["icp_nn_reuse"] == 0.02 and "icp_nn_reuse" not in SectorIterAttack().params
    with pytest.raises(InputError, match="icp_nn_reuse"):
        SectorIterAttack(icp_nn_reuse=-1.0)
