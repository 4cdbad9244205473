"""Differentiable replicas of the black-box targets, and the robust kernels of ``ICPConfig``.

Each replica must land where its black box lands on the small synthetic lidar scene
(:func:`icpbench.datasets.synthetic_scene.scene_sample`: ground, boxes and poles; scans with 2 cm
noise, up to 0.3 m / 5 deg from T_init = identity), and its gradient must match central finite
differences (unrolled, and implicit at a converged pose).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.harness.runner import build_target
from icpbench.targets.icp import ICPConfig, kernel_weight
from icpbench.targets.p2plane import PointToPlaneICP
from icpbench.targets.p2point import PointToPointICP

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def scene():
    return [scene_sample(n_scan=1_500, n_map=15_000, seed=k, noise_m=0.02) for k in range(2)]


def _pose_gap(T_a: torch.Tensor, T_b: torch.Tensor) -> tuple[float, float]:
    """Largest translation (m) and rotation (deg) difference between two batches of poses."""
    d = pose_error_components(T_a.detach().double(), T_b.detach().double())
    return float(d["trans_err"].max()), float(torch.rad2deg(d["rot_err"]).max())


def _register_both(black_box, samples):
    """The black box's and its replica's registrations of the same scans (float64)."""
    batch = Batch.from_samples(samples)
    scans = batch.scans.double()
    bb = black_box.register(scans, [black_box.prepare(s.map, s.map_normals) for s in samples],
                            batch.T_init)
    rep = black_box.replica()
    assert rep is not None and rep.differentiable and rep.replica() is rep
    rr = rep.register(scans, batch.maps, batch.T_init)
    return bb, rr, batch


# -- robust kernels -----------------------------------------------------------------------------

@pytest.mark.parametrize("kernel", ["cauchy", "huber", "geman_mcclure"])
def test_kernel_weight_values_and_slope(kernel):
    c = 0.5
    r2 = torch.tensor([0.0, 0.01, 0.2, 0.25, 0.3, 4.0], dtype=torch.float64, requires_grad=True)
    w, slope = kernel_weight(r2, kernel, c * c)
    r = r2.detach().sqrt()
    want = {"cauchy": 1 / (1 + r**2 / c**2),
            "huber": torch.where(r <= c, torch.ones_like(r), c / r),
            "geman_mcclure": (c**2) ** 2 / (c**2 + r**2) ** 2}[kernel]  # KISS-ICP's form
    torch.testing.assert_close(w.detach(), want, rtol=1e-14, atol=0)
    (auto,) = torch.autograd.grad(w.sum(), r2)
    torch.testing.assert_close(slope.detach(), auto, rtol=1e-12, atol=0)
    fd = (kernel_weight(r2.detach() + 1e-7, kernel, c * c)[0]
          - kernel_weight(r2.detach() - 1e-7, kernel, c * c)[0]) / 2e-7
    keep = (r2.detach() - c * c).abs() > 1e-3  # Huber's slope jumps at |r| = c
    torch.testing.assert_close(slope.detach()[keep], fd[keep], rtol=1e-5, atol=1e-9)
    with pytest.raises(InputError, match="kernel"):
        ICPConfig(kernel="tukey")


def _weighted_pose(target, batch, scans):
    reg = target.register(scans, batch.maps, batch.T_init)
    e = pose_error_components(reg.T, batch.T_gt)
    xi = torch.stack([e[k] for k in ("rho_x", "rho_y", "rho_z", "phi_x", "phi_y", "phi_z")], -1)
    return (xi * torch.tensor([1.0, -0.7, 0.3, 2.0, 1.0, -3.0], dtype=torch.float64)).sum(), reg


def _check_fd(target, batch, *, draws=12, rtol=1e-3, min_checked=5, points=200):
    """The gradient of a weighted pose error w.r.t. the scan against central differences."""
    x = batch.scans.double().clone().requires_grad_(True)
    loss, reg = _weighted_pose(target, batch, x)
    loss.backward()
    rng = np.random.default_rng(0)
    eps, checked = 1e-6, 0
    for _ in range(draws):
        i, k = int(rng.integers(0, points)), int(rng.integers(0, 3))
        xp, xm = batch.scans.double().clone(), batch.scans.double().clone()
        xp[0, i, k] += eps
        xm[0, i, k] -= eps
        with torch.no_grad():
            fd = float((_weighted_pose(target, batch, xp)[0] - _weighted_pose(target, batch, xm)[0])
                       / (2 * eps))
        g = float(x.grad[0, i, k])
        if abs(fd) < 1e-5 and abs(g) < 1e-5:  # below the differences' rounding noise (~1e-9)
            continue
        assert abs(fd - g) / max(abs(fd), abs(g)) < rtol, (i, k, fd, g)
        checked += 1
    assert checked >= min_checked
    return reg


@pytest.mark.parametrize("cls,kernel", [(PointToPlaneICP, "huber"), (PointToPlaneICP, "geman_mcclure"),
                                        (PointToPointICP, "huber")])
@pytest.mark.parametrize("backprop", ["unrolled", "implicit"])
def test_kernel_gradients_match_finite_differences(cls, kernel, backprop):
    s = scene_sample(300, 4_000, seed=7, noise_m=0.01)
    its = 8 if backprop == "unrolled" else 300
    tgt = cls("lidar", d_max=1.5, cauchy_c=0.05, kernel=kernel, max_iterations=its, tol=1e-13,
              backprop=backprop)
    implicit = backprop == "implicit"
    reg = _check_fd(tgt, Batch.from_samples([s]), rtol=1e-4 if implicit else 1e-3,
                    draws=6 if implicit else 12, min_checked=4)
    if implicit:
        assert bool(reg.converged.all())


def test_kernel_none_is_no_kernel(scene):
    """``kernel="none"`` (what a command line can pass) registers exactly as ``cauchy_c=None``."""
    batch = Batch.from_samples(scene[:1])
    for cls in (PointToPlaneICP, PointToPointICP):
        a = cls("lidar", kernel="none").register(batch.scans, batch.maps, batch.T_init)
        b = cls("lidar", cauchy_c=None).register(batch.scans, batch.maps, batch.T_init)
        c = cls("lidar").register(batch.scans, batch.maps, batch.T_init)
        assert torch.equal(a.T, b.T) and not torch.equal(a.T, c.T)


def test_kernel_changes_the_pose_and_keeps_accuracy(scene):
    """Huber and Cauchy at the same scale: different poses (the kernel is used), both cm-level."""
    batch = Batch.from_samples(scene)
    poses = {}
    for kernel in ("cauchy", "huber"):
        reg = PointToPlaneICP("lidar", cauchy_c=0.05, kernel=kernel).register(
            batch.scans, batch.maps, batch.T_init)
        assert bool(reg.converged.all())
        assert float(pose_error_components(reg.T, batch.T_gt)["trans_err"].max()) < 0.02
        poses[kernel] = reg.T
    assert _pose_gap(poses["cauchy"], poses["huber"])[0] > 1e-6


# -- replicas -----------------------------------------------------------------------------------

def test_replica_of_every_target():
    assert build_target("p2plane", "lidar").replica().name == "p2plane"
    assert build_target("open3d", "lidar").replica().name == "p2plane"
    o3d_point = build_target("open3d", "lidar", {"mode": "point"})
    rep = o3d_point.replica()
    assert rep.name == "p2point" and rep.config == o3d_point.config
    assert rep.config.cauchy_c is None and rep.config.d_max == 1.0 and rep.config.max_iterations == 500
    assert build_target("kiss-icp", "lidar").replica().name == "kiss-icp-replica"
    assert build_target("small-gicp", "lidar").replica().name == "small-gicp-replica"
    assert build_target("small-gicp", "lidar", {"registration_type": "ICP"}).replica().name == "p2point"
    assert build_target("small-gicp", "lidar", {"registration_type": "PLANE_ICP"}).replica() is None


def test_replicas_pickle_without_their_map_cache(scene):
    import pickle

    batch = Batch.from_samples(scene[:1])
    for name in ("kiss-icp-replica", "small-gicp-replica"):
        tgt = build_target(name, "lidar", {"max_iterations": 3})
        first = tgt.register(batch.scans, batch.maps, batch.T_init)
        copy = pickle.loads(pickle.dumps(tgt))
        assert len(copy._maps) == 0 and copy.settings() == tgt.settings()
        assert torch.equal(copy.register(batch.scans, batch.maps, batch.T_init).T, first.T)


def test_kiss_search_and_one_step_equal_kiss_itself(scene):
    """One KISS iteration (the library) equals one replica iteration and one NumPy step on KISS's
    27-voxel neighbours (:class:`VoxelNeighbours`), to rounding."""
    from icpbench.targets.kiss import KissICPTarget, kp, point_to_point_hessian

    s = scene[0]
    bb = KissICPTarget("lidar", max_corr=3.0)  # a gate of 3 voxels: the 27-voxel search matters
    km = bb.prepare(s.map)
    scan = s.scan.astype(np.float64)
    T1 = np.asarray(bb._step._align_points_to_map(
        points=kp._Vector3dVector(scan), voxel_map=km.voxel_map, initial_guess=np.eye(4),
        max_correspondance_distance=bb.max_corr, kernel=bb.kernel))
    d, i = km.search.query(scan)
    exact, _ = MapIndex(km.points).query(scan)
    assert np.all(d[exact < bb.voxel_size] == exact[exact < bb.voxel_size])
    assert np.any((d > exact) & (d < bb.max_corr))  # some pairs are KISS's, not the nearest
    ok = d < bb.max_corr
    q, e = scan[ok], scan[ok] - km.points[i[ok]]
    w = bb.kernel**2 / (bb.kernel + d[ok] ** 2) ** 2
    g = np.concatenate([(w[:, None] * e).sum(0), (w[:, None] * np.cross(q, e)).sum(0)])
    dx = -np.linalg.solve(point_to_point_hessian(q, w), g)
    from icpbench.core.se3 import se3_exp

    np.testing.assert_allclose(se3_exp(torch.as_tensor(dx[None]))[0].numpy(), T1, atol=1e-12)
    rep = bb.replica().with_settings(max_iterations=1)
    reg = rep.register(torch.as_tensor(scan[None]), [MapIndex(s.map)], torch.eye(4)[None].double())
    np.testing.assert_allclose(reg.T[0].numpy(), T1, atol=1e-7)


def test_kiss_replica_lands_on_kiss(scene):
    from icpbench.targets.kiss import KissICPTarget

    bb, rr, batch = _register_both(KissICPTarget("lidar"), scene)
    dt, dr = _pose_gap(bb.T, rr.T)
    assert dt < 1e-5 and dr < 1e-4, (dt, dr)  # metres, degrees
    assert torch.equal(bb.iterations, rr.iterations)
    assert rr.status == ["ok", "ok"]
    assert float(pose_error_components(rr.T, batch.T_gt)["trans_err"].max()) < 0.05


def test_gicp_scan_covariances_are_small_gicps(scene):
    import small_gicp

    from icpbench.targets.gicp_replica import scan_covariances

    pts = scene[0].scan.astype(np.float64)
    cloud = small_gicp.PointCloud(pts)
    small_gicp.estimate_covariances(cloud, small_gicp.KdTree(cloud, num_threads=1), 20, 1)
    want = np.asarray(cloud.covs())[:, :3, :3]
    six = scan_covariances(torch.as_tensor(pts[None]), torch.ones(1, len(pts), dtype=torch.bool),
                           20)[0].numpy()
    got = six[[0, 3, 4, 3, 1, 5, 4, 5, 2]].T.reshape(-1, 3, 3)
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_gicp_replica_lands_on_small_gicp(scene):
    from icpbench.targets.small_gicp import SmallGICPTarget

    bb, rr, batch = _register_both(SmallGICPTarget("lidar"), scene)
    dt, dr = _pose_gap(bb.T, rr.T)
    assert dt < 2e-3 and dr < 0.02, (dt, dr)  # small_gicp stops at 1e-3 / 0.1 deg steps
    assert rr.status == ["ok", "ok"]


def test_open3d_point_to_point_replica_lands_on_open3d(scene):
    pytest.importorskip("open3d")
    bb, rr, _ = _register_both(build_target("open3d", "lidar", {"mode": "point"}), scene)
    dt, dr = _pose_gap(bb.T, rr.T)
    assert dt < 2e-3 and dr < 0.02, (dt, dr)


@pytest.mark.parametrize("backprop", ["unrolled", "implicit"])
def test_kiss_replica_gradient_matches_finite_differences(backprop):
    from icpbench.targets.kiss_replica import KissICPReplica

    s = scene_sample(300, 4_000, seed=7, noise_m=0.01)
    its = 8 if backprop == "unrolled" else 500
    tgt = KissICPReplica("lidar", max_iterations=its, tol=1e-13, backprop=backprop)
    implicit = backprop == "implicit"
    reg = _check_fd(tgt, Batch.from_samples([s]), rtol=1e-4 if implicit else 1e-3,
                    draws=6 if implicit else 12, min_checked=4)
    if backprop == "implicit":
        assert bool(reg.converged.all())


@pytest.mark.parametrize("backprop", ["unrolled", "implicit"])
@pytest.mark.parametrize("scan_cov_grad", [True, False])
def test_gicp_replica_gradient_matches_finite_differences(backprop, scan_cov_grad):
    """With differentiable scan covariances the gradient is that of small_gicp's whole response;
    without, finite differences must hold the covariances too (they are computed once here)."""
    from icpbench.targets import gicp_replica
    from icpbench.targets.gicp_replica import SmallGICPReplica

    s = scene_sample(300, 4_000, seed=7, noise_m=0.01)
    its = 6 if backprop == "unrolled" else 100
    tgt = SmallGICPReplica("lidar", d_max=1.5, max_iterations=its, tol=1e-12, backprop=backprop,
                           scan_cov_grad=scan_cov_grad)
    batch = Batch.from_samples([s])
    if not scan_cov_grad:  # finite differences of the function the gradient is of
        fixed = gicp_replica.scan_covariances(batch.scans.double(),
                                              torch.ones(1, 300, dtype=torch.bool), 20, grad=False)
        orig = gicp_replica.scan_covariances
        gicp_replica.scan_covariances = lambda *a, **k: fixed
        try:
            reg = _check_fd(tgt, batch, rtol=1e-3)
        finally:
            gicp_replica.scan_covariances = orig
    else:
        reg = _check_fd(tgt, batch, rtol=1e-3)
    if backprop == "implicit":
        assert bool(reg.converged.all())
