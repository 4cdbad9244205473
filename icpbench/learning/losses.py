"""The paper's training losses (Zhang et al. 2025, eqs. 3-5); the weighted pose error they are built
on lives in :mod:`icpbench.core.pose_loss`."""

from __future__ import annotations

import torch

from icpbench.core.pose_loss import WEIGHT_PRESETS, weighted_pose_error, weights

__all__ = ["WEIGHT_PRESETS", "adversarial_loss", "reconstruction_loss", "weighted_pose_error", "weights"]


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
