"""Attack ``jitter``: move every point by exactly lambda in an independent random 3-D direction."""

from typing import ClassVar

import torch

from icpbench.attacks.base import Attack


class JitterAttack(Attack):
    """Each point moves by lambda along its own random direction (a weak, noise-like attack)."""

    name: ClassVar[str] = "jitter"
    description: ClassVar[str] = "Move every point by lambda in a random 3-D direction (example plugin)"

    def _perturb(self, batch, budget_m, *, surrogate, generator):
        d = generator.randn(*batch.scans.shape[1:], dtype=batch.scans.dtype)  # one stream per sample
        return batch.scans + budget_m * d / torch.linalg.norm(d, dim=-1, keepdim=True)
