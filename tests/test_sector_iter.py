"""The iterated analytic attack (icpbench/core/iterated_sector.py, attacks/sector_iter.py): its start
is the sector attack, it never returns less than that start on the surrogate, it finds more on
scenes where ICP moves, the budget holds exactly, it is deterministic, and one settings type serves
the attack, the generator's prior and PGD's start, which share one computation per batch."""

from __future__ import annotations

import pytest
import torch

from icpbench.attacks.sector import SectorAttack
from icpbench.attacks.sector_iter import SectorIterAttack
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.iterated_sector import SectorIterSettings
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


#: the fixture surrogate's own cap on exact correspondences (the defaults run 100 iterations)
EXACT25 = {"icp_iterations": 25, "icp_nn_reuse": 0.0}


def _fresh(batch):
    """The same samples in a new batch (an empty memo)."""
    return Batch.from_samples(batch.samples)


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
    out = SectorIterAttack(iterations=4, **EXACT25).run(batch, budget, surrogate=icp, generator=0)
    e_sec, e_it = _xy_error(icp, batch, sec), _xy_error(icp, batch, out.scans)
    assert torch.all(e_it >= e_sec - 1e-9)
    assert e_it.mean() > 1.1 * e_sec.mean()
    torch.testing.assert_close(out.extra["sector_iter_surrogate_xy"].to(torch.float64), e_it,
                               atol=1e-9, rtol=0)
    assert out.stats["disp_max"].max() <= budget + 1e-9
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    again = SectorIterAttack(iterations=4, **EXACT25).run(_fresh(batch), budget, surrogate=icp,
                                                         generator=99)
    assert torch.equal(out.scans, again.scans)  # no random stream enters it


def test_registered_and_checked(icp, batch):
    assert registry.attacks.get("sector-iter") is SectorIterAttack
    for bad in ({"iterations": -1}, {"step_size": 0.0}, {"step_size": 3.0},
                {"icp_iterations": 0}, {"d_max": -1.0}, {"icp_nn_reuse": -1.0}):
        with pytest.raises(InputError):
            SectorIterAttack(**bad)
        with pytest.raises(InputError):
            SectorIterSettings.from_mapping(bad)
    with pytest.raises(InputError, match="icp_iters"):
        SectorIterSettings.from_mapping({"icp_iters": 3})
    with pytest.raises(InputError, match="surrogate"):
        SectorIterAttack().run(batch, 0.3, generator=0)
    # the registered defaults are the settings type's defaults (what Table 1 runs)
    assert SectorIterAttack().params == SectorIterSettings().as_dict()


def test_ball_generator_with_iterated_prior_starts_as_the_attack(batch, icp):
    """A 'ball' generator with the sector-iter prior, gain 1 and its zero-initialised head returns
    the iterated attack's scans (to float32 rounding); a trained head moves no point beyond lambda
    and the prior needs its budget and surrogate."""
    from icpbench.learning.network import Generator, generator_config
    from icpbench.learning.prior import prior_channels

    cfg = generator_config("objects", output="ball", prior="sector-iter", prior_dmax=5.0,
                           prior_gain=1.0)
    settings = SectorIterSettings(iterations=3, **EXACT25)
    g = Generator(cfg).eval()
    lam = torch.tensor([0.3, 0.3, 0.5])
    x = batch.scans.float()
    pr = prior_channels(cfg, batch, lam, icp, settings)
    with torch.no_grad():
        out = g(x, g.precompute(x), lam, pr).double()
    for value in (0.3, 0.5):
        k = (lam == value).nonzero()[:, 0]
        sub = Batch.from_samples([batch.samples[i] for i in k.tolist()])
        ref = SectorIterAttack(iterations=3, **EXACT25).run(sub, value, surrogate=icp,
                                                            generator=0).scans
        torch.testing.assert_close(out[k] - batch.scans[k], ref - sub.scans, atol=1e-5, rtol=0)
    with torch.no_grad():
        g.head[-1].weight.normal_(0, 0.5)
        moved = g(x, g.precompute(x), lam, pr).double() - batch.scans
    assert (torch.linalg.norm(moved, dim=-1) <= lam[:, None] * (1 + 1e-5)).all()
    with pytest.raises(InputError, match="surrogate"):
        prior_channels(cfg, batch, lam, None)


def test_pgd_from_the_iterated_attack_never_falls_below_it(batch, icp):
    """``pgd`` with ``init="sector-iter"`` and its ``sector_iter`` settings: the ascent never ends
    below that start on its surrogate; the settings are recorded."""
    from icpbench.attacks.pgd import PGDAttack

    small = {"iterations": 2, **EXACT25}
    start = SectorIterAttack(**small).run(batch, 0.3, surrogate=icp, generator=0).scans
    sector = SectorIterAttack(iterations=0).run(batch, 0.3, surrogate=icp, generator=0).scans
    assert not torch.equal(start, sector)  # the settings reach the start
    atk = PGDAttack(steps=2, init="sector-iter", sector_iter=small, icp_iterations=25)
    out = atk.run(batch, 0.3, surrogate=icp, generator=0)
    assert torch.all(_xy_error(icp, batch, out.scans) >= _xy_error(icp, batch, start) - 1e-9)
    assert out.stats["disp_max"].max() <= 0.3 + 1e-9
    assert atk.params["sector_iter"] == SectorIterSettings(**small).as_dict()


def test_one_computation_serves_the_attack_the_prior_and_pgd(batch, icp, reuse_radii):
    """In one batch the ``sector-iter`` row, the generator's prior and PGD's start with the same
    settings run the iterated attack once: the later users issue no surrogate ICP for it, get the
    same displacement and report the reused time."""
    from icpbench.attacks.pgd import PGDAttack
    from icpbench.learning.network import generator_config
    from icpbench.learning.prior import prior_channels

    b, budget, settings = _fresh(batch), 0.3, {"iterations": 2, **EXACT25}
    first = SectorIterAttack(**settings).run(b, budget, surrogate=icp, generator=0)
    n_icp = len(reuse_radii)
    assert n_icp > 0 and float(first.extra["reused_s"].max()) == 0.0
    again = SectorIterAttack(**settings).run(b, budget, surrogate=icp, generator=0)
    assert len(reuse_radii) == n_icp and torch.equal(again.scans, first.scans)
    assert float(again.extra["reused_s"].min()) > 0.0
    cfg = generator_config("objects", output="ball", prior="sector-iter", prior_dmax=5.0)
    ch = prior_channels(cfg, b, torch.full((len(b),), budget, dtype=torch.float64), icp,
                        SectorIterSettings(**settings))
    assert len(reuse_radii) == n_icp
    torch.testing.assert_close(ch[..., 0:3].double() * budget, first.scans - b.scans, atol=1e-6,
                               rtol=0)
    start = PGDAttack(steps=1, init="sector-iter", sector_iter=settings, icp_iterations=25)
    start.run(b, budget, surrogate=icp, generator=0)
    assert all(r == 0.0 for r in reuse_radii)  # only the ascent's own ICPs ran


def test_icp_nn_reuse_reaches_the_surrogate_and_keeps_the_budget(batch, icp, reuse_radii):
    """``icp_nn_reuse`` builds the surrogate with ``nn_reuse_m``: the attack still holds the
    budget exactly and stays close to the exact surrogate's attack on the exact ICP."""
    budget = 0.3
    exact = SectorIterAttack(iterations=3, **EXACT25).run(_fresh(batch), budget, surrogate=icp,
                                                          generator=0)
    assert reuse_radii and set(reuse_radii) == {0.0}
    reuse_radii.clear()
    att = SectorIterAttack(iterations=3, icp_iterations=25, icp_nn_reuse=0.02)
    out = att.run(_fresh(batch), budget, surrogate=icp, generator=0)
    assert reuse_radii and set(reuse_radii) == {0.02}
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    e_exact, e_out = _xy_error(icp, batch, exact.scans), _xy_error(icp, batch, out.scans)
    assert e_out.mean() > 0.9 * e_exact.mean()
    assert att.params["icp_nn_reuse"] == 0.02
