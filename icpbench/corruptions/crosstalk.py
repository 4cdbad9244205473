"""Crosstalk: pulses of another lidar are taken for echoes, giving outliers at random ranges."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.corruptions.base import Corruption, rays


class Crosstalk(Corruption):
    """Crosstalk: another lidar's pulses arrive at the receiver at times unrelated to our own pulse
    (Robo3D's "cross-talk", Kong et al., ICCV 2023). A seeded share of the points is replaced by
    outliers on their own rays at ranges drawn uniformly from the receiving window
    ``[min_range_m, max_range_m]`` (default 1..120 m). The count is ``round(share * N)``; with one
    seed, the points replaced at a level are also replaced at every higher level.

    Levels (share of the points replaced):

    ========  ==============
    severity  share replaced
    ========  ==============
    1         0.005
    2         0.01
    3         0.02
    4         0.04
    5         0.08
    ========  ==============
    """

    name = "crosstalk"
    description = "Outliers at uniform random ranges along their rays (another lidar's pulses)"
    LEVELS = {1: {"share": 0.005}, 2: {"share": 0.01}, 3: {"share": 0.02}, 4: {"share": 0.04},
              5: {"share": 0.08}}

    def __init__(self, min_range_m: float = 1.0, max_range_m: float = 120.0) -> None:
        if not (0 < min_range_m < max_range_m and math.isfinite(max_range_m)):
            raise InputError("crosstalk needs 0 < min_range_m < max_range_m (metres), got "
                             f"{min_range_m}, {max_range_m}")
        super().__init__(min_range_m=float(min_range_m), max_range_m=float(max_range_m))

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        n = scan.shape[0]
        _, dirs = rays(scan)
        order = rng.permutation(n)  # the first k points of the order are replaced
        u = rng.random(n)
        k = int(round(float(level["share"]) * n))
        chosen = order[:k]
        lo, hi = self.params["min_range_m"], self.params["max_range_m"]
        out = scan.copy()
        out[chosen] = dirs[chosen] * (lo + u[chosen] * (hi - lo))[:, None]
        replaced = np.zeros(n, dtype=bool)
        replaced[chosen] = True
        return out, replaced, {"replaced": k}
