"""The monitors as a penalty a gradient attack can climb against.

A gradient attack that maximises the pose error alone leaves the region where no monitor fires
within a step or two (an odometry gate of 0.65 m is crossed long before the error peaks), and its
candidates are then rejected by the monitored oracle. The adaptive form (Carlini and Wagner,
"Adversarial examples are not easily detected: bypassing ten detection methods", AISec 2017:
add the detector's differentiable score to the loss) ascends

``objective = weighted pose error - weight * sum_m relu(s_m / tau_m - (1 - margin))``

per scan, with ``s_m`` each differentiable monitor's score (:meth:`Monitor.differentiable_score`,
equal to the monitor's own score of the surrogate's registration) and ``tau_m`` its calibrated
threshold: nothing changes while every score stays below ``(1 - margin) tau_m``, and past that a
steep wall (``weight`` metres of objective per threshold's worth of score) turns the ascent back.
A candidate is *feasible* where every differentiable score is at most its threshold; the attack
keeps the feasible iterate with the largest error. Monitors without a differentiable score are
not seen here (:attr:`MonitorPenalty.blind`); the oracle still checks them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.monitors.base import Monitor
from icpbench.monitors.differentiable import DiffInput
from icpbench.monitors.inputs import MotionPrior

__all__ = ["MonitorPenalty"]

#: Default wall height: metres of objective per threshold's worth of score past the margin.
WEIGHT = 10.0
#: Default margin: the wall starts at this share below each threshold.
MARGIN = 0.05


class MonitorPenalty:
    """The penalty of B registrations (module docstring).

    Args:
        monitors: the monitors with their thresholds; those with ``differentiable`` are used.
        maps: B maps with unit normals (map frame, metres), one per sample.
        priors: ``{monitor name: B motion priors}`` for the monitors that use one.
        sample_ids: B sample identifiers (for messages).
        weight: metres of objective per threshold's worth of score past the margin (> 0).
        margin: the wall starts at ``(1 - margin)`` times each threshold (0 <= margin < 1).

    Attributes:
        seen: the monitors the penalty uses; ``blind``: the names of the others.
    """

    def __init__(self, monitors: Sequence[Monitor], maps: Sequence[MapIndex],
                 priors: dict[str, Sequence[MotionPrior | None]], sample_ids: Sequence[str], *,
                 weight: float = WEIGHT, margin: float = MARGIN) -> None:
        if not (np.isfinite(weight) and weight > 0):
            raise InputError(f"monitor penalty: weight must be a positive number, got {weight!r}")
        if not (0.0 <= margin < 1.0):
            raise InputError(f"monitor penalty: margin must lie in [0, 1), got {margin!r}")
        if len(maps) != len(sample_ids):
            raise InputError(f"monitor penalty: {len(maps)} maps for {len(sample_ids)} samples")
        self.seen = [m for m in monitors if m.differentiable]
        self.blind = tuple(m.name for m in monitors if not m.differentiable)
        self.maps, self.ids = list(maps), list(sample_ids)
        self.priors = {n: list(p) for n, p in priors.items()}
        self.weight, self.margin = float(weight), float(margin)

    def __call__(self, scans: torch.Tensor, T: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """The penalty (B,) (metres of objective, with gradients) and whether each candidate is
        feasible (B,) bool, for scans (B, N, 3) (sensor frame) registered at T (B, 4, 4)
        scan->map. A non-finite pose, or a score that is not finite, makes a candidate
        infeasible and adds no gradient."""
        if scans.shape[0] != len(self.maps) or T.shape[0] != len(self.maps):
            raise InputError(f"monitor penalty: built for {len(self.maps)} samples, given "
                             f"{scans.shape[0]} scans and {T.shape[0]} poses")
        pens, feasible = [], np.ones(len(self.maps), dtype=bool)
        for b, (m_idx, sid) in enumerate(zip(self.maps, self.ids, strict=True)):
            pen = scans.new_zeros(())
            if not bool(torch.isfinite(T[b].detach()).all()):
                feasible[b] = False
                pens.append(pen)
                continue
            # one input per sample, so the monitors without a prior share its nearest-map lookup
            x = DiffInput(scans[b], T[b], m_idx, None, sid)
            for m in self.seen:
                prior = self.priors.get(m.name, [None] * len(self.maps))[b]
                s = m.differentiable_score(x if prior is None else
                                           dataclasses.replace(x, prior=prior))
                if not bool(torch.isfinite(s.detach())):
                    feasible[b] = False
                    continue
                feasible[b] &= bool(s.detach() <= m.threshold)
                scale = m.threshold if m.threshold > 0 else 1.0
                pen = pen + self.weight * torch.relu(s / scale - (1.0 - self.margin))
            pens.append(pen)
        return torch.stack(pens), feasible
