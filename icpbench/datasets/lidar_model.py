"""A spinning multi-beam lidar, ray-cast against triangle meshes with Open3D's ``RaycastingScene``.

Sensor frame: origin at the optical centre, x forward, y left, z up (metres). A sweep fires
``n_beams`` lasers at fixed elevation angles (uniform over ``vfov_deg``, or the explicit
``elevations_deg`` of a real sensor with non-uniform spacing) at every azimuth step of
``h_res_deg`` over 360 degrees, each ring shifted by its own azimuth offset
(``ring_azimuth_offsets_deg``, like the per-laser rotational corrections of a Velodyne); the
motion during a sweep is ignored (scans are deskewed). Presets of common sensors are in
:mod:`icpbench.datasets.sensors`. Each
return is the first hit of the ray with the scene, kept when its range lies in
``[min_range_m, max_range_m]``, with Gaussian range noise of standard deviation ``range_noise_m``
along the beam. Optional effects: random dropouts, and spurious weather returns (snowflakes /
rain drops: a ray hits a particle at a random short range before the surface).

Hit normals are the exact normals of the hit triangles, turned to face the sensor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # Open3D is imported where rays are cast: cached scans load without it
    import open3d as o3d

from icpbench.core.errors import InputError


@dataclass(frozen=True)
class LidarConfig:
    """Lidar model parameters (defaults: a 32-beam sensor with a -25..+15 degree vertical field of
    view, like a Velodyne VLP-32C, at 0.2 degree azimuth steps, i.e. 10 Hz).

    Attributes:
        n_beams: number of lasers.
        vfov_deg: (lowest, highest) elevation angle in degrees; beams are spread uniformly.
        h_res_deg: azimuth step in degrees (0.2 -> 1800 firings per sweep).
        min_range_m, max_range_m: valid range interval (metres); nearer returns (the ego vehicle)
            and farther ones are dropped.
        range_noise_m: standard deviation of the Gaussian range noise (metres).
        dropout: probability that a valid return is lost.
        mount_height_m: height of the optical centre above the road (metres).
        elevations_deg: explicit elevation angle of every beam in degrees (``n_beams`` values,
            any order; empty: uniform over ``vfov_deg``). ``vfov_deg`` must then be their
            (min, max).
        ring_azimuth_offsets_deg: azimuth offset of every ring in degrees (``n_beams`` values in
            the order of the elevations; empty: all 0).

    The two per-beam fields are left out of :meth:`to_dict` while empty, so configurations that do
    not use them keep their old parameter hash (dataset cache key).
    """

    n_beams: int = 32
    vfov_deg: tuple[float, float] = (-25.0, 15.0)
    h_res_deg: float = 0.2
    min_range_m: float = 2.0
    max_range_m: float = 100.0
    range_noise_m: float = 0.02
    dropout: float = 0.0
    mount_height_m: float = 1.9
    elevations_deg: tuple[float, ...] = ()
    ring_azimuth_offsets_deg: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        lo, hi = self.vfov_deg
        if self.n_beams < 1 or not (-90 <= lo <= hi <= 90):
            raise InputError(f"lidar needs n_beams >= 1 and -90 <= vfov low <= high <= 90; got "
                             f"n_beams={self.n_beams}, vfov_deg={self.vfov_deg}")
        if not (0 < self.h_res_deg <= 10):
            raise InputError(f"h_res_deg must be in (0, 10], got {self.h_res_deg}")
        if not (0 <= self.min_range_m < self.max_range_m):
            raise InputError("need 0 <= min_range_m < max_range_m")
        if self.range_noise_m < 0 or not (0 <= self.dropout < 1):
            raise InputError("range_noise_m must be >= 0 and dropout in [0, 1)")
        if not self.mount_height_m > 0:
            raise InputError(f"mount_height_m must be positive, got {self.mount_height_m}")
        for what, vals in (("elevations_deg", self.elevations_deg),
                           ("ring_azimuth_offsets_deg", self.ring_azimuth_offsets_deg)):
            if vals and len(vals) != self.n_beams:
                raise InputError(f"{what} needs one value per beam ({self.n_beams}), got {len(vals)}")
            if not np.all(np.isfinite(np.asarray(vals, dtype=np.float64))):
                raise InputError(f"{what} must be finite numbers")
        if self.elevations_deg and not np.allclose(
                [min(self.elevations_deg), max(self.elevations_deg)], [lo, hi], atol=1e-6):
            raise InputError(f"vfov_deg {self.vfov_deg} must be the (min, max) of elevations_deg "
                             f"({min(self.elevations_deg)}, {max(self.elevations_deg)})")

    @classmethod
    def from_any(cls, cfg: LidarConfig | dict | None) -> LidarConfig:
        """A config from None (defaults), a dict of overrides, or a config."""
        if cfg is None:
            return cls()
        if isinstance(cfg, LidarConfig):
            return cfg
        if isinstance(cfg, dict):
            unknown = set(cfg) - set(cls.__dataclass_fields__)
            if unknown:
                raise InputError(f"unknown lidar setting(s) {sorted(unknown)}; valid: "
                                 f"{sorted(cls.__dataclass_fields__)}")
            kw = dict(cfg)
            for key in ("vfov_deg", "elevations_deg", "ring_azimuth_offsets_deg"):
                if key in kw:
                    kw[key] = tuple(float(v) for v in kw[key])
            return cls(**kw)
        raise InputError(f"lidar settings must be a LidarConfig or a dict, got {type(cfg).__name__}")

    def to_dict(self) -> dict:
        """JSON-ready settings; the per-beam fields only when set (see the class docstring)."""
        d = asdict(self)
        d["vfov_deg"] = list(self.vfov_deg)
        for key in ("elevations_deg", "ring_azimuth_offsets_deg"):
            if d[key]:
                d[key] = list(d[key])
            else:
                del d[key]
        return d

    def elevations(self) -> np.ndarray:
        """Elevation angle of every beam (n_beams,) in degrees."""
        if self.elevations_deg:
            return np.asarray(self.elevations_deg, dtype=np.float64)
        return np.linspace(self.vfov_deg[0], self.vfov_deg[1], self.n_beams)

    def directions(self, azimuth_offset_rad: float = 0.0) -> np.ndarray:
        """Unit beam directions (n_beams * n_azimuth, 3) in the sensor frame, beam-major."""
        el = np.deg2rad(self.elevations())[:, None]
        az = (np.deg2rad(np.arange(0.0, 360.0, self.h_res_deg)) + azimuth_offset_rad)[None, :]
        if self.ring_azimuth_offsets_deg:
            az = az + np.deg2rad(np.asarray(self.ring_azimuth_offsets_deg, dtype=np.float64))[:, None]
        ce = np.cos(el)
        return np.stack([ce * np.cos(az), ce * np.sin(az),
                         np.broadcast_to(np.sin(el), (el.shape[0], az.shape[1]))], -1).reshape(-1, 3)


def make_scene(vertices: np.ndarray, triangles: np.ndarray, threads: int = 1
               ) -> o3d.t.geometry.RaycastingScene | None:
    """An Open3D raycasting scene of one triangle mesh (vertices (V, 3), triangles (F, 3));
    None for an empty mesh."""
    if len(triangles) == 0:
        return None
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene(nthreads=threads)
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


@dataclass
class LidarScan:
    """One simulated sweep.

    Attributes:
        points: (K, 3) float64 returns in the sensor frame (metres), range noise included.
        normals: (K, 3) float64 unit normals of the hit surfaces in the sensor frame, facing the
            sensor (weather returns: the reversed beam direction).
        source: (K,) int8 index of the scene each return came from (the order of ``scenes``),
            -1 for weather returns.
    """

    points: np.ndarray
    normals: np.ndarray
    source: np.ndarray


def cast_scan(scenes: Sequence[o3d.t.geometry.RaycastingScene | None], T_world_sensor: np.ndarray,
              cfg: LidarConfig, rng: np.random.Generator, *, weather_rate: float = 0.0,
              weather_range_m: tuple[float, float] = (2.0, 25.0), threads: int = 1) -> LidarScan:
    """Simulate one sweep from the sensor pose ``T_world_sensor`` (4, 4) against several scenes
    (the nearest hit over all scenes wins, e.g. static town + parked cars + a passing truck).

    ``weather_rate`` is the probability that a ray returns from a particle at a range uniform in
    ``weather_range_m`` (if that is nearer than the surface). The azimuth of the first firing is
    random, so two sweeps from the same pose sample different directions.
    """
    T = np.asarray(T_world_sensor, dtype=np.float64)
    R = np.ascontiguousarray(T[:3, :3])
    dirs = cfg.directions(rng.uniform(0, np.deg2rad(cfg.h_res_deg)))
    dw = dirs @ np.ascontiguousarray(R.T)
    rays = np.empty((len(dirs), 6), dtype=np.float32)
    rays[:, :3] = T[:3, 3]
    rays[:, 3:] = dw
    import open3d as o3d

    rays_t = o3d.core.Tensor(rays)
    t_hit = np.full(len(dirs), np.inf, dtype=np.float32)
    source = np.full(len(dirs), -2, dtype=np.int8)
    answers = []
    for k, scene in enumerate(scenes):
        if scene is None:
            continue
        ans = scene.cast_rays(rays_t, nthreads=threads)
        th = ans["t_hit"].numpy()
        closer = th < t_hit
        t_hit[closer] = th[closer]
        source[closer] = k
        answers.append((k, ans["primitive_normals"].numpy()))
    if weather_rate > 0:
        lo, hi = weather_range_m
        flake = rng.random(len(dirs)) < weather_rate
        r_flake = rng.uniform(lo, hi, len(dirs)).astype(np.float32)
        hit = flake & (r_flake < t_hit)
        t_hit[hit] = r_flake[hit]
        source[hit] = -1
    valid = np.isfinite(t_hit) & (t_hit >= cfg.min_range_m) & (t_hit <= cfg.max_range_m)
    if cfg.dropout > 0:
        valid &= rng.random(len(dirs)) >= cfg.dropout
    idx = np.flatnonzero(valid)
    src = source[idx]
    d_s = dirs[idx]
    r = t_hit[idx].astype(np.float64) + rng.normal(0.0, cfg.range_noise_m, len(idx))
    pts = d_s * r[:, None]
    nrm_w = -dw[idx]  # weather returns face the sensor
    for k, normals in answers:
        m = src == k
        nrm_w[m] = normals[idx[m]]
    nrm = nrm_w @ R  # world -> sensor: R^T n
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    flip = (nrm * d_s).sum(1) > 0
    nrm[flip] *= -1
    return LidarScan(points=pts, normals=nrm, source=src)
