"""Weighted pose error: the quantity every gradient attack and the generator's loss maximise.

Zhang et al. (ICRA 2025), eq. 3 uses ``||w_1:3 * rho|| + ||w_4:6 * phi||`` over the pose error
``xi = [rho, phi]`` (metres, radians; :func:`icpbench.core.se3.pose_error`) with three weight
presets. It lives below both the attacks and the training code, which share it.
"""

from __future__ import annotations

import torch

from icpbench.core.errors import InputError

#: w_1..w_6 of eq. 3 over [rho_x, rho_y, rho_z, phi_x, phi_y, phi_z] (paper §IV-C1).
WEIGHT_PRESETS: dict[str, tuple[float, ...]] = {
    "xy": (1.0, 1.0, 0.0, 0.0, 0.0, 0.0),
    "x-only": (1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    "theta-only": (0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
}


def weights(preset: str | tuple[float, ...] | list[float]) -> torch.Tensor:
    """The 6 weights of a preset name or an explicit sequence, as a float64 tensor (6,)."""
    if isinstance(preset, str):
        if preset not in WEIGHT_PRESETS:
            raise InputError(f"unknown weight preset {preset!r}; valid: {', '.join(WEIGHT_PRESETS)}")
        preset = WEIGHT_PRESETS[preset]
    w = torch.as_tensor(list(preset), dtype=torch.float64)
    if w.shape != (6,) or not torch.isfinite(w).all() or (w < 0).any():
        raise InputError(f"weights must be 6 non-negative numbers, got {list(preset)}")
    return w


def _safe_norm(v: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the last axis with a finite gradient at zero."""
    return torch.sqrt((v * v).sum(-1) + 1e-12)


def weighted_pose_error(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``||w_1:3 * rho|| + ||w_4:6 * phi||`` for xi (..., 6) = [rho, phi]; the negative of eq. 3."""
    w = w.to(xi.dtype)
    return _safe_norm(w[:3] * xi[..., :3]) + _safe_norm(w[3:] * xi[..., 3:])
