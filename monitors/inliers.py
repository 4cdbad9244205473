"""``inliers``: the share of the scan that finds no map at the estimated pose.

Each scan point moved into the map frame by ``T_hat`` counts as an inlier when its nearest map
point lies within ``gate_m``. The score is ``1 - (inliers / N)`` (dimensionless, 0..1): the
complement of the "fitness" registration libraries report (Open3D's ``RegistrationResult``).
A pose off by more than the gate leaves the surfaces across its error without partners.

Unlike the registration's own ``inlier_fraction`` (the target's gate, e.g. ``d_max`` = 5 m on
lidar, and whatever correspondence rule the target uses), this monitor applies one gate to every
target, so targets are checked alike.

Defaults (uncalibrated; :func:`icpbench.harness.monitoring.calibrate` sets a threshold for a
false-alarm rate): gate 0.5 m and threshold 0.4, for lidar maps in metres. Clean lidar scans have
outliers of their own (cars and other clutter the map lacks, places the map's passes did not
see): on every second scan of the lidar-sim test split (186 scans) at the true pose the score was
0.16 (median) and 0.34 (largest, a highway stretch); moving the p2plane ICP's pose of 24 of them by
1 m across the street raised it to 0.35-0.71 (median 0.45). The gate must be larger than the
map's point spacing, or clean scans have outliers between map points.
"""

from __future__ import annotations

from typing import ClassVar

import torch

from icpbench.core.registry import Range
from icpbench.monitors.base import Monitor
from icpbench.monitors.differentiable import DiffInput, soft_within, straight_through
from icpbench.monitors.inputs import MonitorInput


class InlierMonitor(Monitor):
    """``1 -`` the share of scan points with a map point within ``gate_m`` at ``T_hat``.

    Args:
        threshold: fires above this outlier share (0..1).
        gate_m: distance (metres) within which a scan point's nearest map point makes it an inlier.
    """

    name: ClassVar[str] = "inliers"
    description: ClassVar[str] = ("1 - share of scan points with a map point within a gate at the "
                                  "estimated pose")
    param_ranges: ClassVar[dict[str, Range]] = {"threshold": Range(0.0, 1.0, hi_open=True),
                                                "gate_m": Range(0.0, lo_open=True)}
    differentiable: ClassVar[bool] = True

    def __init__(self, *, threshold: float = 0.4, gate_m: float = 0.5) -> None:
        super().__init__(threshold=threshold, gate_m=gate_m)
        self.gate_m = float(gate_m)

    def _score(self, inp: MonitorInput) -> float:
        return 1.0 - float(inp.nearest.within(self.gate_m).mean())

    def _differentiable_score(self, x: DiffInput) -> torch.Tensor:
        # the exact outlier share, with the slope of a logistic count of the inliers
        pr, n = x.pairs, x.scan.shape[0]
        exact = 1.0 - float(pr.within(self.gate_m).sum()) / n
        return straight_through(exact, 1.0 - soft_within(pr.dist, self.gate_m).sum() / n)
