"""``degeneracy``: whether the geometry at the estimated pose constrains every direction of travel.

Each scan point moved into the map frame by ``T_hat`` is paired with its nearest map point when it
lies within ``gate_m``; that point's unit normal ``n_i`` is the direction the point-to-plane cost
constrains. The translation block of the point-to-plane Hessian (Gauss-Newton normal matrix,
weights 1) is ``H_tt = sum_i n_i n_i^T``, whose trace is the number K of pairs. Its smallest
eigenvalue ``lambda_min`` measures the weakest direction: Zhang, Kaess and Singh ("On degeneracy of
optimization-based state estimation problems", ICRA 2016) call it the degeneracy factor, and X-ICP
(Tuna et al., "X-ICP: Localizability-Aware LiDAR Registration for Robust Localization in Extreme
Environments", IEEE T-RO 2024) reads localisability off the same constraint directions
(:mod:`icpbench.analysis.localisability`). Along a weak direction a small change of the scan (a
corruption, an attack) moves the pose far, and the residual and inlier checks cannot see the error
(the scan still fits the map after sliding along a corridor).

The score is ``K / lambda_min`` (dimensionless): the inverse of the weakest direction's share of
the unit constraints. It is 3 when the normals are spread evenly over the three axes (a box room),
grows without bound as one direction loses its constraints (inf when ``lambda_min`` is 0, or
fewer than 3 pairs exist), and does not depend on the point count. Unlike the condition number
``lambda_max / lambda_min`` it does not rise when one direction is very well constrained (the
ground under a lidar). Only the translation block is used: that is the error Table 1 reports.

Defaults (uncalibrated; :func:`icpbench.harness.monitoring.calibrate` sets a threshold for a
false-alarm rate): gate 1 m (lidar maps in metres; on ``objects`` give it in normalised units) and
threshold 250 (the weakest direction holds 0.4% of the constraints). A degenerate place fires on
clean scans too, and should: there a stack does not trust the registration. On every second scan
of the lidar-sim test split (186 scans) at the true pose the score was 4-7 on dense stretches,
8-25 on open ones and underpasses, and 115-191 on highways (long walls, little across them).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import torch

from icpbench.core.registry import Range
from icpbench.monitors.base import Monitor
from icpbench.monitors.differentiable import DiffInput, soft_within, straight_through
from icpbench.monitors.inputs import MonitorInput


def translation_hessian(normals: np.ndarray) -> np.ndarray:
    """``sum_i n_i n_i^T`` (3, 3) of unit normals (K, 3) (map frame): the translation block of the
    unweighted point-to-plane Hessian."""
    n = np.asarray(normals, dtype=np.float64)
    return n.T @ n


class DegeneracyMonitor(Monitor):
    """``K / lambda_min`` of the point-to-plane translation Hessian of the K gated pairs at ``T_hat``.

    Args:
        threshold: fires above this score (3 is the best possible; 250 means the weakest direction
            holds 0.4% of the constraints).
        gate_m: largest distance (metres) from a scan point to its nearest map point for the pair
            to count.
    """

    name: ClassVar[str] = "degeneracy"
    description: ClassVar[str] = ("inverse share of the weakest translation direction in the "
                                  "point-to-plane Hessian at the estimated pose")
    param_ranges: ClassVar[dict[str, Range]] = {"threshold": Range(3.0),
                                                "gate_m": Range(0.0, lo_open=True)}
    differentiable: ClassVar[bool] = True

    def __init__(self, *, threshold: float = 250.0, gate_m: float = 1.0) -> None:
        super().__init__(threshold=threshold, gate_m=gate_m)
        self.gate_m = float(gate_m)

    def _score(self, inp: MonitorInput) -> float:
        nn = inp.nearest
        keep = nn.within(self.gate_m)
        k = int(keep.sum())
        if k < 3:
            return math.inf
        lam = float(np.linalg.eigvalsh(translation_hessian(inp.normals()[nn.index[keep]]))[0])
        return k / lam if lam > 0 else math.inf

    def _differentiable_score(self, x: DiffInput) -> torch.Tensor:
        # the exact K / lambda_min, with the slope of the same ratio over logistic pair weights
        # (a normal belongs to the map, so only the weights move: points entering or leaving
        # the gate)
        pr = x.pairs
        keep = pr.within(self.gate_m)
        k = int(keep.sum())
        n_all = x.normals()[pr.index]
        lam = (float(np.linalg.eigvalsh(translation_hessian(n_all[keep]))[0]) if k >= 3
               else 0.0)
        if lam <= 0:
            return torch.tensor(math.inf, dtype=torch.float64)
        w = soft_within(pr.dist, self.gate_m)
        n = torch.as_tensor(n_all)
        soft = w.sum() / torch.linalg.eigvalsh((n * w[:, None]).T @ n)[0]
        return straight_through(k / lam, soft)
