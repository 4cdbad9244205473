"""The generator's no-autograd fast path (icpbench.learning.fast) equals the autograd path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.learning import fast
from icpbench.learning.network import Generator, generator_config

torch.set_num_threads(1)


def _cloud(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-20.0, 20.0, (n, 3))
    p[:, 2] = rng.normal(0.0, 0.5, n) + (rng.random(n) < 0.3) * rng.uniform(0, 5, n)
    return p.astype(np.float32)


def _randomised(cfg, seed: int = 0) -> Generator:
    """A generator with every parameter drawn at random (zero-initialised layers included), so
    every branch (negative GroupNorm scales, budget channel, prior) matters."""
    G = Generator(cfg).eval()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in G.parameters():
            fan_in = p[0].numel() if p.ndim > 1 else 1
            p.copy_(torch.randn(p.shape, generator=gen) / fan_in**0.5)
    return G


@pytest.mark.parametrize("overrides", [
    {"output": "bounded", "conditioned": True},
    {"output": "residual"},
    {"output": "bounded", "conditioned": True, "prior": "sector"},
    {"output": "ball", "conditioned": True, "prior": "sector-iter", "prior_gain": 1.0},
    {"output": "absolute"},
])
def test_fast_path_equals_the_autograd_path(overrides):
    G = _randomised(generator_config("lidar", **overrides))
    x = torch.as_tensor(np.stack([_cloud(1, 1_200), _cloud(2, 1_200)]))
    geo = G.precompute(x)
    budget = torch.tensor([1.0, 4.0]) if G.needs_budget else None
    prior = (torch.randn(2, 1_200, 8, generator=torch.Generator().manual_seed(3))
             if G.needs_prior else None)
    assert any(bool((n.weight < 0).any()) for n in G.modules() if isinstance(n, torch.nn.GroupNorm))
    with torch.no_grad():
        assert fast.eligible(G, x)
        got = G(x, geo, budget, prior)
        ref = G.decode(x, geo, G.encode(x, geo, prior), budget, prior=prior)  # autograd layers
        again = G(x, geo, budget, prior)  # workspace reused
    scale = float((ref - x).abs().max())
    assert scale > 1e-2  # the network does move points
    torch.testing.assert_close(got, ref, rtol=0, atol=2e-5 * max(scale, 1.0))
    assert torch.equal(got, again)
    with torch.enable_grad():
        assert not fast.eligible(G, x)  # training keeps the autograd path


def test_shipped_lidar_generator_output_is_unchanged():
    """The shipped lidar-sim model on a lidar-sim test scan, with the prior channels the generator
    attack gives it (its own ``prior`` kind; for ``sector-iter`` the iterated attack with its default
    settings through the lidar ICP): the fast path agrees with the autograd path within float32
    rounding (measured 4e-6 m at displacements up to 4 m)."""
    from icpbench.attacks.generator import resolve_checkpoint
    from icpbench.core import registry
    from icpbench.core.types import Batch
    from icpbench.learning.checkpoint import load_checkpoint
    from icpbench.learning.prior import prior_channels
    from icpbench.targets.p2plane import PointToPlaneICP

    model = load_checkpoint(resolve_checkpoint("lidar-sim", 1.0)).model.eval()
    batch = Batch.from_samples([registry.datasets.get("lidar-sim")(seed=0, split="test")[0]])
    x = batch.scans.to(torch.float32)
    geo = model.precompute(x)
    budget = torch.tensor([4.0])
    prior = prior_channels(model.config, batch, budget, PointToPlaneICP("lidar"))
    assert (prior is not None) == model.needs_prior
    with torch.no_grad():
        got = model(x, geo, budget, prior)
        ref = model.decode(x, geo, model.encode(x, geo, prior), budget, prior=prior)
    assert float((ref - x).norm(dim=-1).max()) > 1.0
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-4)


def test_fast_path_with_zero_norm_scales():
    """A GroupNorm channel with weight 0 outputs the constant relu(bias): the folded clamp of the
    fast path must keep that constant (its threshold -b/a does not exist)."""
    G = _randomised(generator_config("lidar", output="bounded", conditioned=True), seed=5)
    with torch.no_grad():
        for n in G.modules():
            if isinstance(n, torch.nn.GroupNorm):
                n.weight[::3] = 0.0
                n.bias[::3] = torch.linspace(-1.0, 1.0, n.bias[::3].numel())
    x = torch.as_tensor(np.stack([_cloud(4, 1_200)]))
    geo, budget = G.precompute(x), torch.tensor([2.0])
    with torch.no_grad():
        got = G(x, geo, budget)
        ref = G.decode(x, geo, G.encode(x, geo), budget)
    scale = float((ref - x).abs().max())
    assert scale > 1e-2
    torch.testing.assert_close(got, ref, rtol=0, atol=2e-5 * max(scale, 1.0))
