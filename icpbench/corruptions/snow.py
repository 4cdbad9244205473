"""Snowfall: echoes from snowflakes in the beam, and attenuation of the hard returns."""

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


def _level(rate_mm_per_h: float) -> dict[str, float]:
    n0 = 3.8e3 * rate_mm_per_h**-0.87  # Gunn-Marshall intercept, 1/(m^3 mm)
    lam = 2.55 * rate_mm_per_h**-0.48  # Gunn-Marshall slope, 1/mm
    return {"rate_mm_per_h": rate_mm_per_h, "n0_per_m3_mm": round(n0, 1),
            "lambda_per_mm": round(lam, 4),
            # extinction of spheres (efficiency 2): 2 * Int N(D) pi D^2 / 4 dD = pi N0 / lambda^3
            "alpha_per_m": math.pi * n0 / lam**3 * 1e-6}


class Snow(Corruption):
    """Snowfall after Hahner et al., "LiDAR Snowfall Simulation for Robust 3D Object Detection",
    CVPR 2022.

    Physics (written from the paper; powers relative to the noise floor, see
    :mod:`icpbench.corruptions.link_budget`):

    - Snowflakes are spheres whose (melted) diameters D follow the Gunn-Marshall (1958) exponential
      distribution of the snowfall rate r: ``N(D) = N0 exp(-Lambda D)`` with
      ``N0 = 3.8e3 r^-0.87`` 1/(m^3 mm) and ``Lambda = 2.55 r^-0.48`` 1/mm.
    - Each laser beam is a cone (exit diameter ``beam_exit_diameter_mm``, full divergence
      ``beam_divergence_mrad``). A flake of diameter D at range r intercepts the share
      ``(D / d(r))^2`` of the beam of diameter d(r) and echoes it like a Lambertian target of
      reflectivity ``snow_reflectivity``: ``p = (D / d(r))^2 (rho_snow / RHO_REF) (R_max / r)^2
      xi(r) exp(-2 alpha r)``.
    - Only flakes whose echo clears the noise floor matter. Along each ray, up to its point, they
      are drawn exactly: a Poisson number with mean ``Int N0 / Lambda exp(-Lambda D_min(r))
      pi d(r)^2 / 4 dr`` (D_min(r): the smallest detectable flake at r), positions from that
      density and sizes ``D_min(r) + Exp(Lambda)``. This happens on a random subset of the rays,
      mostly within the first metres to tens of metres.
    - The hard return is attenuated by the flakes' extinction ``alpha = pi N0 / Lambda^3``
      (extinction efficiency 2): ``p_hard = margin * exp(-2 alpha R)``.
    - The sensor reports each ray's strongest echo: where a flake's echo beats the hard return, the
      point moves to the flake along its own ray (a scatter return). A hard return attenuated below
      the floor with no flake to report is lost; its slot gets a duplicate of a surviving point, so
      N is unchanged.

    Levels (snowfall rate as liquid water equivalent, light to heavy snowfall):

    ========  =============  ============  =============  ==============
    severity  rate (mm/h)    N0 (1/m^3mm)  Lambda (1/mm)  alpha (1/m)
    ========  =============  ============  =============  ==============
    1         0.5            6945.1        3.5566         4.85e-4
    2         1.0            3800.0        2.5500         7.20e-4
    3         1.5            2670.4        2.0990         9.07e-4
    4         2.0            2079.2        1.8283         1.07e-3
    5         2.5            1712.3        1.6426         1.21e-3
    ========  =============  ============  =============  ==============

    Sensor constants (settings): beam exit diameter 10 mm, divergence 3 mrad, snow reflectivity
    0.9 (fresh snow in the near infrared), overlap from 1 m to 10 m; detection reference
    R_max = 120 m at reflectivity 0.8.
    """

    name = "snow"
    description = "Snowfall (Hahner et al. CVPR 2022): snowflake echoes along random rays, attenuation"
    LEVELS = {1: _level(0.5), 2: _level(1.0), 3: _level(1.5), 4: _level(2.0), 5: _level(2.5)}

    def __init__(self, beam_divergence_mrad: float = 3.0, beam_exit_diameter_mm: float = 10.0,
                 snow_reflectivity: float = 0.9, overlap_start_m: float = OVERLAP_START_M,
                 overlap_full_m: float = OVERLAP_FULL_M) -> None:
        for key, v in (("beam_divergence_mrad", beam_divergence_mrad),
                       ("beam_exit_diameter_mm", beam_exit_diameter_mm),
                       ("snow_reflectivity", snow_reflectivity)):
            if not (v > 0 and math.isfinite(v)):
                raise InputError(f"snow {key} must be a positive number, got {v}")
        if not (0 <= overlap_start_m < overlap_full_m and math.isfinite(overlap_full_m)):
            raise InputError("snow needs 0 <= overlap_start_m < overlap_full_m (metres), got "
                             f"{overlap_start_m}, {overlap_full_m}")
        super().__init__(beam_divergence_mrad=float(beam_divergence_mrad),
                         beam_exit_diameter_mm=float(beam_exit_diameter_mm),
                         snow_reflectivity=float(snow_reflectivity),
                         overlap_start_m=float(overlap_start_m), overlap_full_m=float(overlap_full_m))

    def _beam_diameter_m(self, r: np.ndarray) -> np.ndarray:
        """Beam diameter (metres) at ranges ``r`` (metres)."""
        return self.params["beam_exit_diameter_mm"] * 1e-3 + self.params["beam_divergence_mrad"] * 1e-3 * r

    def _gain(self, r: np.ndarray, alpha: float) -> np.ndarray:
        """Echo power over the floor of a flake filling the whole beam at ranges ``r`` (metres)."""
        xi = overlap(r, self.params["overlap_start_m"], self.params["overlap_full_m"])
        return (self.params["snow_reflectivity"] / RHO_REF) * (R_MAX_M / r) ** 2 * xi \
            * np.exp(-2.0 * alpha * r)

    def flake_density(self, level: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Detectable flakes along a ray.

        Returns:
            (ranges (K,) m, expected number of detectable flakes per metre of ray (K,),
            smallest detectable melted diameter (K,) in mm; inf where nothing is detectable).
        """
        n0, lam, alpha = (float(level[k]) for k in ("n0_per_m3_mm", "lambda_per_mm", "alpha_per_m"))
        r = np.arange(self.params["overlap_start_m"] + 0.005, R_MAX_M, 0.01)
        d = self._beam_diameter_m(r)
        gain = self._gain(r, alpha)
        with np.errstate(divide="ignore"):
            d_min_mm = np.where(gain > 0, d / np.sqrt(gain) * 1e3, np.inf)
        density = n0 / lam * np.exp(-lam * d_min_mm) * np.pi / 4 * d**2
        return r, density, d_min_mm

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        lam, alpha = float(level["lambda_per_mm"]), float(level["alpha_per_m"])
        n = scan.shape[0]
        r0, dirs = rays(scan)
        reflectivity = draw_reflectivity(r0, rng)
        p_hard = clear_margin(r0, reflectivity) * np.exp(-2.0 * alpha * r0)

        grid, density, d_min_mm = self.flake_density(level)
        cum = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(grid))])
        cum = cum + 1e-12 * np.arange(cum.size)  # strictly increasing, for the inverse
        mu = np.interp(r0, grid, cum, left=0.0)  # detectable flakes in front of each point
        counts = rng.poisson(mu)
        ray = np.repeat(np.arange(n), counts)
        r_flake = np.interp(rng.random(ray.size) * mu[ray], cum, grid)
        d_mm = np.interp(r_flake, grid, d_min_mm) + rng.exponential(1.0 / lam, ray.size)
        p_flake = self._gain(r_flake, alpha) * (d_mm * 1e-3 / self._beam_diameter_m(r_flake)) ** 2

        # the strongest flake echo of every ray that has flakes
        order = np.lexsort((-p_flake, ray))
        first = order[np.r_[True, ray[order][1:] != ray[order][:-1]]] if ray.size else order
        best_p = np.zeros(n)
        best_r = np.zeros(n)
        best_p[ray[first]] = p_flake[first]
        best_r[ray[first]] = r_flake[first]

        scatter = (best_p >= 1.0) & (best_p > p_hard)
        lost = ~scatter & (p_hard < 1.0)
        out = scan.copy()
        out[scatter] = dirs[scatter] * best_r[scatter, None]
        kept = np.flatnonzero(~lost)
        if kept.size == 0:
            lost[:] = False  # nothing survives to stand in for the lost points: leave them
        elif lost.any():
            out[lost] = out[kept[rng.integers(0, kept.size, int(lost.sum()))]]
        details = {"scatter": int(scatter.sum()), "lost": int(lost.sum()),
                   "flakes_detectable": int(ray.size),
                   "scatter_range_m_median": float(np.median(best_r[scatter])) if scatter.any() else 0.0}
        return out, scatter | lost, details
