"""The compiled point-to-point forward pass registers as ``icp`` does (poses to rounding, the same
iteration counts and status), its candidate lists name the exact nearest neighbour, and query
attacks answered by it see the target's own errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.kiss import VoxelNeighbours
from icpbench.targets.kiss_replica import KissICPReplica
from icpbench.targets.p2point import PointToPointICP
from icpbench.targets.point_forward import (
    CANDIDATES,
    NO_VOXELS,
    CompiledPointICP,
    NearestRows,
    _assign,
    _search_lists,
    _voxel_rows,
)


def _attacked(batch: Batch, seed: int, share: float = 0.4, lift_m: float = 0.8) -> torch.Tensor:
    """Scans of the batch with a share of their points moved by up to ``lift_m`` in one heading
    (points lifted off the surfaces, where neighbours are nearly equidistant), a few far away
    (beyond the gate) and a few not finite."""
    rng = np.random.default_rng(seed)
    x = batch.scans.numpy().copy()
    for b in range(x.shape[0]):
        sub = rng.random(x.shape[1]) < share
        head = rng.normal(size=3)
        x[b, sub] += head / np.linalg.norm(head) * rng.uniform(0.1, lift_m, size=(sub.sum(), 1))
        x[b, rng.random(x.shape[1]) < 0.02] += 20.0  # beyond d_max: no correspondence
        x[b, rng.random(x.shape[1]) < 0.01] = np.nan
    return torch.as_tensor(x)


@pytest.fixture(scope="module")
def batch() -> Batch:
    return Batch.from_samples([scene_sample(1_500, 12_000, seed=s, noise_m=0.02) for s in range(3)])


@pytest.mark.parametrize("settings", [
    {}, {"kernel": "geman_mcclure", "cauchy_c": 0.5}, {"kernel": "huber", "cauchy_c": 0.3},
    {"kernel": "none"}, {"d_max": None}, {"d_max": 1.0, "max_iterations": 7}])
def test_compiled_pass_registers_as_icp(batch, settings):
    target = PointToPointICP("lidar", **settings)
    compiled = target.exact_replica()
    assert isinstance(compiled, CompiledPointICP)
    for seed in range(2):
        x = _attacked(batch, seed)
        ref, got = target.register(x, batch.maps, batch.T_init), compiled.register(
            x, batch.maps, batch.T_init)
        np.testing.assert_allclose(got.T.numpy(), ref.T.numpy(), rtol=0, atol=1e-9)
        np.testing.assert_array_equal(got.iterations.numpy(), ref.iterations.numpy())
        np.testing.assert_array_equal(got.converged.numpy(), ref.converged.numpy())
        np.testing.assert_array_equal(got.inlier_fraction.numpy(), ref.inlier_fraction.numpy())
        assert got.status == ref.status


def test_compiled_pass_on_duplicated_map_points_and_a_tiny_map():
    """Duplicated map points (equal distances: either row gives the same residual) and a map
    of fewer points than a candidate list holds."""
    s = scene_sample(800, 6_000, seed=4)
    pts = np.concatenate([s.map, s.map[:3_000]])  # every other point twice
    for m in (MapIndex(pts), MapIndex(s.map[:CANDIDATES - 2])):
        b = Batch.from_samples([s])
        target = PointToPointICP("lidar")
        x = _attacked(b, 5)
        ref = target.register(x, [m], b.T_init)
        got = target.exact_replica().register(x, [m], b.T_init)
        np.testing.assert_allclose(got.T.numpy(), ref.T.numpy(), rtol=0, atol=1e-9)
        assert got.status == ref.status and int(got.iterations) == int(ref.iterations)


def test_kiss_replica_compiled_registers_as_the_replica(batch):
    replica = KissICPReplica("lidar")
    compiled = CompiledPointICP(replica, replica.config, replica.kiss_map)
    x = _attacked(batch, 7)
    ref, got = replica.register(x, batch.maps, batch.T_init), compiled.register(
        x, batch.maps, batch.T_init)
    np.testing.assert_allclose(got.T.numpy(), ref.T.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got.iterations.numpy(), ref.iterations.numpy())
    assert got.status == ref.status


def test_candidate_lists_name_the_exact_nearest_neighbour_or_ask_again():
    """After a search at ref, points moved by 0-0.6 m: wherever the lists decide, the row is the
    brute-force nearest map point (or, beyond the gate, every map point is too far)."""
    rng = np.random.default_rng(0)
    table = rng.uniform(-5, 5, size=(3_000, 3))
    m = MapIndex(table)
    N, bound = 2_000, 0.4
    P = rng.uniform(-6, 6, size=(N, 3))
    finite = np.ones(N, dtype=bool)
    cand = np.full((N, CANDIDATES), len(table), dtype=np.int64)
    r_k, idx, need = np.full(N, -np.inf), np.full(N, len(table), dtype=np.int64), np.zeros(N, bool)
    ref = P.copy()
    _search_lists(m, P, np.arange(N), CANDIDATES, cand, r_k, idx)
    decided = 0
    for step in (0.0, 0.05, 0.2, 0.6):
        t = rng.normal(size=3)
        t *= step / np.linalg.norm(t)
        _assign(P, finite, np.eye(3), t, ref, cand, r_k, np.zeros(N, dtype=bool), np.zeros(N),
                table, bound, np.inf, idx, need, np.full(N, np.nan), *NO_VOXELS)
        q = P + t
        d = np.linalg.norm(q[:, None] - table[None], axis=2)
        ok = ~need
        exact = d.argmin(axis=1)
        near = d.min(axis=1) < bound
        assert np.array_equal(idx[ok & near], exact[ok & near])
        assert np.all(d[ok & ~near].min(axis=1) >= bound)  # decided "no correspondence": right
        decided += ok.sum()
    assert 0 < decided < 4 * N  # some decided, some asked again


def test_compiled_voxel_rule_is_kiss_s_search_and_holds_within_its_slack():
    """KISS's 27-voxel neighbour, compiled, names the NumPy search's row (the first of equal
    ones: every map point twice), and a point moved by less than its slack keeps that row (or,
    with its exact neighbour beyond the gate, stays beyond it)."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-5, 5, size=(1_500, 3))
    table = np.concatenate([pts, pts])  # ties: the first in the search's order wins
    vox = VoxelNeighbours(table, 0.7)
    N, bound = 40_000, 1.5
    q = rng.uniform(-7, 7, size=(N, 3))
    exact = MapIndex(table)
    d1 = exact.query(q)[0]
    q, d1 = q[d1 >= 0.7], d1[d1 >= 0.7]  # the rule answers points a voxel or more away
    n = len(q)
    idx, slack2 = np.full(n, -1, dtype=np.int64), np.full(n, np.nan)
    by_slack, low = np.zeros(n, dtype=bool), np.full(n, np.nan)
    _voxel_rows(q, np.arange(n), d1, vox.keys, vox.start, vox.count, vox.order, vox.stored,
                vox.voxel_size, bound, 0.7, idx, slack2, by_slack, low)
    assert by_slack.all() and np.array_equal(low, d1)
    gated = d1 > bound
    assert 0 < gated.sum() < n
    np.testing.assert_array_equal(idx[~gated], vox.query(q[~gated])[1])
    assert np.all(slack2 >= 0) and np.mean(slack2 > 0) > 0.5
    for share in (0.3, 0.99):
        step = rng.normal(size=(n, 3))
        step *= (share * np.sqrt(slack2) / np.linalg.norm(step, axis=1))[:, None]
        moved = q + step
        np.testing.assert_array_equal(vox.query(moved[~gated])[1], idx[~gated])
        assert np.all(exact.query(moved[gated])[0] > bound)
    # leaving the voxel changes the 27 voxels: B (exact, 1.15 m) enters them, A (1.3 m) is KISS's
    one = VoxelNeighbours(np.array([[0.9, 0.5, -0.8], [2.05, 0.5, 0.5]]), 1.0)
    idx, slack2 = np.full(1, -1, dtype=np.int64), np.full(1, np.nan)
    _voxel_rows(np.array([[0.9, 0.5, 0.5]]), np.arange(1), np.array([1.15]), one.keys, one.start,
                one.count, one.order, one.stored, 1.0, bound, 1.0, idx, slack2, np.zeros(1, bool),
                np.zeros(1))
    assert idx[0] == 0 and np.sqrt(slack2[0]) < 0.1 + 1e-12  # the voxel's face at x = 1
    assert one.query(np.array([[1.05, 0.5, 0.5]]))[1][0] == 1


def test_points_on_kiss_s_rule_are_answered_again_without_a_search():
    """A point a voxel or more from KISS's map that moved past its slack takes the voxel rule
    again in the assignment, without a tree search, while the way it moved still leaves it a
    voxel away: at every step its row is the one a search gives (the same lists with their
    distance bounds wiped: every such point searched), and fewer points are searched."""
    s = scene_sample(1_500, 12_000, seed=2)
    replica = KissICPReplica("lidar")
    m = replica.kiss_map(MapIndex(s.map))
    rng = np.random.default_rng(5)
    N, bound = 4_000, 1.5  # a gate some points come within as they move
    P = s.map[rng.choice(len(s.map), N)] + rng.normal(scale=1.5, size=(N, 3))
    finite = np.ones(N, dtype=bool)
    rows, searched = NearestRows(m, P, finite, bound), NearestRows(m, P, finite, bound)
    t, step = np.zeros(3), np.array([0.06, -0.04, 0.02])
    for _ in range(15):
        t = t + step
        got = rows.update(np.eye(3), t).copy()
        searched.low[:] = np.nan
        want = searched.update(np.eye(3), t)
        q, table = P + t, np.vstack([m.points, np.full((1, 3), np.inf)])  # row M: none
        near = np.linalg.norm(q - table[want], axis=1) <= bound
        np.testing.assert_array_equal(got[near], want[near])
        assert np.all(np.linalg.norm(q - table[got], axis=1)[~near] > bound)  # gated either way
    assert rows.searched < 0.7 * searched.searched


def test_queries_answered_by_the_compiled_pass_see_the_targets_errors(batch, answers_as_target):
    answers_as_target(PointToPointICP("lidar"), batch, 0.5, members="uniform,spoof,valley",
                      spoof_queries=4, valley_queries=3)


@pytest.mark.parametrize("make", [lambda: PointToPointICP("lidar"),
                                  lambda: KissICPReplica("lidar")], ids=["p2point", "kiss-replica"])
def test_the_implicit_gradient_takes_the_compiled_iterations_and_rows_stay_icps_own(
        scene_pair, make, monkeypatch):
    """A gradient attack's surrogate registration (implicit gradient) runs its iterations
    compiled: the same poses to rounding, the same iteration counts and the same gradient as
    PyTorch's iterations give; a registration without a gradient (a row) never does."""
    import icpbench.targets.icp as icp_module
    import icpbench.targets.point_forward as pf
    from icpbench.targets import forward_cache

    target = make().with_settings(backprop="implicit")
    batch = scene_pair
    x0 = _attacked(batch, 5).to(torch.float64)
    calls = []
    real = pf.register_point
    monkeypatch.setattr(pf, "register_point", lambda *a: calls.append(1) or real(*a))

    def gradient():
        forward_cache.clear()
        x = x0.clone().requires_grad_(True)
        reg = target.register(x, batch.maps, batch.T_init)
        (g,) = torch.autograd.grad((reg.T[:, :3, 3] ** 2).sum() + reg.T[:, 0, 1].sum(), x)
        return reg, torch.nan_to_num(g)

    reg_c, g_c = gradient()
    assert len(calls) == len(batch)  # one compiled registration per scan
    with torch.no_grad():  # a row: PyTorch's iterations, though the same scans were just registered
        row = target.register(x0, batch.maps, batch.T_init)
    assert len(calls) == len(batch)
    monkeypatch.setattr(icp_module, "_compiled_forward", lambda *a: False)
    reg_t, g_t = gradient()
    assert len(calls) == len(batch)
    np.testing.assert_allclose(reg_c.T.detach().numpy(), reg_t.T.detach().numpy(), rtol=0,
                               atol=1e-12)
    np.testing.assert_allclose(row.T.numpy(), reg_t.T.detach().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(reg_c.iterations.numpy(), reg_t.iterations.numpy())
    assert reg_c.status == reg_t.status
    assert float(g_t.abs().max()) > 0
    np.testing.assert_allclose(g_c.numpy(), g_t.numpy(), rtol=0, atol=1e-9 * float(g_t.abs().max()))
