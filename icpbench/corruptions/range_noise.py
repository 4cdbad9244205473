"""Range noise: extra Gaussian noise of the measured range, along each ray."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from icpbench.corruptions.base import Corruption, rays

#: Smallest range (metres) a noisy point may get (it stays on its own side of the sensor).
MIN_NOISY_RANGE_M = 0.01


class RangeNoise(Corruption):
    """Range noise: every range gets extra zero-mean Gaussian noise along its own ray (a degraded
    timing circuit, a dirty or wet window, a cheaper sensor). Directions are kept; only the range
    changes, ``r' = max(r + sigma * n, 0.01 m)`` with n ~ N(0, 1) per point. With one seed, the
    noise of every level is the same draw scaled by the level's sigma. Severity grading as in Robo3D
    (Kong et al., ICCV 2023).

    Levels (standard deviation of the added range noise; a good sensor's own is about 0.02 m):

    ========  =========
    severity  sigma (m)
    ========  =========
    1         0.02
    2         0.04
    3         0.08
    4         0.15
    5         0.30
    ========  =========
    """

    name = "range-noise"
    description = "Gaussian range noise along each ray (directions kept)"
    LEVELS = {1: {"sigma_m": 0.02}, 2: {"sigma_m": 0.04}, 3: {"sigma_m": 0.08},
              4: {"sigma_m": 0.15}, 5: {"sigma_m": 0.30}}

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        r, dirs = rays(scan)
        noisy = r + float(level["sigma_m"]) * rng.standard_normal(r.shape)
        clamped = noisy < MIN_NOISY_RANGE_M
        new_r = np.maximum(noisy, MIN_NOISY_RANGE_M)
        moved = new_r != r
        out = np.where(moved[:, None], dirs * new_r[:, None], scan)
        return out, moved, {"clamped": int(clamped.sum())}
