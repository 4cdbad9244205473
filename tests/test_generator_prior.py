"""The analytic prior channels of the generator (icpbench.learning.prior) and prior models."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.learning.network import Generator, add_prior, generator_config
from icpbench.learning.prior import PRIOR_CHANNELS, sector_prior, sector_prior_batch


@pytest.fixture(scope="module")
def batch() -> Batch:
    return Batch.from_samples([scene_sample(n_scan=1024, n_map=12000, seed=s) for s in (5, 6)])


def test_direction_channel_is_the_sector_attack(batch):
    """Channels 0:3 times lambda are exactly the sector attack's displacement (same gate)."""
    from icpbench.attacks.sector import SectorAttack

    lam = 0.4
    adv = SectorAttack(d_max=0.3).perturb(batch, lam)
    pr = sector_prior_batch(batch.scans, batch.T_gt, batch.maps)
    pr03 = torch.stack([torch.as_tensor(sector_prior(batch.scans[b].numpy(), batch.T_gt[b].numpy(),
                                                     batch.maps[b], d_max=0.3)) for b in range(2)])
    assert pr.shape == (2, 1024, PRIOR_CHANNELS) and pr.dtype == torch.float32
    torch.testing.assert_close((adv - batch.scans).float(), lam * pr03[..., 0:3], atol=2e-6, rtol=0)
    # unit normals where associated; direction = +-normal; sensitivities have mean |g| = 1
    valid = pr[..., 3:6].norm(dim=-1) > 0
    assert valid.float().mean() > 0.9
    torch.testing.assert_close(pr[..., 3:6].norm(dim=-1)[valid], torch.ones(int(valid.sum())))
    dot = (pr[..., 0:3] * pr[..., 3:6]).sum(-1)[valid]
    torch.testing.assert_close(dot.abs(), torch.ones_like(dot), atol=1e-5, rtol=0)
    for b in range(2):
        g = pr[b, valid[b], 6:8]
        torch.testing.assert_close(g.abs().mean(0), torch.ones(2), atol=1e-4, rtol=0)


@pytest.mark.parametrize("output, gain, scale", [("bounded", 1.5, np.tanh(1.5)), ("ball", 1.0, 1.0)])
def test_untrained_prior_model_is_the_sector_attack(batch, output, gain, scale):
    """Zero last layer: output = x + lambda * scale * d_prior, where the bounded squashing gives
    scale = tanh(gain) and the ball output (gain 1) gives the sector attack itself; unassociated
    points stay put."""
    cfg = generator_config("objects", output=output, prior="sector", prior_gain=gain)
    g = Generator(cfg).eval()
    x = batch.scans.float()
    pr = sector_prior_batch(batch.scans, batch.T_gt, batch.maps)
    lam = torch.tensor([0.3, 0.7])
    with torch.no_grad():
        out = g(x, g.precompute(x), lam, pr)
    expect = x + lam[:, None, None] * scale * pr[..., 0:3]
    torch.testing.assert_close(out, expect, atol=1e-5, rtol=0)


def test_add_prior_keeps_the_trained_function_and_learns(batch):
    """A widened model with zero prior channels gives the original output; the gain and the new
    input weights receive gradients."""
    torch.manual_seed(0)
    base = Generator(generator_config("objects", output="bounded", conditioned=True))
    with torch.no_grad():  # a 'trained' model: non-zero last layer
        base.head[-1].weight.normal_(0, 0.05)
    x = batch.scans.float()
    geo = base.precompute(x)
    lam = torch.tensor([0.3, 0.7])
    wide = add_prior(base, gain=2.0)
    zero = torch.zeros(2, x.shape[1], PRIOR_CHANNELS)
    torch.testing.assert_close(wide(x, geo, lam, zero), base(x, geo, lam), atol=1e-5, rtol=1e-5)
    pr = sector_prior_batch(batch.scans, batch.T_gt, batch.maps)
    loss = ((wide(x, geo, lam, pr) - x) * torch.randn_like(x)).sum()
    loss.backward()
    assert wide.prior_gain.grad is not None and wide.prior_gain.grad.abs() > 0
    assert wide.head[0].weight.grad[:, 259:259 + PRIOR_CHANNELS].abs().sum() > 0
    assert wide.sa[0].first.weight.grad[:, 3:].abs().sum() > 0


def test_prior_inputs_are_checked(batch):
    g = Generator(generator_config("objects", output="bounded", prior="sector"))
    x = batch.scans.float()
    geo = g.precompute(x)
    with pytest.raises(InputError, match="prior channels"):
        g(x, geo, torch.ones(2))
    plain = Generator(generator_config("objects", output="bounded"))
    with pytest.raises(InputError, match="no prior"):
        plain(x, geo, torch.ones(2), torch.zeros(2, x.shape[1], PRIOR_CHANNELS))
    with pytest.raises(InputError, match="bounded"):
        generator_config("objects", prior="sector")
