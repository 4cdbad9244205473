"""Attack ``normal``: move every point by lambda along its associated map normal, projected to x-y.

Zhang et al. 2025, §IV-B2 ("Normal Translation Baseline"), after Laconte et al. (RA-L 2024), who
show that shifting points along the normals of their associated map points is an effective attack
on point-to-plane ICP.

Association: nearest map point of each scan point at the scan's *initial* pose (``T_init``), as a
localiser would see it; no distance limit.

Orientation rule (normals have no intrinsic sign): one horizontal direction ``u`` is drawn per
sample (uniformly, from the attack's generator) and every projected normal is flipped so that it
points into the half-plane of ``u`` (``n_xy . u >= 0``). All points of one planar feature therefore
move the same way, and walls of different orientation all push the scan towards the same side
(walls facing x shift in x, walls facing y shift in y: the "sqrt(2)" effect no rigid translation
can produce). Points whose normal is nearly vertical (``|n_xy| < 0.1``: ground, roofs) have no
meaningful horizontal normal and are moved along ``u`` itself, so *every* point moves by exactly
lambda and the displacement audit shows ``disp_max = disp_mean = lambda``.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack
from icpbench.attacks.uniform import random_xy_directions
from icpbench.core.se3 import transform_points
from icpbench.core.types import Batch

MIN_HORIZONTAL = 0.1  # |n_xy| below which a normal counts as vertical


class NormalTranslationAttack(Attack):
    """Move each point by lambda along its map normal projected onto the x-y plane."""

    name: ClassVar[str] = "normal"
    cost_class: ClassVar[int] = 0
    description: ClassVar[str] = (
        "Move every point by lambda along its associated map normal projected onto x-y"
    )

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        scans = batch.scans
        u_sensor = random_xy_directions(batch, generator)  # (B, 3), sensor frame
        R_init = batch.T_init[:, :3, :3]
        u_map = (R_init @ u_sensor[..., None])[..., 0]
        q = transform_points(batch.T_init, scans.to(torch.float64)).numpy()
        out = []
        for b, mi in enumerate(batch.maps):
            _, idx = mi.query(q[b])
            n = mi.normals[np.minimum(idx, len(mi) - 1)].copy()  # (N, 3) map frame
            n[:, 2] = 0.0
            norm = np.linalg.norm(n, axis=1, keepdims=True)
            u = u_map[b].numpy()
            flat = norm[:, 0] < MIN_HORIZONTAL
            d = np.where(flat[:, None], u[None, :], n / np.maximum(norm, 1e-12))
            d = d * np.where((d @ u) < 0, -1.0, 1.0)[:, None]
            d_sensor = d @ R_init[b].numpy()  # R^T d for each row
            out.append(torch.as_tensor(d_sensor, dtype=scans.dtype))
        return scans + budget_m * torch.stack(out)
