"""Our differentiable point-to-plane ICP agrees with Open3D's ``registration_icp`` (issue requirement).

Same inputs (lidar-like synthetic scene: 5,000-point scan with 2 cm noise vs a 50,000-point map with
exact normals, 0.3 m / 5 deg offset), same settings (d_max = 5 m, Cauchy c = 1 m or no kernel), and
the final transforms must agree within 1 mm and 0.01 deg.

The two updates differ: Open3D applies ``T <- [R_zyx(phi) | rho] T`` (Euler angles of the 6-vector),
we apply ``T <- exp(delta^) T``. Both are Gauss-Newton steps on the same weighted point-to-plane cost
with correspondences re-found every iteration, so they share their fixed points, which the last test
checks directly (each method started at the other's answer stays there to ~1e-11 mm). From the same
start their paths differ slightly; on sparser problems (2,000-point scans vs 20,000-point maps) that
was measured to end, for 2 of 12 runs, in a different nearby fixed point 0.4-0.7 mm away (and once
in a 2-cycle of Open3D's iteration), which is why this test uses the 5k/50k problem.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.datasets.synthetic_scene import scene_sample
from icpbench.targets.p2plane import PointToPlaneICP

o3d = pytest.importorskip("open3d")
from icpbench.targets.open3d_icp import Open3DICP  # noqa: E402

torch.set_num_threads(1)
reg = o3d.pipelines.registration
ITERS = 30
KERNELS = [None, 1.0]  # no robust kernel, then the lidar preset's Cauchy c


@pytest.fixture(scope="module", params=[0, 1], ids=["seed0", "seed1"])
def problem(request):
    s = scene_sample(n_scan=5_000, n_map=50_000, seed=request.param, noise_m=0.02)
    batch = Batch.from_samples([s])
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s.map.astype(np.float64)))
    target.normals = o3d.utility.Vector3dVector(s.map_normals.astype(np.float64))
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s.scan.astype(np.float64)))
    return s, batch, source, target


def _diff(Ta, Tb) -> tuple[float, float]:
    """(translation mm, rotation deg) between two (4, 4) transforms."""
    e = pose_error_components(torch.as_tensor(Ta, dtype=torch.float64)[None],
                              torch.as_tensor(Tb, dtype=torch.float64)[None])
    return 1e3 * float(e["trans_err"][0]), float(np.degrees(float(e["rot_err"][0])))


def _open3d(source, target, T0, c, iters):
    est = (reg.TransformationEstimationPointToPlane() if c is None
           else reg.TransformationEstimationPointToPlane(reg.CauchyLoss(k=c)))
    o3d.utility.set_max_threads(1)
    crit = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=iters)
    return np.array(reg.registration_icp(source, target, 5.0, T0, est, crit).transformation)


def _ours(batch, T0, c, iters):
    tgt = PointToPlaneICP("lidar", cauchy_c=c, tol=1e-12, max_iterations=iters)
    return tgt.register(batch.scans, batch.maps, torch.as_tensor(T0, dtype=torch.float64)[None])


@pytest.mark.parametrize("c", KERNELS, ids=["no-kernel", "cauchy"])
def test_same_iteration_budget_agrees_within_1mm_and_0p01deg(problem, c):
    s, batch, source, target = problem
    assert _diff(s.T_init, s.T_gt)[0] > 100  # starts > 10 cm off
    T_o3d = _open3d(source, target, s.T_init, c, ITERS)  # exactly 30 iterations
    ours = _ours(batch, s.T_init, c, ITERS)  # up to 30; stops early only when ||delta|| < 1e-12
    assert ours.status == ["ok"]
    dt_mm, dr_deg = _diff(ours.T[0].numpy(), T_o3d)
    assert dt_mm < 1.0 and dr_deg < 0.01, (dt_mm, dr_deg)
    assert _diff(T_o3d, s.T_gt)[0] < 20  # and both are right (< 2 cm)


@pytest.mark.parametrize("c", KERNELS, ids=["no-kernel", "cauchy"])
def test_targets_at_their_own_convergence_agree(problem, c):
    """The two targets with the lidar preset's stopping rules (tol 1e-4, mapped for Open3D)."""
    s, batch, _, _ = problem
    ours = PointToPlaneICP("lidar", cauchy_c=c).register(batch.scans, batch.maps, batch.T_init)
    o3d_t = Open3DICP("lidar", cauchy_c=c)
    theirs = o3d_t.register(batch.scans, [o3d_t.prepare(s.map, s.map_normals)], batch.T_init)
    assert ours.status == ["ok"] and theirs.status == ["ok"]
    dt_mm, dr_deg = _diff(ours.T[0].numpy(), theirs.T[0].numpy())
    assert dt_mm < 1.0 and dr_deg < 0.01, (dt_mm, dr_deg)
    assert abs(float(ours.inlier_fraction[0]) - float(theirs.inlier_fraction[0])) < 1e-3


@pytest.mark.parametrize("c", KERNELS, ids=["no-kernel", "cauchy"])
def test_each_result_is_a_fixed_point_of_the_other_method(problem, c):
    """Same cost, same Jacobian, same weights and gate: one step of either method from the other's
    converged answer moves it by less than a nanometre."""
    s, batch, source, target = problem
    T_o3d = _open3d(source, target, s.T_init, c, ITERS)
    T_ours = _ours(batch, s.T_init, c, ITERS).T[0].numpy()
    ours_from_o3d = _ours(batch, T_o3d, c, 1).T[0].numpy()
    o3d_from_ours = _open3d(source, target, T_ours, c, 1)
    assert _diff(ours_from_o3d, T_o3d)[0] < 1e-6  # mm
    assert _diff(o3d_from_ours, T_ours)[0] < 1e-6
