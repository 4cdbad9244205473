"""``lidar-sim``: teach-and-repeat localisation in a simulated lidar town (the default benchmark).

This mirrors the Boreas protocol of Zhang et al. (ICRA 2025, §IV-A), itself following the teach
and repeat setup of Burnett et al. (2023): a *teach* pass along a closed route builds submaps; the
live scans of *repeat* passes are localised against them. Here everything is simulated, so the
ground truth is exact:

* the town (:mod:`icpbench.datasets.town`) is a set of triangle meshes along a ~2.8 km loop with
  labelled stretches: dense suburban streets, open parking lots and fields, a highway and an
  underpass;
* the lidar (:mod:`icpbench.datasets.lidar_model`) is a spinning multi-beam sensor ray-cast with
  Open3D's ``RaycastingScene``;
* teach pass (pass 0): the vehicle drives the lane centre; a scan every ``teach_spacing_m``. The
  submap of teach vertex ``v`` (at arc length ``v * sample_spacing_m``) accumulates the teach
  scans within ``submap_window_m`` along the route, cropped to ``submap_radius_m`` around the
  vertex, voxel-averaged (``map_voxel_m``) with the exact surface normals of the hit triangles;
* repeat passes 1, 2, ... (each with its own seed): for every vertex one live scan from a pose
  near it (longitudinal jitter up to a quarter of the vertex spacing, a lateral offset within the
  lane, a small heading error), with the parked cars re-drawn, sometimes a passing truck in the
  next lane occluding the view, and optional spurious weather returns;
* sample (:func:`~icpbench.datasets.submaps.make_sample`): the live scan subsampled to
  ``n_points`` and the vertex submap, both in the *true vehicle frame of the live scan* (x forward
  along the route, y left, z up; origin at the lidar), so pose errors ``rho_x``/``rho_y`` are
  longitudinal/lateral (docs/architecture.md, "Frames, units and pose error"). The scan is then
  moved by the paper's random offset
  (uniform +-0.3 m, +-10 deg on all axes): ``T_gt`` maps scan->map and ``T_init`` is the identity.

Variety (beyond the paper): ``town_seed=N`` builds another town
(:func:`~icpbench.datasets.town_style.random_style`: route, stretch order and lengths, road widths,
houses, densities, sloping and cambered ground, irregular vegetation, signs, posts, kerbs, and
moving road users in the repeat passes that never reach the map); ``sensor=NAME`` picks a lidar
preset (:mod:`icpbench.datasets.sensors`: ``sim32`` (default), ``vlp16``, ``hdl32``, ``hdl64``,
``os128``), with ``lidar={...}`` overriding its fields. Without them, the original town and sensor
are generated exactly as before (same scans, sample ids and cache folder). A *list* of town seeds
and/or sensors (``town_seed=[1,2,3]``) makes :meth:`LidarSimDataset.create` (what the runner calls)
return a :class:`~icpbench.datasets.lidar_mix.LidarSimMix`:
every (town, sensor) combination, each generated and cached once in its own folder, shuffled
together; evaluate on other town seeds for a generalisation split.

Train and test splits are disjoint sets of repeat passes. Generated scans and submaps are cached
as ``.npz`` under ``<cache_dir>/lidar-sim/<hash of the parameters>/`` (written atomically); the
random offsets are re-drawn from the seed when a sample is loaded. By default samples come in a
seeded shuffled order, so ``dataset.take(k)`` is spread over the whole route; ``order="route"``
gives passes in driving order.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Sample
from icpbench.datasets import submaps as sm
from icpbench.datasets.base import Dataset, Split, default_cache_dir
from icpbench.datasets.lidar_model import LidarConfig, cast_scan, make_scene
from icpbench.datasets.sensors import DEFAULT_SENSOR, sensor_config
from icpbench.datasets.town import PLACES, Route, Town, make_ground, make_route, make_town
from icpbench.datasets.town_style import town_style

FORMAT_VERSION = 1  # bump whenever the town, lidar or submap code changes what is generated
#: Random streams (third key of :func:`~icpbench.datasets.submaps.sample_rng`).
_CARS, _LIVE_POSE, _LIVE_SCAN, _SUBSAMPLE, _OFFSET, _TEACH, _PASS, _ORDER, _MOVERS = range(9)


#: Towns built in this process, shared by datasets of the same town (e.g. one per sensor).
_TOWNS = sm.LRU(2)


def _single(value: Any) -> Any:
    """A one-element list or tuple as its element; anything else unchanged."""
    if isinstance(value, list | tuple) and len(value) == 1:
        return value[0]
    return value


def _is_multi(value: Any) -> bool:
    return isinstance(value, list | tuple) and len(value) > 1


class LidarSimDataset(Dataset):
    """Simulated Boreas-style teach-and-repeat lidar localisation (see the module docstring).

    Args:
        seed: town, passes and offsets are all derived from it.
        split: ``"test"`` (passes ``test_passes``), ``"train"`` (``train_passes``, default all
            other repeat passes up to ``n_passes``) or ``"all"``.
        n_points: points per live scan (N).
        n_passes: number of repeat passes (numbered 1..n_passes; pass 0 is the teach pass).
        test_passes / train_passes: the passes of each split (must be disjoint).
        route_scale: scales the route (1.0: about 2.8 km); small values make small towns (tests).
        sample_spacing_m: distance between teach vertices = samples per pass along the route.
        teach_spacing_m: distance between teach scans.
        submap_window_m: teach scans within this arc length of the vertex form its submap.
        submap_radius_m: horizontal crop radius of the submap around the vertex.
        map_voxel_m: voxel size of the submap (metres).
        scan_voxel_m: the live scan keeps one return per voxel of this size (shrunk if needed to
            keep at least ``n_points`` voxels) before the random draw of ``n_points`` (0: a
            uniform draw over all returns); see :func:`~icpbench.datasets.submaps.spatial_subsample`.
        town_seed: None (the original town) or the seed of another town; a list gives a mix of
            towns (see the module docstring).
        sensor: lidar preset (:data:`~icpbench.datasets.sensors.SENSORS`); a list gives a mix.
        lidar: :class:`LidarConfig` (replaces the preset) or a dict of overrides of the preset's
            fields (beams, field of view, range, noise, mount height, dropout, ring offsets).
        lateral_offset_m: maximum lateral offset of the repeat passes from the teach line.
        car_change: share of parking spaces re-drawn in each pass (teach included): the other
            spaces keep their usual car (or stay empty).
        truck_prob: probability that a truck passes in the next lane in a live scan.
        weather_rate: probability per ray of a spurious weather return in live scans (0: clear).
        offset_trans_m, offset_rot_deg: range of the random initial offset (paper: 0.3, 10).
        order: ``"shuffled"`` (seeded permutation) or ``"route"``.
        cache_dir: cache root (default :func:`~icpbench.datasets.base.default_cache_dir`).
        threads: threads for ray casting.
    """

    name: ClassVar[str] = "lidar-sim"
    param_ranges: ClassVar[dict[str, Range]] = {
        "n_points": Range(6, 10_000_000), "n_passes": Range(1, 1000), "test_passes": Range(0, 999),
        "route_scale": Range(0.0, 100.0, lo_open=True),
        "sample_spacing_m": Range(0.0, lo_open=True), "teach_spacing_m": Range(0.0, lo_open=True),
        "submap_window_m": Range(0.0), "submap_radius_m": Range(0.0, lo_open=True),
        "map_voxel_m": Range(0.0, lo_open=True), "scan_voxel_m": Range(0.0),
        "town_seed": Range(0, 2**63 - 1), "lateral_offset_m": Range(0.0, 100.0),
        "car_change": Range(0.0, 1.0), "truck_prob": Range(0.0, 1.0), "weather_rate": Range(0.0, 1.0),
        "offset_trans_m": Range(0.0, 100.0), "offset_rot_deg": Range(0.0, 180.0),
        "threads": Range(1, 1024)}
    description: ClassVar[str] = ("Simulated lidar town (teach and repeat, ~2.8 km loop: dense streets, "
                                  "open lots and fields, highway, underpass)")
    icp_preset: ClassVar[str] = "lidar"
    default_budgets: ClassVar[tuple[float, ...]] = (1.0, 2.0, 3.0, 4.0, 5.0)

    @classmethod
    def create(cls, **settings: Any) -> Dataset:
        """Several town seeds or sensors give a :class:`~icpbench.datasets.lidar_mix.LidarSimMix`
        of single-town datasets (same name, same other parameters); one of each, this class."""
        if _is_multi(settings.get("town_seed")) or _is_multi(settings.get("sensor")):
            from icpbench.datasets.lidar_mix import LidarSimMix

            return LidarSimMix(**settings)
        return cls(**settings)

    def __init__(self, *, seed: int = 0, split: Split = "test", n_points: int = 10_000,
                 n_passes: int = 6, test_passes: Sequence[int] = (1, 2),
                 train_passes: Sequence[int] | None = None, route_scale: float = 1.0,
                 sample_spacing_m: float = 15.0, teach_spacing_m: float = 5.0,
                 submap_window_m: float = 20.0, submap_radius_m: float = 45.0,
                 map_voxel_m: float = 0.25, scan_voxel_m: float = 0.3,
                 town_seed: int | Sequence[int] | None = None,
                 sensor: str | Sequence[str] = DEFAULT_SENSOR,
                 lidar: LidarConfig | dict | None = None, lateral_offset_m: float = 0.5,
                 car_change: float = 0.5, truck_prob: float = 0.2, weather_rate: float = 0.0,
                 offset_trans_m: float = 0.3, offset_rot_deg: float = 10.0,
                 order: Literal["shuffled", "route"] = "shuffled", cache_dir: str | Path | None = None,
                 threads: int = 1) -> None:
        if _is_multi(town_seed) or _is_multi(sensor):
            raise InputError("several town seeds or sensors make a mix: build it with "
                             "LidarSimDataset.create(...) (the runner does)")
        town_seed, sensor = _single(town_seed), _single(sensor)
        if town_seed is not None:
            if isinstance(town_seed, bool) or not isinstance(town_seed, int | np.integer):
                raise InputError(f"town_seed must be an integer or a list of integers, got {town_seed!r}")
            town_seed = int(town_seed)
        if not isinstance(sensor, str):
            raise InputError(f"sensor must be a preset name or a list of names, got {sensor!r}")
        lidar_cfg = sensor_config(sensor, lidar)
        self.style = town_style(town_seed)
        test_p = tuple(sorted({int(p) for p in test_passes}))
        all_p = tuple(range(1, int(n_passes) + 1))
        train_p = (tuple(p for p in all_p if p not in test_p) if train_passes is None
                   else tuple(sorted({int(p) for p in train_passes})))
        if set(test_p) & set(train_p):
            raise InputError(f"train and test passes overlap: {sorted(set(test_p) & set(train_p))}; "
                             "a pass must be in one split only")
        if any(p < 1 for p in test_p + train_p):
            raise InputError("repeat passes are numbered from 1 (pass 0 is the teach pass)")
        if order not in ("shuffled", "route"):
            raise InputError(f"order must be 'shuffled' or 'route', got {order!r}")
        if n_points < 6:
            raise InputError(f"n_points must be >= 6, got {n_points}")
        if not (0 < teach_spacing_m <= submap_window_m):
            raise InputError("need 0 < teach_spacing_m <= submap_window_m")
        if not (sample_spacing_m > 0 and map_voxel_m > 0 and submap_radius_m > 0):
            raise InputError("sample_spacing_m, map_voxel_m and submap_radius_m must be positive")
        if not (0 <= truck_prob <= 1 and 0 <= car_change <= 1 and 0 <= weather_rate < 1
                and lateral_offset_m >= 0):
            raise InputError("need truck_prob and car_change in [0, 1], weather_rate in [0, 1) and "
                             "lateral_offset_m >= 0")
        # Parameters that change the generated data (cache key); the split, order and offsets do not.
        self._gen = {
            "seed": int(seed), "n_points": int(n_points), "route_scale": float(route_scale),
            "sample_spacing_m": float(sample_spacing_m), "teach_spacing_m": float(teach_spacing_m),
            "submap_window_m": float(submap_window_m), "submap_radius_m": float(submap_radius_m),
            "map_voxel_m": float(map_voxel_m), "scan_voxel_m": float(scan_voxel_m),
            "lidar": lidar_cfg.to_dict(),
            "lateral_offset_m": float(lateral_offset_m), "car_change": float(car_change),
            "truck_prob": float(truck_prob),
            "weather_rate": float(weather_rate),
        }
        # only when set, so that the original town and sensor keep their cache key and records
        if town_seed is not None:
            self._gen["town_seed"] = town_seed
        if sensor != DEFAULT_SENSOR:
            self._gen["sensor"] = sensor
        gen_rest = {k: v for k, v in self._gen.items() if k != "seed"}
        super().__init__(seed=seed, split=split, **gen_rest, n_passes=int(n_passes),
                         test_passes=list(test_p), train_passes=list(train_p),
                         offset_trans_m=float(offset_trans_m), offset_rot_deg=float(offset_rot_deg),
                         order=order)
        self.lidar = lidar_cfg
        self.n_points = int(n_points)
        self.sample_spacing_m = float(sample_spacing_m)
        self.teach_spacing_m = float(teach_spacing_m)
        self.offset = (float(offset_trans_m), float(offset_rot_deg))
        self.threads = int(threads)
        self.town_seed, self.sensor = town_seed, sensor
        # random streams: the original town keeps its keys (seed, ...); other towns get their own
        self._keys: tuple[int, ...] = (self.seed,) if town_seed is None else (self.seed, 7_000_003,
                                                                               town_seed)
        tag = ([f"town{town_seed}"] if town_seed is not None else []) \
            + ([sensor] if sensor != DEFAULT_SENSOR else [])
        self._prefix = "/".join(["lidar-sim", *tag])  # sample ids: lidar-sim[/townN][/sensor]/...
        if town_seed is None:
            self.route: Route = make_route(self.seed, scale=float(route_scale))
        else:
            self.route = make_route(town_seed, scale=float(route_scale), corners=self.style.corners,
                                    layout=self.style.layout)
        self.ground = make_ground(self.route, self.style)
        self.n_vertices = int(self.route.length // self.sample_spacing_m)
        self.n_teach = int(self.route.length // self.teach_spacing_m)
        if self.n_vertices < 1:
            raise InputError("the route is shorter than one sample spacing; increase route_scale")
        self.cache_root = (Path(cache_dir) if cache_dir is not None else default_cache_dir()) \
            / "lidar-sim" / sm.params_hash(self._gen, FORMAT_VERSION)
        passes = {"test": test_p, "train": train_p, "all": tuple(sorted(set(test_p + train_p)))}[split]
        index = [(p, f) for p in passes for f in range(self.n_vertices)]
        if order == "shuffled":
            perm = sm.sample_rng(*self._keys, 0, _ORDER, len(passes), *passes).permutation(len(index))
            index = [index[i] for i in perm]
        self._index = index
        self._town: Town | None = None
        self._static = None
        self._car_scenes = sm.LRU(3)
        self._teach_scans = sm.LRU(24)

    # -- Dataset API -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, i: int) -> Sample:
        if not -len(self) <= i < len(self):
            raise IndexError(f"sample index {i} out of range for {len(self)} samples")
        p, f = self._index[i]
        return self.sample(p, f)

    def sample_id(self, i: int) -> str:
        """The id of sample ``i`` without generating it."""
        p, f = self._index[i]
        return f"{self._prefix}/pass{p}/{f:06d}"

    def sample(self, pass_id: int, frame: int) -> Sample:
        """The sample of repeat pass ``pass_id`` at teach vertex ``frame`` (any pass, any split)."""
        if pass_id < 1 or not 0 <= frame < self.n_vertices:
            raise InputError(f"need a repeat pass >= 1 and 0 <= frame < {self.n_vertices}; "
                             f"got pass {pass_id}, frame {frame}")
        live = self._live(pass_id, frame)
        sub = self._submap(frame)
        T_live_vertex = sm.inv(live["T_town_live"]) @ sub["T_town_vertex"]
        map_pts = sm.transform(T_live_vertex, sub["points"])
        map_n = sm.rotate(T_live_vertex, sub["normals"].astype(np.float64))
        map_n /= np.linalg.norm(map_n, axis=1, keepdims=True)  # stored as float16
        place = str(live["place"])
        x, y = (float(v) for v in live["T_town_live"][:2, 3])
        meta = {"x": x, "y": y, "stretch": PLACES[place], "place": place, "pass": int(pass_id),
                "frame": int(frame), "s_m": float(live["s"]), "lateral_m": float(live["d"]),
                "truck": bool(live["truck"]), "n_returns": int(live["n_returns"])}
        if self.town_seed is not None:
            meta.update(town=self.town_seed, movers=int(live["movers"]))
        if self.sensor != DEFAULT_SENSOR:
            meta["sensor"] = self.sensor
        rng = sm.sample_rng(*self._keys, pass_id, _OFFSET, frame)
        return sm.make_sample(f"{self._prefix}/pass{pass_id}/{frame:06d}", live["scan"], map_pts, map_n,
                              rng, meta, *self.offset)

    def prepare(self, progress: bool | None = None) -> None:
        """Generate (or check the cache of) every sample of the split, with a progress bar
        (``progress=None``: only on a terminal)."""
        from tqdm import tqdm

        for p, f in tqdm(sorted(self._index), desc=f"lidar-sim {self.split}",
                         disable=None if progress is None else not progress):
            self._submap(f)
            self._live(p, f)

    # -- world -----------------------------------------------------------------------------------
    @property
    def town(self) -> Town:
        """The town meshes (built on first use; cached samples do not need them)."""
        if self._town is None:
            seed = self.seed if self.town_seed is None else self.town_seed
            key = (seed, self.town_seed is None, self._gen["route_scale"])
            self._town = _TOWNS.get(key, lambda: make_town(seed, route=self.route, style=self.style))
        return self._town

    def _static_scene(self):
        if self._static is None:
            self._static = make_scene(self.town.vertices, self.town.triangles, self.threads)
        return self._static

    def _cars_scene(self, pass_id: int):
        """Ray-casting scene of the parked cars of a pass (0: teach)."""
        def build():
            V, F = self.town.cars_mesh(sm.sample_rng(*self._keys, pass_id, _CARS),
                                       self._gen["car_change"])
            return make_scene(V, F, self.threads)

        return self._car_scenes.get(pass_id, build)

    def sensor_pose(self, s: float, d: float = 0.0, dyaw: float = 0.0) -> np.ndarray:
        """T_town_sensor (4, 4) of the lidar at route coordinates (s, d) with heading error dyaw
        (on a sloping or cambered road the vehicle pitches and rolls with it)."""
        xy, h = self.route.pose(s, d)
        if self.ground.flat:
            return sm.pose_2d(float(xy[0]), float(xy[1]), float(h) + dyaw, self.lidar.mount_height_m)
        return self.ground.vehicle_pose(xy, float(h) + dyaw, self.lidar.mount_height_m)

    # -- teach pass and submaps ------------------------------------------------------------------
    def _teach_scan(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Teach scan j (at s = j * teach_spacing_m): points and normals in the town frame."""
        def build() -> tuple[np.ndarray, np.ndarray]:
            T = self.sensor_pose(j * self.teach_spacing_m)
            scan = cast_scan([self._static_scene(), self._cars_scene(0)], T, self.lidar,
                             sm.sample_rng(*self._keys, 0, _TEACH, j), threads=self.threads)
            return sm.transform(T, scan.points), sm.rotate(T, scan.normals)

        return self._teach_scans.get(j, build)

    def _submap(self, v: int) -> dict[str, np.ndarray]:
        """Submap of teach vertex v: points (int16 at 2 mm) and normals (float16) in the vertex
        frame, and T_town_vertex; loaded from the cache or generated."""
        path = self.cache_root / "submaps" / f"v{v:05d}.npz"
        rec = sm.load_npz(path)
        if rec is None:
            rec = self._make_submap(v)
            sm.write_params(self.cache_root, {**self._gen, "format_version": FORMAT_VERSION})
            sm.atomic_savez(path, **rec)
        pts = rec["points_mm2"].astype(np.float64) * 0.002
        return {"points": pts, "normals": rec["normals"], "T_town_vertex": rec["T_town_vertex"]}

    def _make_submap(self, v: int) -> dict[str, np.ndarray]:
        s_v = v * self.sample_spacing_m
        T_tv = self.sensor_pose(s_v)
        s_teach = np.arange(self.n_teach) * self.teach_spacing_m
        js = sm.window_indices(s_teach, s_v, self._gen["submap_window_m"], self.route.length)
        clouds = [self._teach_scan(int(j)) for j in js]
        pts, nrm = sm.build_submap(clouds, self._gen["map_voxel_m"], T_tv[:3, 3],
                                   self._gen["submap_radius_m"])
        T_vt = sm.inv(T_tv)
        pts_v, nrm_v = sm.transform(T_vt, pts), sm.rotate(T_vt, nrm)
        q = np.round(pts_v / 0.002)
        if np.abs(q).max() >= 32767:
            raise InputError("submap radius too large for the 2 mm int16 storage (max 65 m)")
        return {"points_mm2": q.astype(np.int16), "normals": nrm_v.astype(np.float16),
                "T_town_vertex": T_tv}

    # -- repeat passes ---------------------------------------------------------------------------
    def _live(self, p: int, f: int) -> dict[str, Any]:
        path = self.cache_root / f"pass{p:02d}" / f"f{f:05d}.npz"
        rec = sm.load_npz(path)
        if rec is None:
            rec = self._make_live(p, f)
            sm.write_params(self.cache_root, {**self._gen, "format_version": FORMAT_VERSION})
            sm.atomic_savez(path, **rec)
        return rec

    def live_pose(self, p: int, f: int) -> tuple[float, float, float, bool, float]:
        """(s, d, dyaw, truck, truck_ds) of repeat pass p at vertex f: arc length (m), lateral
        offset (m), heading error (rad), whether a truck passes, its longitudinal offset (m)."""
        if p < 1:
            raise InputError("live scans come from repeat passes >= 1")
        prng = sm.sample_rng(*self._keys, p, _PASS)
        lat_max = self._gen["lateral_offset_m"]
        base = prng.uniform(-0.6, 0.6) * lat_max
        rng = sm.sample_rng(*self._keys, p, _LIVE_POSE, f)
        s = f * self.sample_spacing_m + rng.uniform(-0.25, 0.25) * self.sample_spacing_m
        d = float(np.clip(base + rng.normal(0, 0.3) * lat_max, -lat_max, lat_max))
        dyaw = float(np.deg2rad(np.clip(rng.normal(0, 1.0), -2.5, 2.5)))
        truck = bool(rng.random() < self._gen["truck_prob"])
        return float(s) % self.route.length, d, dyaw, truck, float(rng.uniform(-30, 30))

    def _make_live(self, p: int, f: int) -> dict[str, Any]:
        s, d, dyaw, truck, truck_ds = self.live_pose(p, f)
        T = self.sensor_pose(s, d, dyaw)
        scenes = [self._static_scene(), self._cars_scene(p)]
        if truck:
            scenes.append(make_scene(*self.town.truck_mesh(s + truck_ds, 3.5), self.threads))
        n_movers = 0
        if self.style.movers_per_scan > 0:  # road users of this pass only: never in the map
            mrng = sm.sample_rng(*self._keys, p, _MOVERS, f)
            n_movers = int(mrng.poisson(self.style.movers_per_scan))
            scenes.append(make_scene(*self.town.movers_mesh(mrng, s, n_movers), self.threads))
        scan = cast_scan(scenes, T, self.lidar, sm.sample_rng(*self._keys, p, _LIVE_SCAN, f),
                         weather_rate=self._gen["weather_rate"], threads=self.threads)
        idx = sm.spatial_subsample(scan.points, self.n_points, self._gen["scan_voxel_m"],
                                   sm.sample_rng(*self._keys, p, _SUBSAMPLE, f))
        rec = {"scan": scan.points[idx].astype(np.float32), "T_town_live": T,
               "place": np.array(str(self.route.place_at(s))), "s": np.array(s), "d": np.array(d),
               "truck": np.array(truck), "n_returns": np.array(len(scan.points))}
        if self.town_seed is not None:
            rec["movers"] = np.array(n_movers)
        return rec
