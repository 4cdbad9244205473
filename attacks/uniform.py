"""Attack ``uniform``: translate the whole scan by lambda in a random x-y direction.

Zhang et al. 2025, §IV-B1 ("Uniform Translation Baseline"). The direction is drawn uniformly in the
x-y plane of the *map* frame as seen from the initial guess (``T_init``; identity in the paper, where
sensor and map axes coincide) and expressed in the sensor frame, so every point moves exactly lambda.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch

from icpbench.attacks.base import Attack, SampleGenerators
from icpbench.core.types import Batch


def random_xy_directions(batch: Batch, generator: SampleGenerators) -> torch.Tensor:
    """Unit directions (B, 3) in the sensor frame that lie in the map-frame x-y plane under T_init;
    sample b's angle is drawn from its own stream ``generator[b]``."""
    B = len(batch)
    angle = generator.rand(dtype=torch.float64) * 2 * math.pi  # (B,)
    d_map = torch.stack([torch.cos(angle), torch.sin(angle), torch.zeros(B, dtype=torch.float64)], -1)
    R_init = batch.T_init[:, :3, :3]
    return (R_init.transpose(1, 2) @ d_map[..., None])[..., 0]


class UniformTranslationAttack(Attack):
    """Translate every point of the scan by lambda along one random horizontal direction."""

    name: ClassVar[str] = "uniform"
    cost_class: ClassVar[int] = 0
    description: ClassVar[str] = "Translate the whole scan by lambda in a random x-y direction"

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        d = random_xy_directions(batch, generator).to(batch.scans.dtype)
        return batch.scans + budget_m * d[:, None, :]
