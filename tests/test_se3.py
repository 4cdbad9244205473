import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from icpbench.core.se3 import (
    pose_error,
    pose_error_components,
    se3_exp,
    se3_inv,
    se3_log,
    so3_exp,
    so3_log,
)


def _random_twists(n, seed, max_angle=3.0):
    g = torch.Generator().manual_seed(seed)
    rho = torch.randn(n, 3, generator=g, dtype=torch.float64) * 3
    axis = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    ang = torch.rand(n, 1, generator=g, dtype=torch.float64) * max_angle
    return torch.cat([rho, axis * ang], -1)


def test_so3_exp_matches_scipy():
    xi = _random_twists(200, 0)
    R = so3_exp(xi[:, 3:]).numpy()
    R_ref = Rotation.from_rotvec(xi[:, 3:].numpy()).as_matrix()
    np.testing.assert_allclose(R, R_ref, atol=1e-12)


def test_so3_log_matches_scipy_including_near_pi_and_identity():
    phis = torch.cat([
        _random_twists(200, 1)[:, 3:],
        torch.tensor([[0.0, 0.0, 0.0], [1e-9, -2e-9, 0.0], [np.pi - 1e-7, 0.0, 0.0],
                      [0.0, 2.0, 2.0]], dtype=torch.float64),
    ])
    R = torch.as_tensor(Rotation.from_rotvec(phis.numpy()).as_matrix())
    got = so3_log(R).numpy()
    ref = Rotation.from_matrix(R.numpy()).as_rotvec()
    np.testing.assert_allclose(got, ref, atol=1e-6)


@pytest.mark.parametrize("scale", [1.0, 1e-6, 0.0])
def test_se3_round_trip(scale):
    xi = _random_twists(100, 2, max_angle=3.0) * scale
    np.testing.assert_allclose(se3_log(se3_exp(xi)).numpy(), xi.numpy(), atol=1e-9)
    T = se3_exp(xi)
    np.testing.assert_allclose((T @ se3_inv(T)).numpy(), np.broadcast_to(np.eye(4), T.shape),
                               atol=1e-12)


def test_se3_exp_translation_is_left_jacobian_times_rho():
    # For pure translation, exp gives the translation itself; for pure rotation, zero translation.
    xi = torch.tensor([[1.0, 2.0, 3.0, 0, 0, 0], [0, 0, 0, 0.1, 0.2, 0.3]], dtype=torch.float64)
    T = se3_exp(xi)
    np.testing.assert_allclose(T[0, :3, 3].numpy(), [1, 2, 3], atol=1e-15)
    np.testing.assert_allclose(T[1, :3, 3].numpy(), [0, 0, 0], atol=1e-15)


def test_log_gradient_finite_at_identity():
    xi = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    se3_log(se3_exp(xi)).sum().backward()
    assert torch.isfinite(xi.grad).all()
    np.testing.assert_allclose(xi.grad.numpy(), np.ones((1, 6)), atol=1e-9)


def test_pose_error_of_known_offset():
    # T_hat = exp(delta) T_gt  ->  xi = delta exactly.
    T_gt = se3_exp(_random_twists(10, 3))
    delta = _random_twists(10, 4, max_angle=0.5) * 0.3
    T_hat = se3_exp(delta) @ T_gt
    np.testing.assert_allclose(pose_error(T_hat, T_gt).numpy(), delta.numpy(), atol=1e-10)
    c = pose_error_components(T_hat, T_gt)
    np.testing.assert_allclose(c["trans_err_xy"].numpy(), torch.linalg.norm(delta[:, :2], dim=-1),
                               atol=1e-10)
    np.testing.assert_allclose(c["yaw_err"].numpy(), delta[:, 5].abs().numpy(), atol=1e-10)
    np.testing.assert_allclose(c["rot_err"].numpy(), torch.linalg.norm(delta[:, 3:], dim=-1),
                               atol=1e-10)
