"""The paper's losses (Zhang et al. 2025, eqs. 2-4) and the pose-error weight presets."""

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


def adversarial_loss(xi: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Eq. 3: ``L_adv = -||w_1:3 * rho|| - ||w_4:6 * phi||`` per sample (...,)."""
    return -weighted_pose_error(xi, w)


def reconstruction_loss(x: torch.Tensor, x_adv: torch.Tensor, budget_m: torch.Tensor | float
                        ) -> torch.Tensor:
    """Eqs. 4-5: ``L_rec = mean_i SoftShrink_lambda(||x_i - x_adv_i||)^2`` per sample (B,).

    Args:
        x, x_adv: (B, N, 3) clean and adversarial clouds.
        budget_m: lambda, a float or a (B,) tensor (one budget per sample).
    """
    d = torch.sqrt(((x - x_adv) ** 2).sum(-1) + 1e-12)  # (B, N)
    lam = torch.as_tensor(budget_m, dtype=d.dtype)
    if lam.ndim == 1:
        lam = lam[:, None]
    shrunk = torch.clamp(d - lam, min=0.0)  # SoftShrink of a non-negative argument
    return (shrunk**2).mean(-1)


def imitation_loss(x: torch.Tensor, x_adv: torch.Tensor, target_disp: torch.Tensor,
                   budget_m: torch.Tensor | float) -> torch.Tensor:
    """Beyond the paper: distance to an oracle's answer (learning from the oracle), per sample (B,).

    ``mean_i ||(x_adv_i - x_i) - d_i||^2 / lambda^2``: the squared error of the displacement,
    in units of the budget, so that budgets weigh alike and a model that moves every point to the
    opposite side of its ball scores 4.

    Args:
        x, x_adv: (B, N, 3) clean and adversarial clouds (sensor frame, metres).
        target_disp: (B, N, 3) the oracle's displacements (e.g. cached PGD answers).
        budget_m: lambda, a float or a (B,) tensor.
    """
    lam = torch.as_tensor(budget_m, dtype=x_adv.dtype, device=x_adv.device)
    if lam.ndim == 1:
        lam = lam[:, None]
    err = ((x_adv - x - target_disp.to(x_adv.dtype)) ** 2).sum(-1)  # (B, N)
    return (err / lam**2).mean(-1)
