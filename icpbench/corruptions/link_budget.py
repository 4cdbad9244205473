"""The detection model shared by the weather corruptions: how strong a return is, relative to the
sensor's noise floor.

A scan carries no intensities, so the power of each return is modelled. The lidar equation (as
Hahner et al., ICCV 2021, write it) gives a Lambertian hard target of reflectivity rho at range R a
received peak power proportional to ``rho / R**2``. We express every power as a multiple of the
noise floor, set so that a target of the reference reflectivity ``RHO_REF`` is just detected at
``R_MAX_M`` in clear air (a Velodyne HDL-64E class sensor: about 120 m on cars, about 50 m on dark
pavement):

    margin(R, rho) = (rho / RHO_REF) * (R_MAX_M / R)**2        (>= 1: detected)

Every point of a clean scan was detected, so its unknown reflectivity is drawn log-uniformly from
``[RHO_MIN, RHO_REF]`` *conditioned on detection* (truncated below at ``RHO_REF * (R / R_MAX_M)**2``):
near points may be dark, far points must be bright. Weather then multiplies the margin by the
two-way transmittance ``exp(-2 alpha R)``; a return whose margin falls below 1 is lost. Near the
sensor the transmitter beam and the receiver field of view overlap only partly (:func:`overlap`),
which weakens echoes from the first metres.
"""

from __future__ import annotations

import numpy as np

#: Range (metres) at which a target of reflectivity RHO_REF is just detected in clear air.
R_MAX_M = 120.0
#: Reference reflectivity of R_MAX_M (a car's paint).
RHO_REF = 0.8
#: Darkest reflectivity drawn for a point (dark asphalt, tyres).
RHO_MIN = 0.05


def draw_reflectivity(ranges_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Reflectivities (N,) of points at ``ranges_m`` (N,) metres: log-uniform on
    ``[max(RHO_MIN, RHO_REF (R / R_MAX_M)^2), RHO_REF]``, i.e. conditioned on the point having been
    detected in clear air (points beyond R_MAX_M get RHO_REF)."""
    lo = np.clip(RHO_REF * (ranges_m / R_MAX_M) ** 2, RHO_MIN, RHO_REF)
    u = rng.random(ranges_m.shape)
    return np.exp(np.log(lo) + u * (np.log(RHO_REF) - np.log(lo)))


def clear_margin(ranges_m: np.ndarray, reflectivity: np.ndarray) -> np.ndarray:
    """Clear-air peak return power (N,) over the noise floor of targets at ``ranges_m`` (N,) metres
    with ``reflectivity`` (N,); at least 1 (every point of a clean scan was detected)."""
    return np.maximum((reflectivity / RHO_REF) * (R_MAX_M / ranges_m) ** 2, 1.0)

#: Range (metres) where the transmitter beam starts to overlap the receiver's field of view.
OVERLAP_START_M = 1.0
#: Range (metres) from which the overlap is complete (a bistatic sensor; returns nearer than this
#: are weakened, the paper's crossover function xi).
OVERLAP_FULL_M = 10.0


def overlap(ranges_m: np.ndarray, start_m: float = OVERLAP_START_M,
            full_m: float = OVERLAP_FULL_M) -> np.ndarray:
    """The crossover function xi(R) (same shape as ``ranges_m``, metres): 0 up to ``start_m``,
    rising linearly to 1 at ``full_m``, 1 beyond (the crossover function of Hahner et al., ICCV 2021)."""
    return np.clip((ranges_m - start_m) / max(full_m - start_m, 1e-9), 0.0, 1.0)
