"""Foundation must-shows for the differentiable ICP targets."""

import numpy as np
import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.p2plane import PointToPlaneICP
from icpbench.targets.p2point import PointToPointICP

SCENE_SCALE_M = 80.0  # side of the synthetic scene's ground square


def _run(target, samples):
    batch = Batch.from_samples(samples)
    reg = target.register(batch.scans, batch.maps, batch.T_init)
    return reg, pose_error_components(reg.T, batch.T_gt)


@pytest.mark.parametrize("cls", [PointToPlaneICP, PointToPointICP])
def test_recovers_known_transform_on_lidar_like_scene(cls):
    samples = [scene_sample(2_000, 20_000, seed=s, scan_from_map=True) for s in range(3)]
    reg, err = _run(cls("lidar", d_max=2.0, tol=1e-8, max_iterations=150), samples)
    assert reg.converged.all(), reg.status
    assert (err["trans_err"] < 1e-3 * SCENE_SCALE_M).all(), err["trans_err"]
    assert (torch.rad2deg(err["rot_err"]) < 0.05).all(), err["rot_err"]
    # With an exact solution available the error is far below the bar.
    assert err["trans_err"].max() < 1e-4


def test_p2plane_recovers_from_independent_samples():
    """Scan and map are independent surface samples (no exact solution): still cm-level."""
    samples = [scene_sample(2_000, 20_000, seed=s) for s in range(3)]
    reg, err = _run(PointToPlaneICP("lidar", d_max=2.0), samples)
    assert reg.converged.all()
    assert (err["trans_err"] < 1e-3 * SCENE_SCALE_M).all()
    assert (torch.rad2deg(err["rot_err"]) < 0.05).all()


@pytest.mark.parametrize("cls", [PointToPlaneICP, PointToPointICP])
def test_batch_equals_one_by_one(cls):
    samples = [scene_sample(1_000, 10_000, seed=s, noise_m=0.02) for s in range(3)]
    tgt = cls("lidar", d_max=2.0)
    reg_b, _ = _run(tgt, samples)
    for i, s in enumerate(samples):
        reg_1, _ = _run(tgt, [s])
        np.testing.assert_allclose(reg_b.T[i].numpy(), reg_1.T[0].numpy(), atol=1e-12)
        assert int(reg_b.iterations[i]) == int(reg_1.iterations[0])


def _weighted_pose_error(target, batch, scans):
    """A fixed weighted sum of the six pose-error components of ``target`` on ``scans``, and the
    registration (the scalar whose gradient the finite-difference tests check)."""
    reg = target.register(scans, batch.maps, batch.T_init)
    e = pose_error_components(reg.T, batch.T_gt)
    xi = torch.stack([e[k] for k in ("rho_x", "rho_y", "rho_z", "phi_x", "phi_y", "phi_z")], -1)
    w = torch.tensor([1.0, -0.7, 0.3, 2.0, 1.0, -3.0], dtype=torch.float64)
    return (xi * w).sum(), reg


def _assert_central_differences(loss, scans, grad, *, draws, rtol, min_checked):
    """Compare ``grad`` (1, N, 3) with central differences (eps 1e-6) of the scalar ``loss(scans)``
    at ``draws`` random coordinates of the first 300 points (seed 0); pairs that are both ~0 are
    skipped, at least ``min_checked`` must be compared."""
    rng = np.random.default_rng(0)
    eps, checked = 1e-6, 0
    for _ in range(draws):
        i, k = int(rng.integers(0, 300)), int(rng.integers(0, 3))
        xp, xm = scans.clone(), scans.clone()
        xp[0, i, k] += eps
        xm[0, i, k] -= eps
        with torch.no_grad():
            fd = float((loss(xp) - loss(xm)) / (2 * eps))
        g = float(grad[0, i, k])
        if abs(fd) < 1e-7 and abs(g) < 1e-7:
            continue
        assert abs(fd - g) / max(abs(fd), abs(g)) < rtol, (i, k, fd, g)
        checked += 1
    assert checked >= min_checked


@pytest.mark.parametrize("cls", [PointToPlaneICP, PointToPointICP])
def test_gradient_matches_finite_differences(cls):
    """d(pose error)/d(scan points), float64, hard d_max filter, association fixed by small eps."""
    s = scene_sample(300, 4_000, seed=7, noise_m=0.01)
    tgt = cls("lidar", d_max=1.5, cauchy_c=0.5, max_iterations=8, tol=1e-14)
    batch = Batch.from_samples([s])

    def loss(scans):
        return _weighted_pose_error(tgt, batch, scans)[0]

    x = batch.scans.clone().requires_grad_(True)
    loss(x).backward()
    _assert_central_differences(loss, batch.scans, x.grad, draws=12, rtol=1e-3, min_checked=8)


@pytest.mark.parametrize("cls", [PointToPlaneICP, PointToPointICP])
def test_implicit_gradient_is_the_derivative_of_the_converged_pose(cls):
    """backprop="implicit": same pose as the unrolled ICP; its gradient equals central finite
    differences of the converged pose and the unrolled gradient once the iterations converged."""
    s = scene_sample(300, 4_000, seed=7, noise_m=0.01)
    settings = dict(d_max=1.5, cauchy_c=0.5, max_iterations=200, tol=1e-13)
    implicit, unrolled = cls("lidar", backprop="implicit", **settings), cls("lidar", **settings)
    batch = Batch.from_samples([s])

    def loss(target, scans):
        return _weighted_pose_error(target, batch, scans)

    x_i = batch.scans.clone().requires_grad_(True)
    l_i, reg = loss(implicit, x_i)
    l_i.backward()
    assert bool(reg.converged.all())
    x_u = batch.scans.clone().requires_grad_(True)
    l_u, _ = loss(unrolled, x_u)
    l_u.backward()
    # the pose value is untouched (point-to-point's iterations run compiled: equal to rounding)
    assert abs(float(l_i.detach()) - float(l_u.detach())) <= 1e-13 * abs(float(l_u.detach()))
    assert float((x_i.grad - x_u.grad).norm() / x_u.grad.norm()) < 1e-5
    _assert_central_differences(lambda scans: loss(implicit, scans)[0], batch.scans, x_i.grad,
                                draws=10, rtol=1e-4, min_checked=6)


def test_implicit_backprop_gives_a_gradient_and_checks_its_name():
    """The implicit mode still yields a differentiable pose (finite, non-zero gradient) and a bad
    mode name is refused."""
    s = scene_sample(300, 4_000, seed=3, noise_m=0.01)
    batch = Batch.from_samples([s])
    x = batch.scans.clone().requires_grad_(True)
    reg = PointToPlaneICP("lidar", d_max=1.5, backprop="implicit").register(x, batch.maps,
                                                                           batch.T_init)
    assert reg.T.requires_grad
    reg.T[:, :3, 3].sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    with pytest.raises(InputError, match="backprop"):
        PointToPlaneICP("lidar", backprop="one-step")


def test_soft_gate_is_differentiable_and_close_to_hard():
    s = scene_sample(500, 5_000, seed=3, noise_m=0.01)
    batch = Batch.from_samples([s])
    hard = PointToPlaneICP("lidar", d_max=2.0).register(batch.scans, batch.maps, batch.T_init)
    x = batch.scans.clone().requires_grad_(True)
    soft = PointToPlaneICP("lidar", d_max=2.0, soft_dmax=True).register(x, batch.maps, batch.T_init)
    soft.T[:, :3, 3].sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    assert torch.linalg.norm(hard.T[0, :3, 3] - soft.T[0, :3, 3].detach()) < 0.05


def test_nonfinite_points_are_ignored_and_bad_shapes_raise():
    s = scene_sample(1_000, 10_000, seed=1)
    batch = Batch.from_samples([s])
    scans = batch.scans.clone()
    scans[0, :50] = float("nan")
    reg = PointToPlaneICP("lidar", d_max=2.0).register(scans, batch.maps, batch.T_init)
    err = pose_error_components(reg.T, batch.T_gt)
    assert torch.isfinite(reg.T).all() and err["trans_err"][0] < 0.05
    with pytest.raises(InputError, match="shape"):
        PointToPlaneICP().register(batch.scans[0], batch.maps, batch.T_init)
    with pytest.raises(InputError, match="maps"):
        PointToPlaneICP().register(batch.scans, batch.maps * 2, batch.T_init)


def test_degenerate_scan_is_flagged_not_crashing():
    """A planar scan (ground only) leaves x, y and yaw unconstrained: flagged, finite."""
    s = scene_sample(1_000, 10_000, seed=2)
    batch = Batch.from_samples([s])
    ground = batch.scans.clone()
    ground[..., 2] = 0.0
    maps = [PointToPlaneICP().prepare(np.c_[np.random.default_rng(0).uniform(-30, 30, (5000, 2)),
                                            np.zeros(5000)],
                                      np.tile([0.0, 0.0, 1.0], (5000, 1)))]
    reg = PointToPlaneICP("lidar").register(ground, maps, batch.T_init)
    assert torch.isfinite(reg.T).all()
    assert reg.status[0] == "singular" and not bool(reg.converged[0])


def test_correspondence_cache_returns_the_nearest_neighbour_of_every_point():
    """The ICP re-queries only points that moved more than half their d2 - d1 gap; after any
    sequence of small and large moves every point still has its true nearest map point."""
    from icpbench.core.mapindex import MapIndex
    from icpbench.targets.icp import _Correspondences

    rng = np.random.default_rng(0)
    s = scene_sample(2_000, 5_000, seed=4)
    maps = [MapIndex(s.map, s.map_normals)] * 2  # the same map twice: one table entry
    p = torch.as_tensor(np.stack([s.scan, s.scan[::-1]]), dtype=torch.float64)  # (2, N, 3)
    p[1, :7] = float("nan")
    finite = torch.isfinite(p).all(-1)
    nn = _Correspondences(maps, torch.nan_to_num(p), finite, torch.float64)
    q = torch.nan_to_num(p).transpose(1, 2).contiguous()  # (B, 3, N)
    skipped = 0
    for step in (0.5, 1e-3, 1e-4, 0.05, 1e-5, 2.0, 1e-6):
        q = q + torch.as_tensor(rng.normal(0, step, (2, 3, 1)) + rng.normal(0, step / 10, q.shape))
        before = nn.queried
        idx = nn.update(q, torch.ones(2, dtype=torch.bool)).numpy()
        skipped += 2 * p.shape[1] - (nn.queried - before)
        for b in range(2):
            _, want = maps[b].query(q[b].T.numpy())
            got = idx[b] - nn.offsets[b]
            assert np.array_equal(got[finite[b].numpy()], want[finite[b].numpy()])
            assert (got[~finite[b].numpy()] == len(maps[b])).all()  # sentinel row
    assert skipped > 2 * p.shape[1]  # the cache really saved queries


def test_correspondence_cache_requeries_points_whose_two_nearest_were_tied():
    """A point whose nearest and second-nearest map points were equally far (a duplicated map
    point; d2 - d1 = 0 leaves no slack) is asked again after any move, so it still gets its true
    nearest map point once it has moved away from the duplicate."""
    from icpbench.core.mapindex import MapIndex
    from icpbench.targets.icp import _Correspondences

    rng = np.random.default_rng(2)
    s = scene_sample(500, 5_000, seed=4)
    twins = s.map[rng.choice(len(s.map), 500, replace=False)]
    m = MapIndex(np.vstack([s.map, twins]))  # every twin is a duplicate of a map point
    p = torch.as_tensor(twins[None].copy())  # (1, N, 3): each point on a duplicated map point
    finite = torch.ones(1, 500, dtype=torch.bool)
    nn = _Correspondences([m], p, finite, torch.float64)
    q = p.transpose(1, 2).contiguous()
    for step in (0.0, 0.3, 0.05, 0.2):
        q = q + torch.as_tensor(rng.normal(0, step, q.shape))
        got = nn.update(q, torch.ones(1, dtype=torch.bool)).numpy()[0]
        want, _ = m.query(q[0].T.numpy())
        have = np.linalg.norm(m.points[got] - q[0].T.numpy(), axis=1)
        np.testing.assert_allclose(have, want, rtol=0, atol=1e-12)  # a tie may name either twin


def test_correspondence_cache_beyond_the_bound_never_changes_which_points_count():
    """With a query bound, points whose nearest map point is beyond it may keep a stale row while
    they move less than the excess; every point within the bound still gets its true nearest map
    point, and every stale row stays beyond the bound (so the ICP gives it no weight)."""
    from icpbench.core.mapindex import MapIndex
    from icpbench.targets.icp import _Correspondences

    rng = np.random.default_rng(1)
    s = scene_sample(2_000, 5_000, seed=4)
    maps = [MapIndex(s.map, s.map_normals)]
    p = torch.as_tensor(s.scan[None] + rng.normal(0, 3.0, (1, 2_000, 3)))  # many far points
    bound = 1.0
    finite = torch.ones(1, 2_000, dtype=torch.bool)
    nn = _Correspondences(maps, p, finite, torch.float64, bound=bound)
    plain = _Correspondences(maps, p, finite, torch.float64)
    q = p.transpose(1, 2).contiguous()
    saved, stale = 0, 0
    for step in (0.3, 0.05, 1e-3, 0.2, 1e-4, 0.5, 1e-2):
        q = q + torch.as_tensor(rng.normal(0, step, (1, 3, 1)) + rng.normal(0, step / 10, q.shape))
        b0, b1 = nn.queried, plain.queried
        got = nn.update(q, torch.ones(1, dtype=torch.bool)).numpy()[0]
        plain.update(q, torch.ones(1, dtype=torch.bool))
        saved += (plain.queried - b1) - (nn.queried - b0)
        dist, want = maps[0].query(q[0].T.numpy())
        near = dist < bound
        assert np.array_equal(got[near], want[near])
        d_got = np.linalg.norm(maps[0].points[got[~near]] - q[0].T.numpy()[~near], axis=1)
        assert (d_got > bound).all()
        stale += int((got[~near] != want[~near]).sum())
    assert saved > 0 and stale > 0  # the rule was used, and it did leave stale rows


def test_icp_result_does_not_depend_on_the_far_point_rule(monkeypatch):
    """A scan with many points beyond d_max registers to exactly the same pose whether far points
    are re-queried every iteration or kept while they cannot come within the bound."""
    import icpbench.targets.icp as icp_mod

    s = scene_sample(3_000, 8_000, seed=2)
    scan = s.scan.copy()
    scan[::3] += np.random.default_rng(0).normal(0, 6.0, (len(scan[::3]), 3))  # clutter
    batch = Batch.from_samples([s])
    x = torch.as_tensor(scan[None])
    target = PointToPlaneICP("lidar")
    maps = [target.prepare(s.map, s.map_normals)]
    with_rule = target.register(x, maps, batch.T_init)
    real = icp_mod._Correspondences

    class Plain(real):
        def __init__(self, *args, bound=np.inf, **kw):
            super().__init__(*args, **kw)

    monkeypatch.setattr(icp_mod, "_Correspondences", Plain)
    without = target.register(x, maps, batch.T_init)
    assert torch.equal(with_rule.T, without.T)
    assert torch.equal(with_rule.iterations, without.iterations)


def test_candidate_lists_name_the_nearest_row_within_the_bound_and_search_less():
    """The correspondence search with candidate lists: after any sequence of moves every point
    within the bound has its true nearest map point, every stale row lies beyond the bound, and
    fewer points are searched than with the slack alone; lists refuse ``nn_reuse_m``."""
    from icpbench.core.mapindex import MapIndex
    from icpbench.targets.icp import _Correspondences

    rng = np.random.default_rng(5)
    s = scene_sample(2_000, 5_000, seed=4)
    maps = [MapIndex(s.map, s.map_normals)] * 2
    p = torch.as_tensor(np.stack([s.scan, s.scan[::-1]]) + rng.normal(0, 1.0, (2, 2_000, 3)))
    p[1, :5] = float("nan")
    finite = torch.isfinite(p).all(-1)
    p = torch.nan_to_num(p)
    bound = 1.0
    nn = _Correspondences(maps, p, finite, torch.float64, bound=bound, lists=True)
    plain = _Correspondences(maps, p, finite, torch.float64, bound=bound)
    q = p.transpose(1, 2).contiguous()
    for step in (0.3, 1e-3, 0.05, 1e-4, 0.5, 1e-2):
        q = q + torch.as_tensor(rng.normal(0, step, (2, 3, 1)) + rng.normal(0, step / 10, q.shape))
        got = nn.update(q, torch.ones(2, dtype=torch.bool)).numpy()
        plain.update(q, torch.ones(2, dtype=torch.bool))
        for b in range(2):
            f = finite[b].numpy()
            dist, want = maps[b].query(q[b].T.numpy())
            rows = got[b] - nn.offsets[b]
            near = f & (dist < bound)
            assert np.array_equal(rows[near], want[near])
            far = f & ~near
            assert (np.linalg.norm(s.map[rows[far]] - q[b].T.numpy()[far], axis=1) > bound).all()
            assert (rows[~f] == len(maps[b])).all() and not nn.found[b, ~f].any()
    assert 0 < nn.queried < plain.queried
    with pytest.raises(InputError, match="nn_reuse_m"):
        _Correspondences(maps, p, finite, torch.float64, reuse=0.05, lists=True)


@pytest.mark.parametrize("kiss", [False, True])
def test_candidate_lists_give_the_same_registration_and_gradient(monkeypatch, kiss):
    """Point-to-point ICP (and KISS-ICP's replica, with its voxel rule) registers an attacked
    scan to the same pose, iterations and scan gradient with the candidate lists as with the
    slack search alone."""
    import icpbench.targets.icp as icp_mod
    from icpbench.targets.kiss_replica import KissICPReplica
    from icpbench.targets.point_forward import NearestRows

    s = scene_sample(2_000, 8_000, seed=6)
    rng = np.random.default_rng(1)
    scan = s.scan.copy()
    lift = rng.random(len(scan)) < 0.4
    scan[lift] += rng.uniform(0.1, 0.9, (lift.sum(), 1)) * np.array([0.6, 0.8, 0.0])
    batch = Batch.from_samples([s])
    target = KissICPReplica("lidar") if kiss else PointToPointICP("lidar")
    calls = []
    real = NearestRows.update_at
    monkeypatch.setattr(NearestRows, "update_at", lambda self, Q: calls.append(1) or real(self, Q))

    def run():
        x = torch.as_tensor(scan[None]).requires_grad_(True)
        reg = target.register(x, batch.maps, batch.T_init)
        (g,) = torch.autograd.grad(reg.T[:, :3, 3].norm(), x)
        return reg, g

    with_lists, g_lists = run()
    assert calls  # the lists decided
    monkeypatch.setattr(icp_mod, "_lists", lambda cfg, mode: False)
    n = len(calls)
    slack, g_slack = run()
    assert len(calls) == n
    assert torch.equal(with_lists.T, slack.T) and torch.equal(g_lists, g_slack)
    assert torch.equal(with_lists.iterations, slack.iterations)


@pytest.mark.parametrize("kernel", ["cauchy", "huber", "geman_mcclure"])
def test_plane_backward_matches_autograd_of_the_formula(kernel):
    """The hand-written backward of the point-to-plane normal equations equals autograd of the
    same formula, with and without the robust kernel, with and without a gradient on H."""
    from icpbench.targets.icp import _PlaneNormalEquations, kernel_weight

    gen = torch.Generator().manual_seed(0)
    B, N = 3, 50
    q = torch.randn(B, 3, N, generator=gen, dtype=torch.float64, requires_grad=True)
    m = torch.randn(B, 3, N, generator=gen, dtype=torch.float64)
    n = torch.nn.functional.normalize(torch.randn(B, 3, N, generator=gen, dtype=torch.float64), dim=1)
    mask = torch.rand(B, N, generator=gen) > 0.2
    gH = torch.randn(B, 6, 6, generator=gen, dtype=torch.float64)
    gg = torch.randn(B, 6, generator=gen, dtype=torch.float64)

    def reference(c2):
        r = ((q - m) * n).sum(1)
        w = mask * kernel_weight(r * r, kernel, c2)[0]
        J = torch.cat([n, torch.linalg.cross(q, n, dim=1)], 1)
        return torch.einsum("bin,bjn,bn->bij", J, J, w), torch.einsum("bin,bn->bi", J, w * r), w

    for c2 in (0.7, float("inf")):
        H_ref, g_ref, w_ref = reference(c2)
        H, g, w = _PlaneNormalEquations.apply(q, m, n, mask, c2, kernel)
        for got, want in ((H, H_ref), (g, g_ref), (w, w_ref)):
            torch.testing.assert_close(got, want.detach(), rtol=1e-12, atol=1e-12)
        for use_H in (True, False):
            H_ref, g_ref, _ = reference(c2)
            H, g, _ = _PlaneNormalEquations.apply(q, m, n, mask, c2, kernel)
            (want,) = torch.autograd.grad((g_ref * gg).sum() + use_H * (H_ref * gH).sum(), q)
            (got,) = torch.autograd.grad((g * gg).sum() + (H * gH).sum() if use_H
                                         else (g * gg).sum(), q)
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_nn_reuse_keeps_rows_within_its_radius_then_requeries_exactly():
    """``nn_reuse_m`` (approximate correspondences): a point keeps its row while it stays within
    the radius of where it was last queried, and gets its true nearest map point once it leaves;
    an ICP with it still recovers a known transform; a negative radius is refused."""
    from icpbench.core.mapindex import MapIndex
    from icpbench.targets.icp import ICPConfig, _Correspondences

    s = scene_sample(2_000, 5_000, seed=4)
    maps = [MapIndex(s.map, s.map_normals)]
    p = torch.as_tensor(s.scan[None], dtype=torch.float64)
    finite = torch.ones(1, p.shape[1], dtype=torch.bool)
    nn = _Correspondences(maps, p, finite, torch.float64, reuse=0.05)
    q = p.transpose(1, 2).contiguous()
    first = nn.update(q, torch.ones(1, dtype=torch.bool)).clone()
    n0 = nn.queried
    for _ in range(4):  # four moves of 1 cm along x: 4 cm from the query, within the radius
        q = q + torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)[None, :, None]
        assert torch.equal(nn.update(q, torch.ones(1, dtype=torch.bool)), first)
    assert nn.queried == n0  # no point was re-queried
    q = q + torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64)[None, :, None]  # 6 cm: beyond
    got = nn.update(q, torch.ones(1, dtype=torch.bool)).numpy()[0]
    _, want = maps[0].query(q[0].T.numpy())
    assert np.array_equal(got, want)  # every point moved 6 cm > 5 cm: all re-queried

    samples = [scene_sample(2_000, 20_000, seed=s, scan_from_map=True) for s in range(2)]
    _, e_approx = _run(PointToPlaneICP("lidar", d_max=2.0, tol=1e-8, max_iterations=150,
                                       nn_reuse_m=0.02), samples)
    assert (e_approx["trans_err"] < 1e-3 * SCENE_SCALE_M).all(), e_approx["trans_err"]
    assert (torch.rad2deg(e_approx["rot_err"]) < 0.05).all()
    with pytest.raises(InputError, match="nn_reuse_m"):
        ICPConfig(nn_reuse_m=-0.01)
