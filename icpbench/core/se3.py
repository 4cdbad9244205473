"""Batched, differentiable SE(3)/SO(3) exponential and logarithm maps, and the paper's pose error.

Conventions follow Barfoot, *State Estimation for Robotics* (2017): a twist is
``xi = [rho (3), phi (3)]`` (translation part first), ``T = exp(xi^)`` with
``R = exp(phi^)`` and ``t = J(phi) rho`` where ``J`` is the left Jacobian of SO(3).
All functions accept any leading batch shape ``(..., 6)`` / ``(..., 4, 4)`` and are differentiable,
including at the identity (small-angle Taylor branches selected with ``torch.where``).
"""

from __future__ import annotations

import torch

_SMALL = 1e-4  # |phi| below which Taylor expansions are used (radians)


def hat(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) skew-symmetric matrix with ``hat(a) @ b == cross(a, b)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)],
        -2,
    )


def vee(M: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) skew-symmetric -> (..., 3)."""
    return torch.stack([M[..., 2, 1], M[..., 0, 2], M[..., 1, 0]], -1)


def _theta(phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Return (theta, theta_safe, small) with a gradient-safe norm of phi (..., 3)."""
    sq = (phi * phi).sum(-1)
    small = sq < _SMALL**2
    theta_safe = torch.sqrt(torch.where(small, torch.ones_like(sq), sq))
    theta = torch.where(small, torch.zeros_like(sq), theta_safe)
    return theta, theta_safe, small


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rotation vector (..., 3) -> rotation matrix (..., 3, 3) (Rodrigues' formula)."""
    theta, ts, small = _theta(phi)
    sq = (phi * phi).sum(-1)
    a = torch.where(small, 1.0 - sq / 6.0, torch.sin(ts) / ts)
    b = torch.where(small, 0.5 - sq / 24.0, (1.0 - torch.cos(ts)) / (ts * ts))
    K = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_left_jacobian(phi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian J(phi) (..., 3, 3) of SO(3)."""
    _, ts, small = _theta(phi)
    sq = (phi * phi).sum(-1)
    b = torch.where(small, 0.5 - sq / 24.0, (1.0 - torch.cos(ts)) / (ts * ts))
    c = torch.where(small, 1.0 / 6.0 - sq / 120.0, (ts - torch.sin(ts)) / (ts**3))
    K = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + b[..., None, None] * K + c[..., None, None] * (K @ K)


def so3_left_jacobian_inv(phi: torch.Tensor) -> torch.Tensor:
    """Inverse left Jacobian J(phi)^-1 (..., 3, 3), valid for |phi| < pi."""
    _, ts, small = _theta(phi)
    sq = (phi * phi).sum(-1)
    big = 1.0 / (ts * ts) - (1.0 + torch.cos(ts)) / (2.0 * ts * torch.sin(ts))
    d = torch.where(small, 1.0 / 12.0 + sq / 720.0, big)
    K = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye - 0.5 * K + d[..., None, None] * (K @ K)


def _rot_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) as (w, x, y, z) with w >= 0.

    Shepperd's method: the four candidate formulas are all evaluated (with clamped square
    roots so no NaN enters the graph) and the best-conditioned one is selected per element.
    """
    m = R
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    diag = torch.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    k = torch.argmax(diag, dim=-1)
    eps = 1e-12
    s0 = torch.sqrt(torch.clamp(1.0 + tr, min=eps)) * 2.0
    q0 = torch.stack(
        [0.25 * s0, (m[..., 2, 1] - m[..., 1, 2]) / s0, (m[..., 0, 2] - m[..., 2, 0]) / s0,
         (m[..., 1, 0] - m[..., 0, 1]) / s0], -1)
    s1 = torch.sqrt(torch.clamp(1.0 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2], min=eps)) * 2.0
    q1 = torch.stack(
        [(m[..., 2, 1] - m[..., 1, 2]) / s1, 0.25 * s1, (m[..., 0, 1] + m[..., 1, 0]) / s1,
         (m[..., 0, 2] + m[..., 2, 0]) / s1], -1)
    s2 = torch.sqrt(torch.clamp(1.0 + m[..., 1, 1] - m[..., 0, 0] - m[..., 2, 2], min=eps)) * 2.0
    q2 = torch.stack(
        [(m[..., 0, 2] - m[..., 2, 0]) / s2, (m[..., 0, 1] + m[..., 1, 0]) / s2, 0.25 * s2,
         (m[..., 1, 2] + m[..., 2, 1]) / s2], -1)
    s3 = torch.sqrt(torch.clamp(1.0 + m[..., 2, 2] - m[..., 0, 0] - m[..., 1, 1], min=eps)) * 2.0
    q3 = torch.stack(
        [(m[..., 1, 0] - m[..., 0, 1]) / s3, (m[..., 0, 2] + m[..., 2, 0]) / s3,
         (m[..., 1, 2] + m[..., 2, 1]) / s3, 0.25 * s3], -1)
    cands = torch.stack([q0, q1, q2, q3], -2)  # (..., 4, 4)
    q = torch.gather(cands, -2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    return q / torch.linalg.norm(q, dim=-1, keepdim=True)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) -> rotation vector (..., 3) with |phi| <= pi."""
    q = _rot_to_quat(R)
    w, v = q[..., 0], q[..., 1:]
    sn2 = (v * v).sum(-1)
    small = sn2 < 1e-16
    sn = torch.sqrt(torch.where(small, torch.ones_like(sn2), sn2))
    angle_over_sn = torch.where(small, 2.0 / w - 2.0 * sn2 / (3.0 * w**3),
                                2.0 * torch.atan2(sn, w) / sn)
    return v * angle_over_sn[..., None]


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Twist (..., 6) = [rho, phi] -> homogeneous transform (..., 4, 4)."""
    rho, phi = xi[..., :3], xi[..., 3:]
    R = so3_exp(phi)
    t = (so3_left_jacobian(phi) @ rho[..., None])[..., 0]
    top = torch.cat([R, t[..., None]], -1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Homogeneous transform (..., 4, 4) -> twist (..., 6) = [rho, phi]."""
    phi = so3_log(T[..., :3, :3])
    rho = (so3_left_jacobian_inv(phi) @ T[..., :3, 3:4])[..., 0]
    return torch.cat([rho, phi], -1)


def se3_inv(T: torch.Tensor) -> torch.Tensor:
    """Inverse of homogeneous transforms (..., 4, 4) using R^T (exact for rigid transforms)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:4]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -Rt @ t], -1)
    return torch.cat([top, T[..., 3:4, :]], -2)


def transform_points(T: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Apply (B, 4, 4) transforms to (B, N, 3) points."""
    return p @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


POSE_ERROR_COLUMNS = (
    "rho_x", "rho_y", "rho_z", "phi_x", "phi_y", "phi_z",
    "trans_err_xy", "trans_err", "rot_err", "yaw_err",
)


def pose_error(T_hat: torch.Tensor, T_gt: torch.Tensor) -> torch.Tensor:
    """Paper eq. 1: ``xi = log(T_hat @ inv(T_gt))^vee = [rho, phi]`` (..., 6), metres and radians."""
    return se3_log(T_hat @ se3_inv(T_gt))


def pose_error_components(T_hat: torch.Tensor, T_gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """Reported pose-error components (each (...,); docs/architecture.md, "Frames, units and pose
    error"): rho_*, phi_*, and the norms
    ``trans_err_xy = ||rho_xy||`` (Table 1), ``trans_err = ||rho||``, ``rot_err = ||phi||``,
    ``yaw_err = |phi_z|``."""
    xi = pose_error(T_hat, T_gt)
    rho, phi = xi[..., :3], xi[..., 3:]
    out = {name: xi[..., i] for i, name in enumerate(POSE_ERROR_COLUMNS[:6])}
    out["trans_err_xy"] = torch.linalg.norm(rho[..., :2], dim=-1)
    out["trans_err"] = torch.linalg.norm(rho, dim=-1)
    out["rot_err"] = torch.linalg.norm(phi, dim=-1)
    out["yaw_err"] = phi[..., 2].abs()
    return out
