"""lidar-sim variety: the original town is unchanged, other towns (``town_seed``), clutter, sloping
and cambered ground, moving road users, sensor presets, mixes of towns and sensors, pictures.

New towns are built at route scale 0.3 (about 0.5 km) to keep the file fast.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.datasets import clutter
from icpbench.datasets import submaps as sm
from icpbench.datasets.ground import Ground
from icpbench.datasets.lidar_mix import LidarSimMix
from icpbench.datasets.lidar_model import LidarConfig, cast_scan, make_scene
from icpbench.datasets.lidar_sim import LidarSimDataset
from icpbench.datasets.sensors import SENSORS, sensor_config
from icpbench.datasets.town import PLACES, MeshBuilder, make_town
from icpbench.datasets.town_style import LEGACY, random_style

torch.set_num_threads(1)

SMALL = {"route_scale": 0.3, "sample_spacing_m": 40.0, "n_passes": 3, "test_passes": (1,),
         "lidar": {"h_res_deg": 0.4}}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("towns-cache")


# -- the original town is unchanged -----------------------------------------------------------
def test_default_dataset_is_unchanged(tmp_path):
    """Sample ids, cache key, recorded parameters, town meshes and scans of the default dataset
    are those of the code before town seeds and sensors existed (reference numbers computed on
    it), so committed results stay valid. Scans are compared by statistics of the full sweeps
    (count, mean, spread): a change of geometry, lidar or random streams moves them by
    centimetres to metres, while the last-bit differences of ray casting between CPUs do not."""
    ds = LidarSimDataset(cache_dir=tmp_path)
    train = LidarSimDataset(cache_dir=tmp_path, split="train")
    assert ds.cache_root.name == "141479ebffa72f62"
    assert (len(ds), len(train)) == (372, 744)
    assert ds._index[:6] == [(1, 168), (1, 115), (1, 73), (1, 126), (1, 54), (1, 37)]
    assert train._index[:4] == [(3, 62), (3, 129), (3, 157), (3, 164)]
    assert "town_seed" not in ds.describe() and "sensor" not in ds.describe()
    assert ds.describe()["lidar"] == {"n_beams": 32, "vfov_deg": [-25.0, 15.0], "h_res_deg": 0.2,
                                      "min_range_m": 2.0, "max_range_m": 100.0,
                                      "range_noise_m": 0.02, "dropout": 0.0, "mount_height_m": 1.9}
    assert np.isclose(ds.route.length, 2804.4673788094815, rtol=1e-12)
    town = ds.town
    assert town.vertices.shape == (46915, 3) and town.triangles.shape == (87114, 3)
    assert np.isclose(town.vertices.astype(np.float64).sum(), 38272878.453516535, rtol=1e-9)
    assert len(town.car_slots) == 408 and np.isclose(town.base_cars.sum(), 3842.2488358244923)
    pts, _ = ds._teach_scan(7)
    _close_stats(pts, 45603, [16.144547060133164, -5.78659637237606, 1.078332596131215],
                 [12.796582667681168, 12.837561553140112, 1.6976831390714513])
    for (p, f), pose, n, mean, std in (
            ((1, 0), (2.614875324665795, -0.18891573884500273, 0.03485648341903421), 46017,
             [-0.34942086969117364, 0.6822293065945346, -0.8106121392298968],
             [14.628497844943187, 11.474085539224445, 1.785533548968793]),
            ((2, 57), (857.716545687529, -0.14345342679240913, -0.024197172130765852), 45555,
             [1.0662026557822073, 0.6436636285811898, -0.7044916261485769],
             [13.885814218325761, 9.372506498899261, 1.5021854778079913])):
        s, d, dyaw, truck, _ = ds.live_pose(p, f)
        assert np.allclose([s, d, dyaw], pose, rtol=1e-12, atol=1e-12) and not truck
        scan = cast_scan([ds._static_scene(), ds._cars_scene(p)], ds.sensor_pose(s, d, dyaw),
                         ds.lidar, sm.sample_rng(ds.seed, p, 2, f))
        _close_stats(scan.points, n, mean, std)
    sample = ds.sample(1, 0)
    assert sample.id == "lidar-sim/pass1/000000" and "town" not in sample.meta


def _close_stats(pts: np.ndarray, n: int, mean: list[float], std: list[float]) -> None:
    assert abs(len(pts) - n) <= 5
    assert np.allclose(pts.mean(0), mean, atol=2e-3) and np.allclose(pts.std(0), std, atol=2e-3)


# -- other towns ------------------------------------------------------------------------------
def test_town_seeds_vary_layout_sizes_and_densities():
    a, b = random_style(1), random_style(2)
    assert random_style(1) == a and a != b and not a.legacy and a.clutter
    for st in (a, b):
        places = [p for _, p in st.layout]
        assert set(places) == set(PLACES)  # every place, in a town-specific order
        assert all(x != y for x, y in zip(places, places[1:] + places[:1], strict=True))
        fr = [f for f, _ in st.layout]
        assert fr[0] == 0 and all(y - x >= 0.02 for x, y in zip(fr, fr[1:], strict=False))
        assert st.road["field"][0] <= -2.2 and st.road["field"][1] >= 5.0  # room for both lanes
        assert 0.01 <= st.camber <= 0.025 and st.grade_waves
    assert [p for _, p in a.layout] != [p for _, p in b.layout] or a.corners != b.corners
    assert a.road != b.road and a.setback_m != b.setback_m and a.lot_occupancy != b.lot_occupancy
    with pytest.raises(InputError, match="town_seed"):
        random_style(-1)


def test_new_town_ground_slopes_and_camber_and_the_lane_stays_clear():
    style = random_style(4)
    town = make_town(4, style=style, scale=0.3)
    assert make_town(4, style=style, scale=0.3).vertices.tobytes() == town.vertices.tobytes()
    ground = town.terrain.ground
    s = np.arange(0, town.route.length, 2.0)
    z = ground.height_sd(s, 0.0)
    assert np.ptp(z) > 0.5  # the road climbs and descends
    slope = np.abs(np.diff(z)) / 2.0
    assert slope.max() < 0.08  # at most a few percent
    # camber: the crown (lane line at d = 1.75 m) is higher than the lane centre by c * 1.75
    camber_only = Ground(town.route, (), style.camber)
    crown, lane = camber_only.height_sd(s, 1.75), camber_only.height_sd(s, 0.0)
    assert np.allclose(crown - lane, style.camber * 1.75, atol=2e-3)
    assert np.all(camber_only.height_sd(s, 12.0) < crown - 0.05)  # it falls to both sides
    # the mesh follows the ground: vertical rays onto the driven lane hit the road surface, not
    # an object, within a few cm of the analytic height
    scene = make_scene(town.vertices, town.triangles)
    xy, _ = town.route.pose(s, 0.0)
    rays = np.c_[xy, z + 4.5, np.zeros((len(s), 2)), -np.ones(len(s))].astype(np.float32)
    import open3d as o3d

    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # (below bridges and gantries)
    assert np.all(np.abs(4.5 - t) < 0.05), "the lane is covered or the road is off"


def test_clutter_is_irregular_and_adds_objects():
    style = random_style(4)
    with_clutter = make_town(4, style=style, scale=0.3)
    without = make_town(4, style=dataclasses.replace(style, clutter=False), scale=0.3)
    assert len(with_clutter.triangles) > len(without.triangles) + 5000
    # a bush is not a plane nor an ellipsoid: its radius varies over its surface
    mb = MeshBuilder()
    clutter.blob(mb, np.zeros(3), (1.0, 1.0, 1.0), np.random.default_rng(0), roughness=0.35)
    V, _ = mb.arrays()
    r = np.linalg.norm(V, axis=1)
    assert r.std() > 0.05 and r.max() - r.min() > 0.3
    # the same seed gives the same clutter, another seed another one
    mb2 = MeshBuilder()
    clutter.blob(mb2, np.zeros(3), (1.0, 1.0, 1.0), np.random.default_rng(1), roughness=0.35)
    assert not np.allclose(mb2.arrays()[0], V)


@pytest.fixture(scope="module")
def town_ds(cache):
    return LidarSimDataset(cache_dir=cache, town_seed=4, **SMALL)


def test_moving_road_users_are_in_repeat_passes_only(town_ds):
    ds = town_ds
    movers = [int(ds._live(1, f)["movers"]) for f in range(min(6, ds.n_vertices))]
    assert sum(movers) > 0 and ds.sample(1, 0).meta["movers"] == movers[0]
    V, F = ds.town.movers_mesh(np.random.default_rng(0), 100.0, 5)
    assert len(F) > 0
    centre, _ = ds.route.pose(100.0)
    assert np.linalg.norm(V[:, :2] - centre, axis=1).max() < 55.0
    # a live scan sees them; the teach pass (and so the map) does not: the static scene has no
    # geometry where they stand
    static = make_scene(ds.town.vertices, ds.town.triangles)
    import open3d as o3d

    q = o3d.core.Tensor(V.astype(np.float32))
    dist = static.compute_distance(q).numpy()
    assert np.median(dist) > 0.3


def test_new_town_samples_are_tagged_and_localise(town_ds):
    from icpbench.core.se3 import pose_error_components
    from icpbench.core.types import Batch
    from icpbench.targets.p2plane import PointToPlaneICP

    ds = town_ds
    assert ds.cache_root != LidarSimDataset(cache_dir=ds.cache_root.parent.parent, **SMALL).cache_root
    s = ds[0]
    assert s.id.startswith("lidar-sim/town4/pass1/") and s.meta["town"] == 4
    # on a slope the vehicle frame tilts: the map's ground lies at about -mount height under the
    # sensor, and the pose has pitch/roll of a few degrees at most
    ground = s.map[(np.abs(s.map_normals[:, 2]) > 0.97) & (np.linalg.norm(s.map[:, :2], axis=1) < 6)]
    assert abs(np.median(ground[:, 2]) + ds.lidar.mount_height_m) < 0.1
    batch = Batch.from_samples(ds.take(8))
    reg = PointToPlaneICP("lidar").register(batch.scans, batch.maps, batch.T_init)
    err = pose_error_components(reg.T, batch.T_gt)
    assert int(reg.converged.sum()) >= 7 and float(err["trans_err"].median()) < 0.05


# -- sensors ----------------------------------------------------------------------------------
def test_sensor_presets_follow_the_data_sheets():
    spec = {"vlp16": (16, -15.0, 15.0), "hdl32": (32, -30.67, 10.67), "hdl64": (64, -24.8, 2.0),
            "os128": (128, -22.5, 22.5), "sim32": (32, -25.0, 15.0)}
    for name, (n, lo, hi) in spec.items():
        el = SENSORS[name].elevations()
        assert len(el) == n and np.isclose(el.min(), lo) and np.isclose(el.max(), hi), name
    assert SENSORS["sim32"] == LidarConfig()
    gaps = -np.diff(SENSORS["hdl64"].elevations())
    assert np.allclose(gaps[:31], 1 / 3, atol=1e-3) and np.allclose(gaps[32:], 0.515, atol=0.01)
    assert np.allclose(np.diff(SENSORS["vlp16"].elevations()), 2.0)
    # overrides on top of a preset
    cfg = sensor_config("hdl64", {"mount_height_m": 2.1, "dropout": 0.1, "range_noise_m": 0.05})
    assert cfg.mount_height_m == 2.1 and cfg.n_beams == 64 and cfg.elevations_deg
    assert sensor_config("hdl64", {"n_beams": 16}).elevations()[1] != SENSORS["hdl64"].elevations()[1]
    with pytest.raises(InputError, match="unknown sensor"):
        sensor_config("hdl128")
    with pytest.raises(InputError, match="one value per beam"):
        sensor_config("vlp16", {"ring_azimuth_offsets_deg": [1.0, 2.0]})
    with pytest.raises(InputError, match="min, max"):
        LidarConfig(n_beams=2, vfov_deg=(-10.0, 10.0), elevations_deg=(-5.0, 5.0))


def test_ring_offsets_dropout_and_mount_height_change_the_sweep():
    ground = make_scene(np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0]]),
                        np.array([[0, 1, 2], [0, 2, 3]]))
    base = sensor_config("vlp16", {"range_noise_m": 0.0, "h_res_deg": 1.0})
    offsets = tuple(float(v) for v in np.linspace(0, 0.75, 16))
    shifted = sensor_config("vlp16", {"range_noise_m": 0.0, "h_res_deg": 1.0,
                                      "ring_azimuth_offsets_deg": offsets})
    d0 = base.directions().reshape(16, -1, 3)
    d1 = shifted.directions().reshape(16, -1, 3)
    az0, az1 = np.arctan2(d0[..., 1], d0[..., 0]), np.arctan2(d1[..., 1], d1[..., 0])
    diff = np.degrees(np.angle(np.exp(1j * (az1 - az0))))
    assert np.allclose(diff, np.asarray(offsets)[:, None], atol=1e-9)
    T = sm.pose_2d(0, 0, 0, z=2.5)
    full = cast_scan([ground], T, base, np.random.default_rng(0))
    dropped = cast_scan([ground], T, dataclasses.replace(base, dropout=0.3), np.random.default_rng(0))
    assert 0.62 < len(dropped.points) / len(full.points) < 0.78
    assert np.allclose(full.points[:, 2], -2.5, atol=1e-4)


def test_each_sensor_gives_n_points_on_the_same_pose(cache):
    poses, sizes = set(), []
    for name in ("vlp16", "hdl32", "hdl64", "os128"):
        ds = LidarSimDataset(cache_dir=cache, town_seed=4, sensor=name, **SMALL)
        poses.add(tuple(np.round(ds.live_pose(1, 2)[:3], 12)))
        live = ds._live(1, 2)
        assert live["scan"].shape == (10_000, 3) and ds.sample_id(0).startswith(f"lidar-sim/town4/{name}/")
        sizes.append(int(live["n_returns"]))
    assert len(poses) == 1  # the same place for every sensor
    assert sizes[0] < sizes[1] < sizes[2]  # 16 < 32 < 64 beams


# -- mixes ------------------------------------------------------------------------------------
def test_lists_of_towns_and_sensors_make_a_mix(cache):
    mix = LidarSimDataset.create(cache_dir=cache, town_seed=[4, 5], sensor=["sim32", "vlp16"],
                          split="train", **SMALL)
    assert isinstance(mix, LidarSimMix) and len(mix.parts) == 4
    assert len({p.cache_root for p in mix.parts}) == 4  # each (town, sensor) cached once
    assert len(mix) == sum(len(p) for p in mix.parts)
    assert mix.describe()["town_seed"] == [4, 5] and mix.describe()["sensor"] == ["sim32", "vlp16"]
    first = [mix._index[i][0] for i in range(8)]
    assert len(set(first)) >= 3  # take(k) draws from every combination
    got = [mix[i] for i in range(3)]
    assert all(g.id.startswith("lidar-sim/town") for g in got)
    assert [mix.sample_id(i) for i in range(3)] == [g.id for g in got]  # without loading
    single = LidarSimDataset.create(cache_dir=cache, town_seed=[4], **SMALL)
    assert isinstance(single, LidarSimDataset) and single.town_seed == 4
    with pytest.raises(InputError, match="duplicates"):
        LidarSimDataset.create(cache_dir=cache, town_seed=[4, 4], **SMALL)
    with pytest.raises(InputError, match="town_seed"):
        LidarSimDataset(cache_dir=cache, town_seed="x", **SMALL)


# -- pictures ---------------------------------------------------------------------------------
def test_towns_and_sensors_pictures(cache, tmp_path):
    from icpbench.analysis.dataset_figures import sensors_figure, towns_figure

    towns = [LidarSimDataset(cache_dir=cache, town_seed=t, **SMALL) for t in (4, 5)]
    p = towns_figure(towns, tmp_path / "towns.png")
    sensors = [LidarSimDataset(cache_dir=cache, town_seed=4, sensor=n, **SMALL)
               for n in ("vlp16", "hdl64")]
    q = sensors_figure(sensors, tmp_path / "sensors.png", frame=2)
    for f in (p, q):
        assert f.stat().st_size > 20_000 and f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_legacy_style_is_the_default():
    assert LEGACY.legacy and not LEGACY.clutter and not LEGACY.grade_waves
    ds_style = LidarSimDataset(route_scale=0.25).style
    assert ds_style is LEGACY

