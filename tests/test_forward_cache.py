"""The per-sample cache of ICP forward passes (icpbench/targets/forward_cache.py): a cached result
is exactly the computed one (poses, status, iterations, inliers, and the implicit gradient), a
batch mixing cached and new samples equals its uncached registration, and what must not be cached
(an unrolled graph, approximate correspondences) is not."""

from __future__ import annotations

import pytest
import torch

from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets import forward_cache
from icpbench.targets.p2plane import PointToPlaneICP


@pytest.fixture()
def batch():
    forward_cache.clear()
    b = Batch.from_samples([scene_sample(400, 4_000, seed=s, noise_m=0.02) for s in range(3)])
    gen = torch.Generator().manual_seed(0)
    moved = b.scans + 0.3 * torch.randn(b.scans.shape, generator=gen, dtype=b.scans.dtype)
    return b, moved


def _same(a, b):
    assert torch.equal(a.T, b.T) and a.status == b.status
    assert torch.equal(a.iterations, b.iterations) and torch.equal(a.converged, b.converged)
    assert torch.equal(a.inlier_fraction, b.inlier_fraction)


def test_cached_forward_is_the_computed_one(batch):
    b, scans = batch
    icp = PointToPlaneICP("lidar", max_iterations=30)
    with forward_cache.disabled():
        ref = icp.register(scans, b.maps, b.T_init)
    assert forward_cache.size() == 0
    first = icp.register(scans, b.maps, b.T_init)
    assert forward_cache.size() == 3
    again = icp.register(scans, b.maps, b.T_init)
    _same(ref, first)
    _same(ref, again)
    # other settings, another initial pose or another scan are other entries
    icp.with_max_iterations(10).register(scans, b.maps, b.T_init)
    assert forward_cache.size() == 6
    mixed = scans.clone()
    mixed[1] += 0.05
    with forward_cache.disabled():
        ref_mixed = icp.register(mixed, b.maps, b.T_init)
    got = icp.register(mixed, b.maps, b.T_init)  # samples 0 and 2 from the cache, 1 computed alone
    assert forward_cache.size() == 7
    # a sample computed alone rounds like one computed in a batch only to ~1e-16
    torch.testing.assert_close(got.T, ref_mixed.T, atol=1e-12, rtol=0)
    assert got.status == ref_mixed.status and torch.equal(got.iterations, ref_mixed.iterations)


def test_implicit_gradient_from_a_cached_pass_is_the_computed_one(batch):
    b, scans = batch
    icp = PointToPlaneICP("lidar", max_iterations=30).with_settings(backprop="implicit")

    def pose_and_grad():
        x = scans.clone().requires_grad_(True)
        T = icp.register(x, b.maps, b.T_init).T
        return T.detach(), torch.autograd.grad(T[:, :2, 3].sum(), x)[0]

    with forward_cache.disabled():
        T0, g0 = pose_and_grad()
    T1, g1 = pose_and_grad()  # computed, stored
    T2, g2 = pose_and_grad()  # from the cache: no iterations run
    assert forward_cache.size() == 3
    assert torch.equal(T0, T1) and torch.equal(T0, T2)
    assert torch.equal(g0, g1) and torch.equal(g0, g2) and float(g0.abs().max()) > 0
    # the plain (no-grad) evaluation shares the entry: backprop does not change the forward pass
    plain = PointToPlaneICP("lidar", max_iterations=30).register(scans, b.maps, b.T_init)
    assert torch.equal(plain.T, T0) and forward_cache.size() == 3


def test_unrolled_graphs_and_approximate_search_are_not_cached(batch):
    b, scans = batch
    unrolled = PointToPlaneICP("lidar", max_iterations=10)
    x = scans.clone().requires_grad_(True)
    T = unrolled.register(x, b.maps, b.T_init).T
    (g,) = torch.autograd.grad(T[:, :2, 3].sum(), x)
    assert float(g.abs().max()) > 0 and forward_cache.size() == 0
    PointToPlaneICP("lidar", max_iterations=10, nn_reuse_m=0.05).register(scans, b.maps, b.T_init)
    assert forward_cache.size() == 0


def test_a_black_box_registration_asked_for_again_comes_from_the_cache(batch):
    # the ensemble's best scan is registered by its query and again for its row: the library
    # runs once; another scan, initial pose or setting runs it again; a random library never
    from icpbench.targets.small_gicp import SmallGICPTarget

    b, scans = batch
    calls = []

    class Counted(SmallGICPTarget):
        def _register_one(self, scan, target, T0):
            calls.append(1)
            return super()._register_one(scan, target, T0)

    gicp = Counted("lidar")
    maps = [gicp.prepare(s.map, s.map_normals) for s in b.samples]
    with forward_cache.disabled():
        ref = gicp.register(scans, maps, b.T_init)
    assert len(calls) == 3 and forward_cache.size() == 0
    first = gicp.register(scans, maps, b.T_init)
    assert len(calls) == 6 and forward_cache.size() == 3
    again = gicp.register(scans, maps, b.T_init)
    assert len(calls) == 6
    _same(ref, first)
    _same(ref, again)
    gicp.register(scans.to(torch.float32).to(scans.dtype), maps, b.T_init)  # rounded: other scans
    assert len(calls) == 9
    other = b.T_init.clone()
    other[:, 0, 3] += 0.01
    gicp.register(scans, maps, other)  # other initial poses
    Counted("lidar", max_iterations=10).register(scans, maps, b.T_init)  # other settings
    assert len(calls) == 15 and forward_cache.size() == 12

    class Random(Counted):
        deterministic = False

    Random("lidar").register(scans, maps, b.T_init)
    Random("lidar").register(scans, maps, b.T_init)
    assert len(calls) == 21 and forward_cache.size() == 12
