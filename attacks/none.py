"""Attack ``none``: the clean scan (the "Original" row of Table 1)."""

from __future__ import annotations

from typing import ClassVar

import torch

from icpbench.attacks.base import Attack
from icpbench.core.types import Batch


class NoAttack(Attack):
    """No perturbation: returns the clean scans (the 'Original' row)."""

    name: ClassVar[str] = "none"
    cost_class: ClassVar[int] = 0
    description: ClassVar[str] = "No perturbation: the clean scan (Table 1's 'Original' row)"
    budget_invariant: ClassVar[bool] = True

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        return batch.scans.clone()
