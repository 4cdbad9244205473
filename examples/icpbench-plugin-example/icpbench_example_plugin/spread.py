"""Monitor ``spread``: RMS distance (metres) from each scan point within a gate to its nearest map
point at the estimated pose; with a differentiable score, so gradient attacks see it too."""

from typing import ClassVar

import numpy as np
import torch

from icpbench.core.registry import Range
from icpbench.monitors.base import Monitor
from icpbench.monitors.differentiable import DiffInput
from icpbench.monitors.inputs import MonitorInput


class SpreadMonitor(Monitor):
    """Fires when the scan at ``T_hat`` lies, on average, far from the map's points.

    Args:
        threshold: fires above this RMS distance (metres).
        gate_m: only scan points with a map point closer than this count (metres).
    """

    name: ClassVar[str] = "spread"
    description: ClassVar[str] = "RMS point-to-point distance of the gated scan points (example plugin)"
    param_ranges: ClassVar[dict[str, Range]] = {"threshold": Range(0.0, lo_open=True),
                                                "gate_m": Range(0.0, lo_open=True)}
    unit: ClassVar[str] = "m"
    differentiable: ClassVar[bool] = True

    def __init__(self, *, threshold: float = 0.3, gate_m: float = 1.0) -> None:
        super().__init__(threshold=threshold, gate_m=gate_m)
        self.gate_m = float(gate_m)

    def _score(self, inp: MonitorInput) -> float:
        d = inp.nearest.dist[inp.nearest.within(self.gate_m)]
        return float(np.sqrt(np.mean(d * d))) if d.size else self.gate_m

    def _differentiable_score(self, x: DiffInput) -> torch.Tensor:
        keep = torch.as_tensor(x.pairs.within(self.gate_m))
        if not bool(keep.any()):
            return torch.tensor(self.gate_m, dtype=torch.float64)
        return torch.sqrt(torch.mean(x.pairs.dist[keep] ** 2))
