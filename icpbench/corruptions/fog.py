"""Fog: attenuation of the hard returns and backscatter from the fog near the sensor."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.corruptions.base import Corruption, rays
from icpbench.corruptions.link_budget import (
    OVERLAP_FULL_M,
    OVERLAP_START_M,
    R_MAX_M,
    RHO_REF,
    clear_margin,
    draw_reflectivity,
    overlap,
)

#: Speed of light (m/s).
C_M_PER_S = 299_792_458.0


def _level(alpha_per_m: float) -> dict[str, float]:
    mor_m = math.log(20.0) / alpha_per_m
    return {"alpha_per_m": alpha_per_m, "mor_m": round(mor_m, 1),
            "beta_per_m_sr": 0.046 / mor_m}


class Fog(Corruption):
    """Fog after Hahner et al., "Fog Simulation on Real LiDAR Point Clouds for 3D Object Detection
    in Adverse Weather", ICCV 2021.

    Physics (the paper's lidar equation, written here from the paper; powers relative to the noise
    floor, see :mod:`icpbench.corruptions.link_budget`):

    - *Hard returns* (the scan's points) are attenuated by the two-way transmittance: a point at
      range R with clear-air margin m (from a reflectivity drawn per point, conditioned on it having
      been detected) keeps ``p_hard = m * exp(-2 alpha R)``.
    - *Soft returns*: the fog backscatters the pulse. The received backscatter at range R is the
      sin^2 pulse of half-power width tau_H convolved with the fog's response
      ``beta * xi(r) / r^2 * exp(-2 alpha r)`` (xi: the transmitter/receiver overlap):
      ``p_soft(R) = (beta / beta_ref) R_max^2 Int_{R - c tau_H}^{R} sin^2(pi (R - r) / (c tau_H))
      xi(r) / r^2 exp(-2 alpha r) dr`` with ``beta_ref = RHO_REF / pi``. It peaks a few metres from
      the sensor.
    - The sensor reports the strongest echo of each ray: a point is lost when its attenuated hard
      return falls below the noise floor or below the fog's backscatter peak (the paper's rule
      "soft beats hard"). As in the paper, the ray keeps a return: the lost point becomes the fog
      return on its own ray, at a range drawn from the backscatter profile within its half-power
      window (never beyond the original point). Points are never dropped, so N is unchanged.

    Levels: the paper's fog densities, with the meteorological optical range MOR = ln(20) / alpha
    and the backscattering coefficient beta = 0.046 / MOR the paper uses.

    ========  ===========  =======  ===============  ======================
    severity  alpha (1/m)  MOR (m)  beta (1/(m sr))  backscatter peak/floor
    ========  ===========  =======  ===============  ======================
    1         0.005        599.1    7.68e-5          0.29 (at 6.1 m)
    2         0.01         299.6    1.54e-4          0.56 (at 6.1 m)
    3         0.02         149.8    3.07e-4          1.05 (at 6.0 m)
    4         0.03          99.9    4.61e-4          1.48 (at 5.9 m)
    5         0.06          49.9    9.21e-4          2.50 (at 5.8 m)
    ========  ===========  =======  ===============  ======================

    Sensor constants (settings): half-power pulse width ``pulse_width_ns`` = 20 ns (as in the paper),
    overlap from ``overlap_start_m`` = 1 m to ``overlap_full_m`` = 10 m; detection reference
    R_max = 120 m at reflectivity 0.8 (the last column follows from them). The backscatter
    peak exceeds the noise floor from severity 3 on; at severities 1-2 the lost points' fog returns
    are below the floor (counted in the record's ``replaced_below_floor``).
    """

    name = "fog"
    description = "Fog (Hahner et al. ICCV 2021): attenuation exp(-2 alpha R), backscatter near the sensor"
    LEVELS = {1: _level(0.005), 2: _level(0.01), 3: _level(0.02), 4: _level(0.03), 5: _level(0.06)}

    def __init__(self, pulse_width_ns: float = 20.0, overlap_start_m: float = OVERLAP_START_M,
                 overlap_full_m: float = OVERLAP_FULL_M) -> None:
        if not (pulse_width_ns > 0 and math.isfinite(pulse_width_ns)):
            raise InputError(f"fog pulse_width_ns must be a positive number, got {pulse_width_ns}")
        if not (0 <= overlap_start_m < overlap_full_m and math.isfinite(overlap_full_m)):
            raise InputError("fog needs 0 <= overlap_start_m < overlap_full_m (metres), got "
                             f"{overlap_start_m}, {overlap_full_m}")
        super().__init__(pulse_width_ns=float(pulse_width_ns), overlap_start_m=float(overlap_start_m),
                         overlap_full_m=float(overlap_full_m))

    def backscatter_profile(self, alpha_per_m: float, beta_per_m_sr: float
                            ) -> tuple[np.ndarray, np.ndarray]:
        """The fog's backscatter power over the noise floor as a function of range.

        Returns:
            (ranges (K,) in metres, power (K,) relative to the noise floor).
        """
        pulse_m = C_M_PER_S * self.params["pulse_width_ns"] * 1e-9  # c tau_H: the pulse's length
        dr = 0.01
        r = np.arange(self.params["overlap_start_m"], self.params["overlap_full_m"] + 3 * pulse_m, dr)
        response = overlap(r, self.params["overlap_start_m"], self.params["overlap_full_m"]) \
            / r**2 * np.exp(-2.0 * alpha_per_m * r)
        kernel = np.sin(np.pi * np.arange(0.0, pulse_m + dr / 2, dr) / pulse_m) ** 2
        integral = np.convolve(response, kernel)[: r.size] * dr  # Int over [R - c tau_H, R]
        return r, (beta_per_m_sr / (RHO_REF / np.pi)) * R_MAX_M**2 * integral

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        alpha = float(level["alpha_per_m"])
        r0, dirs = rays(scan)
        reflectivity = draw_reflectivity(r0, rng)
        u = rng.random(r0.shape)  # where in the backscatter window each ray's fog return lies
        p_hard = clear_margin(r0, reflectivity) * np.exp(-2.0 * alpha * r0)

        grid, p_soft = self.backscatter_profile(alpha, float(level["beta_per_m_sr"]))
        peak = float(p_soft.max())
        window = p_soft >= 0.5 * peak  # the half-power window of the fog return
        lo, hi = int(np.argmax(window)), int(window.size - np.argmax(window[::-1]))
        cdf = np.cumsum(p_soft[lo:hi])
        r_back = np.interp(u * cdf[-1], cdf, grid[lo:hi])

        replaced = p_hard < max(1.0, peak)
        out = scan.copy()
        out[replaced] = dirs[replaced] * np.minimum(r_back[replaced], r0[replaced])[:, None]
        details = {"backscatter_peak_m": float(grid[np.argmax(p_soft)]),
                   "backscatter_window_m": [float(grid[lo]), float(grid[hi - 1])],
                   "backscatter_peak_over_floor": peak,
                   "replaced": int(replaced.sum()),
                   "replaced_below_floor": int(replaced.sum()) if peak < 1.0 else 0}
        return out, replaced, details
