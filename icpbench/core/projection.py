"""Projection of per-point displacements onto their budget balls (the attacks' hard bound)."""

from __future__ import annotations

import numpy as np
import torch

from icpbench.core.errors import InputError


def clip_displacements(d: np.ndarray, budget_m: float) -> np.ndarray:
    """Displacements ``d`` (..., 3) in metres, each scaled back onto the ball of radius
    ``budget_m`` where it is longer (a new array; the NumPy attacks' projection)."""
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return d * np.minimum(1.0, budget_m / np.maximum(norm, 1e-300))


def project_to_ball(clean: torch.Tensor, adv: torch.Tensor,
                    budget_m: float | torch.Tensor) -> torch.Tensor:
    """Project each point's displacement ``adv - clean`` (B, N, 3) onto the Euclidean ball of radius
    ``budget_m`` (metres): one float for every sample, or a (B,) tensor with one budget per sample.

    Differentiable in ``adv`` (and in a tensor budget); the gradient is finite at zero displacement.
    Points already within their ball (to a relative 1e-12) come back unchanged, bit for bit."""
    d = adv - clean
    norm = torch.linalg.vector_norm(d, dim=-1, keepdim=True)  # (B, N, 1)
    if isinstance(budget_m, torch.Tensor):
        if budget_m.dim() != 1 or budget_m.shape[0] != d.shape[0]:
            raise InputError(f"per-sample budget must have shape ({d.shape[0]},), "
                             f"got {tuple(budget_m.shape)}")
        budget_m = budget_m.to(device=d.device, dtype=d.dtype)[:, None, None]
    scale = torch.clamp(budget_m / torch.clamp(norm, min=1e-12), max=1.0)
    # points within their ball (to a relative 1e-12: a point projected once sits on the sphere up
    # to rounding) are returned as they are, bit for bit (``clean + d`` may round differently from
    # ``adv``), so projecting a scan that needs no projection gives back the same scan
    return torch.where(scale < 1.0 - 1e-12, clean + d * scale, adv)
