"""The simulated lidar town (``lidar-sim``): town geometry, lidar model, submaps, samples, cache,
splits, clean localisation with p2plane, and the dataset pictures.

A small town (route scale 0.25, ~0.7 km, a sample every 40 m, a coarser lidar) keeps the file fast.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from icpbench.core.errors import InputError
from icpbench.datasets import submaps as sm
from icpbench.datasets.lidar_model import LidarConfig, cast_scan, make_scene
from icpbench.datasets.lidar_sim import LidarSimDataset
from icpbench.datasets.town import PLACES, STRETCH_TYPES, make_route, make_town

torch.set_num_threads(1)

SMALL = {"route_scale": 0.25, "sample_spacing_m": 40.0, "n_passes": 3, "test_passes": (1,),
         "lidar": {"h_res_deg": 0.4}}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("lidar-sim-cache")


@pytest.fixture(scope="module")
def ds(cache):
    return LidarSimDataset(cache_dir=cache, **SMALL)


# -- town -------------------------------------------------------------------------------------
def test_default_route_is_a_few_km_with_every_stretch_type():
    route = make_route(0)
    assert 2000 < route.length < 4000
    stretches = {PLACES[p] for _, _, p in route.intervals()}
    assert stretches == set(STRETCH_TYPES)
    # closed loop: the centre line returns to its start smoothly
    assert np.linalg.norm(route.xy[0] - route.xy[-1]) < 1.0
    # projecting a point offset laterally recovers (s, d)
    xy, _ = route.pose(np.array([123.0, 1500.0]), np.array([4.0, -7.0]))
    s, d = route.project(xy)
    assert np.allclose(s, [123.0, 1500.0], atol=0.1) and np.allclose(d, [4.0, -7.0], atol=0.05)


def test_town_is_deterministic_and_keeps_the_lane_clear():
    town = make_town(3, scale=0.25)
    again = make_town(3, scale=0.25)
    other = make_town(4, scale=0.25)
    assert np.array_equal(town.vertices, again.vertices)
    assert town.vertices.shape != other.vertices.shape or not np.array_equal(town.vertices, other.vertices)
    # vertical rays from 4.5 m down onto the driven lane (and +-1.5 m) only meet the road surface
    scene = make_scene(town.vertices, town.triangles)
    s = np.arange(0, town.route.length, 2.0)
    rays = []
    for d in (-1.5, 0.0, 1.5):
        xy, _ = town.route.pose(s, d)
        rays.append(np.c_[xy, np.full(len(s), 4.5), np.zeros((len(s), 2)), -np.ones(len(s))])
    t = scene.cast_rays(o3d.core.Tensor(np.vstack(rays).astype(np.float32)))["t_hit"].numpy()
    assert np.all(t > 4.49), f"{np.sum(t <= 4.49)} lane points are covered by an object"
    # the dense stretches are much more built up than the open ones (vertical structure per metre)
    dense, open_ = _structure_per_metre(town, "dense"), _structure_per_metre(town, "open")
    assert dense > 2 * open_


def _structure_per_metre(town, stretch):
    """Triangle area of vertical-ish faces within 30 m of the route per metre of that stretch."""
    V, F = town.vertices.astype(np.float64), town.triangles
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cr = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    vertical = np.abs(cr[:, 2]) / np.maximum(2 * area, 1e-12) < 0.3
    s, d = town.route.project(((a + b + c) / 3)[:, :2])
    near = np.abs(d) < 30
    place = town.route.place_at(s)
    m = vertical & near & np.array([PLACES[p] == stretch for p in place])
    length = sum(b_ - a_ for a_, b_, p in town.route.intervals() if PLACES[p] == stretch)
    return area[m].sum() / length


# -- lidar model ------------------------------------------------------------------------------
def test_lidar_over_flat_ground_sees_the_plane_at_mount_height():
    ground = make_scene(np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0]]),
                        np.array([[0, 1, 2], [0, 2, 3]]))
    cfg = LidarConfig(n_beams=16, vfov_deg=(-20.0, 10.0), h_res_deg=1.0, range_noise_m=0.0)
    T = sm.pose_2d(10.0, -3.0, 0.7, z=cfg.mount_height_m)
    scan = cast_scan([ground], T, cfg, np.random.default_rng(0))
    # beams below the horizon hit the ground within range, the others see the sky
    el = np.degrees(np.arcsin(scan.points[:, 2] / np.linalg.norm(scan.points, axis=1)))
    expected = sum(1 for e in np.linspace(-20, 10, 16)
                   if e < 0 and cfg.min_range_m <= cfg.mount_height_m / np.sin(-np.radians(e))
                   <= cfg.max_range_m) * 360
    assert len(scan.points) == expected > 0
    assert np.allclose(scan.points[:, 2], -cfg.mount_height_m, atol=1e-4)
    assert np.allclose(scan.normals, [0, 0, 1], atol=1e-6)
    assert np.all(el < 0)
    # range noise is Gaussian with the configured sigma
    noisy = cast_scan([ground], T, LidarConfig(n_beams=16, vfov_deg=(-20.0, 10.0), h_res_deg=1.0,
                                               range_noise_m=0.05), np.random.default_rng(1))
    r_true = cfg.mount_height_m / (-noisy.points[:, 2] / np.linalg.norm(noisy.points, axis=1))
    resid = np.linalg.norm(noisy.points, axis=1) - r_true
    assert 0.045 < np.std(resid) < 0.055
    # weather: spurious near returns, marked with source -1
    wet = cast_scan([ground], T, cfg, np.random.default_rng(2), weather_rate=0.2)
    frac = np.mean(wet.source == -1)
    assert 0.1 < frac < 0.4
    assert np.all(np.linalg.norm(wet.points[wet.source == -1], axis=1) <= 25.0 + 1e-6)


def test_voxel_downsample_keeps_two_sided_normals_and_centroids():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [1.1, 0.1, 0.1]])
    nrm = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]])
    p, n = sm.voxel_downsample(pts, 0.5, nrm)
    order = np.argsort(p[:, 0])
    assert np.allclose(p[order], [[0.15, 0.15, 0.15], [1.1, 0.1, 0.1]])
    assert np.allclose(np.abs(n[order]), [[1, 0, 0], [0, 0, 1]])


def test_spatial_subsample_spreads_points():
    rng = np.random.default_rng(0)
    near = rng.normal(0, 0.5, (9000, 3))  # a dense blob near the sensor
    far = rng.uniform(-30, 30, (3000, 3))
    pts = np.vstack([near, far])
    idx = sm.spatial_subsample(pts, 2000, 0.5, np.random.default_rng(1))
    assert len(idx) == 2000 and len(np.unique(idx)) == 2000
    assert np.mean(idx < 9000) < 0.2  # a uniform draw would take 75 % from the blob


# -- samples ----------------------------------------------------------------------------------
def test_samples_follow_the_protocol(ds):
    assert len(ds) == ds.n_vertices and ds.n_vertices >= 12
    s = ds[0]
    s.validate()
    assert s.scan.shape == (10_000, 3) and s.scan.dtype == np.float32
    assert s.id.startswith("lidar-sim/pass1/")
    assert {"x", "y", "stretch", "pass", "frame", "place"} <= set(s.meta)
    assert s.meta["stretch"] in STRETCH_TYPES and s.meta["pass"] == 1
    assert np.array_equal(s.T_init, np.eye(4))
    # T_gt is the inverse of the paper's offset: |t| <= 0.3 per axis, angles <= 10 deg
    off = np.linalg.inv(s.T_gt)
    assert np.all(np.abs(off[:3, 3]) <= 0.3 + 1e-9)
    assert np.all(np.abs(Rotation.from_matrix(off[:3, :3]).as_euler("xyz", degrees=True)) <= 10 + 1e-6)
    # the scan moved by T_gt lies on the submap: point-to-plane residuals of a few cm
    q = sm.transform(s.T_gt, s.scan)
    d, i = cKDTree(s.map).query(q)
    r = np.abs(((q - s.map[i]) * s.map_normals[i]).sum(1))
    assert np.median(d) < 0.2 and np.median(r[d < 1.0]) < 0.03
    # ... and not at the initial guess (the offset is real)
    d0, _ = cKDTree(s.map).query(s.scan.astype(np.float64))
    assert np.median(d0) > np.median(d)


def test_map_is_in_the_true_vehicle_frame(ds):
    """x points along the route (longitudinal), the ground is at -mount height, origin = lidar."""
    for i in range(3):
        s = ds[i]
        p, f = s.meta["pass"], s.meta["frame"]
        s_m, d, dyaw, _, _ = ds.live_pose(p, f)
        ahead, _ = ds.route.pose(s_m + 10.0, d)
        T = ds.sensor_pose(s_m, d, dyaw)
        assert np.allclose(T[:2, 3], [s.meta["x"], s.meta["y"]])
        local = sm.transform(sm.inv(T), np.r_[ahead, ds.lidar.mount_height_m][None])[0]
        assert local[0] > 9.0 and abs(local[1]) < 1.0
        ground = s.map[np.abs(s.map_normals[:, 2]) > 0.99]
        assert abs(np.median(ground[:, 2]) + ds.lidar.mount_height_m) < 0.05


def test_deterministic_and_cached(ds, cache):
    a = ds[1]
    files = sorted(p.relative_to(cache) for p in cache.rglob("*.npz"))
    assert any("submaps" in str(f) for f in files) and any("pass01" in str(f) for f in files)
    assert not list(cache.rglob("*.tmp"))  # atomic writes leave no temporary files
    fresh = LidarSimDataset(cache_dir=cache, **SMALL)
    b = fresh[1]
    assert fresh._town is None  # loaded from the cache: the town was never built
    assert np.array_equal(a.scan, b.scan) and np.array_equal(a.map, b.map)
    assert np.array_equal(a.T_gt, b.T_gt) and a.meta == b.meta
    # other parameters -> another cache folder; another seed -> another town
    other = LidarSimDataset(cache_dir=cache, **{**SMALL, "n_points": 5000})
    assert other.cache_root != ds.cache_root
    assert LidarSimDataset(cache_dir=cache, seed=1, **SMALL).route.length != ds.route.length


def test_splits_are_disjoint_passes(cache):
    test = LidarSimDataset(cache_dir=cache, split="test", **SMALL)
    train = LidarSimDataset(cache_dir=cache, split="train", **SMALL)
    both = LidarSimDataset(cache_dir=cache, split="all", **SMALL)
    assert {p for p, _ in test._index} == {1} and {p for p, _ in train._index} == {2, 3}
    assert len(both) == len(test) + len(train)
    with pytest.raises(InputError, match="overlap"):
        LidarSimDataset(cache_dir=cache, **{**SMALL, "train_passes": (1, 2)})
    with pytest.raises(InputError):
        LidarSimDataset(cache_dir=cache, lidar={"n_beams": 0})
    with pytest.raises(InputError, match="unknown lidar"):
        LidarSimDataset(cache_dir=cache, lidar={"beams": 32})


def test_repeat_passes_differ_from_the_teach_pass(ds):
    """Lateral offsets within the lane, re-parked cars, sometimes a truck."""
    poses = [ds.live_pose(p, f) for p in (1, 2, 3) for f in range(ds.n_vertices)]
    lat = np.array([d for _, d, _, _, _ in poses])
    assert np.all(np.abs(lat) <= 0.5 + 1e-9) and np.std(lat) > 0.05
    assert any(t for *_, t, _ in poses)
    car_meshes = [ds.town.cars_mesh(sm.sample_rng(ds.seed, p, 0), 0.5)[0] for p in (0, 1)]
    assert len(car_meshes[0]) != len(car_meshes[1]) or not np.allclose(*car_meshes)


def test_clean_localisation_with_p2plane(ds):
    """Paper settings (c = 1 m, d_max = 5 m, 100 iterations): 8 test samples converge with
    centimetre errors."""
    from icpbench.core.se3 import pose_error_components
    from icpbench.core.types import Batch
    from icpbench.targets.p2plane import PointToPlaneICP

    batch = Batch.from_samples(ds.take(8))
    reg = PointToPlaneICP("lidar").register(batch.scans, batch.maps, batch.T_init)
    err = pose_error_components(reg.T, batch.T_gt)
    assert int(reg.converged.sum()) >= 7
    assert float(err["trans_err"].median()) < 0.05
    assert float(err["trans_err_xy"].median()) < 0.03


def test_show_dataset_writes_both_pictures(ds, tmp_path):
    from icpbench.analysis.dataset_figures import show_dataset

    paths = show_dataset(ds, tmp_path)
    assert [p.name for p in paths] == ["lidar-sim_route.png", "lidar-sim_scan_on_submap.png"]
    for p in paths:
        assert p.stat().st_size > 20_000
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_uniform_attack_shifts_the_estimate_by_lambda(ds):
    """The uniform baseline translates the whole scan by 1 m: ICP follows it (mean error within
    10 % of 1 m), so the dataset has no hidden bias in x-y."""
    from icpbench.attacks.uniform import UniformTranslationAttack
    from icpbench.core.se3 import pose_error_components
    from icpbench.core.types import Batch
    from icpbench.targets.p2plane import PointToPlaneICP

    batch = Batch.from_samples(ds.take(8))
    adv = UniformTranslationAttack().run(batch, 1.0, generator=0).scans
    reg = PointToPlaneICP("lidar").register(adv, batch.maps, batch.T_init)
    err = pose_error_components(reg.T, batch.T_gt)["trans_err_xy"][reg.converged]
    assert len(err) >= 7 and abs(float(err.mean()) - 1.0) < 0.1
