"""Occluder: a vehicle next to the sensor hides everything behind it."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.corruptions.base import Corruption


def box_entry(scan: np.ndarray, centre: np.ndarray, yaw: float, size: np.ndarray) -> np.ndarray:
    """Where each ray from the sensor origin to a point of ``scan`` first enters a box.

    Args:
        scan: (N, 3) points, sensor frame, metres (the rays run from the origin to them).
        centre: (3,) box centre, sensor frame, metres.
        yaw: rotation of the box about z, radians (its length runs along ``(cos yaw, sin yaw, 0)``).
        size: (3,) length, width, height of the box in metres.

    Returns:
        (N,) ray parameter t of the first intersection with the box surface (the point ``t * p``);
        ``inf`` where the ray misses the box. ``t < 1`` means the box lies in front of the point (or
        the point lies inside the box). The origin must be outside the box.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # box frame -> sensor frame
    origin = rot.T @ (-np.asarray(centre, dtype=np.float64))
    v = scan @ rot  # ray directions (not normalised) in the box frame: R^T p
    half = np.asarray(size, dtype=np.float64) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origin) / v
        t2 = (half - origin) / v
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    parallel = v == 0  # a ray parallel to a slab: inside it everywhere or nowhere
    inside = np.abs(origin) <= half
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), lo)
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), hi)
    t_in, t_out = lo.max(axis=1), hi.min(axis=1)
    return np.where((t_in <= t_out) & (t_out > 0), np.maximum(t_in, 0.0), np.inf)


class Occluder(Corruption):
    """Occluder: a vehicle-sized box stands next to the sensor (a parked or passing car or van);
    nothing behind it returns. Every point whose ray passes through the box (or that lies inside it)
    is replaced by the ray's first intersection with the box surface; points outside its shadow are
    unchanged. Severity grading as in Robo3D (Kong et al., ICCV 2023); the closer the box, the wider
    its shadow.

    The box (``box_size_m``, default 4.5 x 1.8 x 1.6 m, length x width x height) stands on the
    ground, ``sensor_height_m`` below the sensor (default: estimated as minus the 5th percentile of
    the points' z), broadside to the sensor (its length perpendicular to the bearing from the
    sensor). A seeded bearing (uniform over 360 degrees, the side) and a seeded quantile u pick the
    horizontal distance of its centre ``d_min + u (d_max - d_min)`` in the level's interval; with one
    seed, every level puts the box on the same bearing, nearer at higher levels.

    Levels (horizontal distance from the sensor to the box centre, and the approximate azimuth
    width of its shadow for the default box):

    ========  ===================  ============
    severity  centre distance (m)  shadow (deg)
    ========  ===================  ============
    1         14 - 18              19 - 15
    2         10 - 14              28 - 19
    3         7 - 10               40 - 28
    4         5 - 7                58 - 40
    5         3.5 - 5              82 - 58
    ========  ===================  ============
    """

    name = "occluder"
    description = "A vehicle-sized box next to the sensor; its shadow returns only its surface"
    LEVELS = {1: {"distance_min_m": 14.0, "distance_max_m": 18.0},
              2: {"distance_min_m": 10.0, "distance_max_m": 14.0},
              3: {"distance_min_m": 7.0, "distance_max_m": 10.0},
              4: {"distance_min_m": 5.0, "distance_max_m": 7.0},
              5: {"distance_min_m": 3.5, "distance_max_m": 5.0}}

    def __init__(self, box_size_m: tuple[float, float, float] | list[float] = (4.5, 1.8, 1.6),
                 sensor_height_m: float | None = None) -> None:
        size = [float(v) for v in box_size_m]
        if len(size) != 3 or not all(v > 0 and math.isfinite(v) for v in size):
            raise InputError(f"occluder box_size_m must be 3 positive numbers (length, width, "
                             f"height in metres), got {box_size_m!r}")
        if sensor_height_m is not None and not math.isfinite(sensor_height_m):
            raise InputError(f"occluder sensor_height_m must be a finite number, got {sensor_height_m}")
        if math.hypot(size[0], size[1]) / 2 >= min(v["distance_min_m"] for v in self.LEVELS.values()):
            raise InputError(f"occluder box_size_m {size} is too large: the sensor would be inside it")
        super().__init__(box_size_m=size, sensor_height_m=sensor_height_m)

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        size = np.asarray(self.params["box_size_m"])
        height = self.params["sensor_height_m"]
        ground_z = -float(height) if height is not None else float(np.percentile(scan[:, 2], 5))
        bearing = float(rng.uniform(0.0, 2.0 * math.pi))
        u = float(rng.random())
        dist = level["distance_min_m"] + u * (level["distance_max_m"] - level["distance_min_m"])
        centre = np.array([dist * math.cos(bearing), dist * math.sin(bearing), ground_z + size[2] / 2])
        yaw = bearing + math.pi / 2
        t = box_entry(scan, centre, yaw, size)
        shadow = t < 1.0
        out = scan.copy()
        out[shadow] = scan[shadow] * t[shadow, None]
        details = {"box_centre_m": centre.tolist(), "box_yaw_rad": yaw, "box_size_m": size.tolist(),
                   "bearing_rad": bearing, "distance_m": dist, "ground_z_m": ground_z,
                   "shadowed": int(shadow.sum())}
        return out, shadow, details
