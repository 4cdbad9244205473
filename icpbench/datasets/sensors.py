"""Presets of common spinning lidars for ``lidar-sim`` (``--dataset-param sensor=NAME``).

Each preset is a :class:`~icpbench.datasets.lidar_model.LidarConfig`; the beam layouts follow the
manufacturers' data sheets (vertical field of view and beam count; the azimuth step is the one at
a 10 Hz spin), the mount heights are typical car roofs (KITTI's HDL-64E sits at 1.73 m):

========= ====== =========================== ========== =========== ========================
name      beams  elevation (deg)             azimuth    max range   model
========= ====== =========================== ========== =========== ========================
sim32     32     -25 .. +15, uniform         0.2 deg    100 m       today's default (VLP-32C-like)
vlp16     16     -15 .. +15, uniform (2 deg) 0.2 deg    100 m       Velodyne VLP-16
hdl32     32     -30.67 .. +10.67, uniform   0.16 deg   100 m       Velodyne HDL-32E
hdl64     64     -24.8 .. +2, two blocks     0.17 deg   120 m       Velodyne HDL-64E (KITTI)
os128     128    -22.5 .. +22.5, uniform     0.35 deg   100 m       Ouster OS1-128 (1024 columns)
========= ====== =========================== ========== =========== ========================

The HDL-64E has non-uniform spacing: an upper block of 32 lasers 1/3 deg apart from +2 deg down
to -8.33 deg and a lower block of 32 lasers about 0.52 deg apart from -8.83 deg to -24.8 deg.

Every field can be overridden on top of a preset with ``--dataset-param lidar={KEY: VALUE}``
(mount height, range noise, dropout, per-ring azimuth offsets, ...), see
:meth:`~icpbench.datasets.lidar_model.LidarConfig.from_any`. The live scan is subsampled to the
dataset's ``n_points`` whatever the sensor (as in the paper), so sensors differ in where the
points fall, not in how many there are.
"""

from __future__ import annotations

import numpy as np

from icpbench.core.errors import InputError
from icpbench.datasets.lidar_model import LidarConfig

#: The default sensor (today's ``lidar-sim`` model).
DEFAULT_SENSOR = "sim32"


def _hdl64_elevations() -> tuple[float, ...]:
    """The 64 HDL-64E elevation angles (degrees), highest first."""
    upper = 2.0 - np.arange(32) / 3.0  # +2 .. -8.33
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(float(round(v, 4)) for v in np.r_[upper, lower])


SENSORS: dict[str, LidarConfig] = {
    "sim32": LidarConfig(),
    "vlp16": LidarConfig(n_beams=16, vfov_deg=(-15.0, 15.0), h_res_deg=0.2, max_range_m=100.0,
                         range_noise_m=0.03, mount_height_m=1.8),
    "hdl32": LidarConfig(n_beams=32, vfov_deg=(-30.67, 10.67), h_res_deg=0.16, max_range_m=100.0,
                         range_noise_m=0.02, mount_height_m=1.9),
    "hdl64": LidarConfig(n_beams=64, vfov_deg=(-24.8, 2.0), h_res_deg=0.17, max_range_m=120.0,
                         range_noise_m=0.02, mount_height_m=1.73,
                         elevations_deg=_hdl64_elevations()),
    "os128": LidarConfig(n_beams=128, vfov_deg=(-22.5, 22.5), h_res_deg=0.35, max_range_m=100.0,
                         range_noise_m=0.03, mount_height_m=1.9),
}


def sensor_config(name: str = DEFAULT_SENSOR, overrides: LidarConfig | dict | None = None
                  ) -> LidarConfig:
    """The preset ``name`` with ``overrides`` (a dict of :class:`LidarConfig` fields, or a whole
    config, which then replaces the preset).

    Overriding ``n_beams`` or ``vfov_deg`` of a preset with explicit elevations drops them (the
    beams are then spread uniformly), unless ``elevations_deg`` is given too.

    Raises:
        InputError: unknown sensor name or invalid settings.
    """
    if name not in SENSORS:
        raise InputError(f"unknown sensor {name!r}; valid: {', '.join(SENSORS)}")
    if isinstance(overrides, LidarConfig):
        return overrides
    if overrides is None or not overrides:
        return SENSORS[name]
    if not isinstance(overrides, dict):
        raise InputError(f"lidar settings must be a dict, got {type(overrides).__name__}")
    base = SENSORS[name].to_dict()
    if {"n_beams", "vfov_deg"} & set(overrides) and "elevations_deg" not in overrides:
        base.pop("elevations_deg", None)
        if "n_beams" in overrides and "ring_azimuth_offsets_deg" not in overrides:
            base.pop("ring_azimuth_offsets_deg", None)
    return LidarConfig.from_any({**base, **overrides})

