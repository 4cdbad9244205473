"""Realistic corruptions: the physics of each model on a synthetic ring-structured scan, the contract
every corruption shares (N unchanged, deterministic per seed, graded by severity, bad input refused)
and the plugin kind (registry, ``icpbench list``)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.corruptions.base import SEVERITIES, Corruption
from icpbench.corruptions.beam_loss import BeamLoss, estimate_rings
from icpbench.corruptions.crosstalk import Crosstalk
from icpbench.corruptions.fog import Fog
from icpbench.corruptions.occluder import Occluder
from icpbench.corruptions.range_noise import RangeNoise
from icpbench.corruptions.snow import Snow

NAMES = ("beam-loss", "range-noise", "fog", "snow", "occluder", "crosstalk")
N_RINGS, N_AZ = 16, 360
GROUND_Z = -1.8


def lidar_scan(n_rings: int = N_RINGS, n_az: int = N_AZ) -> tuple[np.ndarray, np.ndarray]:
    """A noise-free spinning lidar (n_rings lasers from -15 to +15 degrees, one firing per degree)
    in a walled yard: ground at z = -1.8 m, walls at x = +-60 m and y = +-30 m.

    Returns:
        (scan (n_rings * n_az, 3) sensor frame metres, ring index (n_rings * n_az,)).
    """
    elev = np.deg2rad(np.linspace(-15.0, 15.0, n_rings))
    az = np.deg2rad(np.arange(n_az) * 360.0 / n_az + 0.5)
    e, a = np.meshgrid(elev, az, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t_ground = np.where(d[:, 2] < 0, GROUND_Z / d[:, 2], np.inf)
        t_wall = np.minimum(60.0 / np.abs(d[:, 0]), 30.0 / np.abs(d[:, 1]))
    return d * np.minimum(t_ground, t_wall)[:, None], np.repeat(np.arange(n_rings), n_az)


SCAN, RINGS = lidar_scan()
RANGE = np.linalg.norm(SCAN, axis=1)


def same_ray(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """(N,) whether each new point lies on the ray (from the origin) of its old point."""
    u = new / np.linalg.norm(new, axis=1, keepdims=True)
    v = old / np.linalg.norm(old, axis=1, keepdims=True)
    return np.abs(np.einsum("ij,ij->i", u, v) - 1.0) < 1e-9


def on_own_ray(new: np.ndarray, old: np.ndarray) -> bool:
    """Every new point lies on the ray (from the origin) of its old point."""
    return bool(np.all(same_ray(new, old)))


# -- plugin kind ----------------------------------------------------------------------------------
def test_registry_lists_all_six_corruptions():
    assert set(NAMES) <= set(registry.corruptions.names())
    for name in NAMES:
        cls = registry.corruptions.get(name)
        assert issubclass(cls, Corruption) and cls.name == name
        assert set(cls.LEVELS) == set(SEVERITIES)
    info = {i.name: i for i in registry.corruptions.info()}
    assert all(info[n].available and info[n].description for n in NAMES)


def test_icpbench_list_shows_a_corruptions_heading():
    out = CliRunner().invoke(app, ["list"])
    assert out.exit_code == 0, out.output
    assert "corruptions (icpbench.corruptions):" in out.output
    tail = out.output.split("corruptions (icpbench.corruptions):")[1]
    for name in NAMES:
        assert name in tail
    assert out.output.index("datasets (icpbench.datasets):") < out.output.index("corruptions (")


def test_settings_are_checked_and_the_contract_enforced():
    with pytest.raises(InputError, match="unknown setting"):
        registry.corruptions.check_params("fog", {"bogus": 1})
    assert registry.corruptions.check_params("occluder", {"sensor_height_m": "1.73"}) == {
        "sensor_height_m": 1.73}
    with pytest.raises(InputError, match="not a subclass"):
        registry.corruptions.register("p2plane", registry.targets.get("p2plane"))
    with pytest.raises(TypeError, match="final"):
        type("Bad", (Corruption,), {"apply": lambda self, *a: None})
    with pytest.raises(TypeError, match="severities"):
        type("Short", (Corruption,), {"LEVELS": {1: {}, 2: {}}})


# -- the contract every model shares --------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_count_determinism_grading_and_record(name):
    c = registry.corruptions.get(name)()
    scan32 = SCAN.astype(np.float32)
    a = c.apply(scan32, 3, seed=7)
    assert a.scan.shape == scan32.shape and a.scan.dtype == np.float32
    assert np.array_equal(a.scan, c.apply(scan32, 3, seed=7).scan)  # same seed, same scan
    assert c.random
    assert not np.array_equal(a.scan, c.apply(scan32, 3, seed=8).scan)  # another seed, another scan
    # unchanged points are bit-identical; the record matches the scan
    moved = np.any(a.scan != scan32, axis=1)
    assert not np.any(moved & ~a.replaced)
    assert a.share_replaced == pytest.approx(a.replaced.mean())
    disp = np.linalg.norm(a.scan.astype(np.float64) - scan32, axis=1).mean()
    assert a.mean_displacement_m == pytest.approx(disp, rel=1e-4, abs=1e-6)
    rec = a.record.as_dict()
    json.dumps(rec)
    assert rec["name"] == name and rec["severity"] == 3 and rec["seed"] == 7
    assert set(c.LEVELS[3]) <= set(rec["params"])
    # severity 1 changes less than severity 5
    lo, hi = (c.apply(SCAN, s, seed=0) for s in (1, 5))
    assert lo.share_replaced < hi.share_replaced or lo.mean_displacement_m < hi.mean_displacement_m
    assert lo.mean_displacement_m < hi.mean_displacement_m


@pytest.mark.parametrize("name", NAMES)
def test_bad_input_raises_input_error(name):
    c = registry.corruptions.get(name)()
    bad_scans = {
        "shape": SCAN[:, :2], "1-D": SCAN[:, 0], "empty": np.zeros((0, 3)),
        "int": SCAN.astype(np.int64), "list": SCAN.tolist(),
        "NaN": np.vstack([SCAN, [[np.nan, 0.0, 0.0]]]), "Inf": np.vstack([SCAN, [[np.inf, 1, 1]]]),
        "origin": np.vstack([SCAN, [[0.0, 0.0, 0.0]]]),
    }
    for why, scan in bad_scans.items():
        with pytest.raises(InputError):
            c.apply(scan, 1, seed=0)
            pytest.fail(f"{why} was accepted")
    for severity in (0, 6, -1, 2.0, True, "3", None):
        with pytest.raises(InputError, match="severity"):
            c.apply(SCAN, severity, seed=0)
    for seed in (-1, 1.5, "0", None):
        with pytest.raises(InputError, match="seed"):
            c.apply(SCAN, 1, seed=seed)


# -- the physics of each model --------------------------------------------------------------------
def test_fog_loses_more_far_returns_as_it_thickens_and_backscatters_near_the_sensor():
    fog = Fog()
    far, near = RANGE > 25.0, RANGE < 15.0
    far_lost = []
    for s in SEVERITIES:
        res = fog.apply(SCAN, s, seed=0)
        far_lost.append(res.replaced[far].mean())
        assert res.replaced[far].mean() > res.replaced[near].mean()
        # the lost points became backscatter returns near the sensor, on their own rays
        new = res.scan[res.replaced]
        r_new = np.linalg.norm(new, axis=1)
        lo, hi = res.record.details["backscatter_window_m"]
        assert np.all((r_new >= lo - 1e-9) & (r_new <= hi + 1e-9)) and hi < 12.0
        assert np.all(r_new < RANGE[res.replaced])
        assert on_own_ray(new, SCAN[res.replaced])
        assert res.record.params["alpha_per_m"] == Fog.LEVELS[s]["alpha_per_m"]
    assert all(a < b for a, b in zip(far_lost, far_lost[1:], strict=False))
    assert far_lost[0] > 0.05 and far_lost[-1] > 0.99
    # the loss grows with range: light fog (MOR 600 m) already thins the farthest returns
    light = fog.apply(SCAN, 1, seed=0).replaced
    assert light[RANGE > 40.0].mean() > light[(RANGE > 30.0) & (RANGE < 40.0)].mean() > 0


def test_snow_adds_near_returns_and_more_with_heavier_snowfall():
    snow = Snow()
    scatter = []
    assert not np.any(RANGE < 6.0)
    for s in SEVERITIES:
        res = snow.apply(SCAN, s, seed=0)
        r_new = np.linalg.norm(res.scan, axis=1)
        # a flake's echo: moved toward the sensor on its own ray (lost points duplicate survivors)
        hit = res.replaced & (r_new < RANGE - 1e-9) & same_ray(res.scan, SCAN)
        assert hit.sum() == res.record.details["scatter"] > 0
        assert np.median(r_new[hit]) < 10.0  # short-to-mid range
        scatter.append(hit.mean())
        near = (r_new < 6.0).mean()
        assert near > 0.005
    assert all(a < b for a, b in zip(scatter, scatter[1:], strict=False))
    assert scatter[0] > 0.005 and scatter[-1] > 2 * scatter[0]


def _inside_box(points: np.ndarray, centre: np.ndarray, yaw: float, size: np.ndarray,
                shrink: float) -> np.ndarray:
    """Whether points (..., 3) lie inside the box shrunk by ``shrink`` metres on every side."""
    c, s = np.cos(yaw), np.sin(yaw)
    q = points - centre
    local = np.stack([c * q[..., 0] + s * q[..., 1], -s * q[..., 0] + c * q[..., 1], q[..., 2]], -1)
    return np.all(np.abs(local) < size / 2 - shrink, axis=-1)


def test_nothing_returns_from_inside_the_occluders_shadow():
    occ = Occluder()
    for s in (1, 3, 5):
        res = occ.apply(SCAN, s, seed=3)
        det = res.record.details
        centre, yaw, size = np.array(det["box_centre_m"]), det["box_yaw_rad"], np.array(det["box_size_m"])
        assert det["ground_z_m"] == pytest.approx(GROUND_Z)
        assert np.hypot(*centre[:2]) == pytest.approx(det["distance_m"])
        lo, hi = Occluder.LEVELS[s]["distance_min_m"], Occluder.LEVELS[s]["distance_max_m"]
        assert lo <= det["distance_m"] <= hi
        # the box lies beyond the plane through the sensor normal to its bearing: only rays to
        # points in front of that plane can meet it (sampled along their length below)
        front = SCAN[:, :2] @ centre[:2] > 0
        assert not np.any(res.replaced[~front])
        t = np.linspace(0.0, 1.0, 801)[:, None, None]
        # every clean point whose ray crosses the inside of the box is replaced ...
        crosses = _inside_box(t * SCAN[front][None], centre, yaw, size, 1e-3).any(axis=0)
        assert crosses.sum() > 20 and np.all(res.replaced[front][crosses])
        # ... by a point on the box surface, nearer on its own ray
        new = res.scan[res.replaced]
        assert on_own_ray(new, SCAN[res.replaced])
        assert np.all(np.linalg.norm(new, axis=1) <= RANGE[res.replaced] + 1e-9)
        assert np.all(_inside_box(new, centre, yaw, size, -1e-6))  # on or in the closed box
        assert not np.any(_inside_box(new, centre, yaw, size, 1e-6))  # not in its interior
        # no ray of the corrupted scan passes through the box: nothing returns from its shadow
        assert not _inside_box(t[:-1] * res.scan[front][None], centre, yaw, size, 1e-6).any()
        # points outside the shadow are unchanged
        assert np.array_equal(res.scan[~res.replaced], SCAN[~res.replaced])
        assert res.record.details["shadowed"] == res.replaced.sum()
    # the nearer box (higher level) casts the wider shadow on the same bearing
    shares = [occ.apply(SCAN, s, seed=3).share_replaced for s in SEVERITIES]
    assert all(a < b for a, b in zip(shares, shares[1:], strict=False))


def test_beam_loss_removes_whole_rings_and_duplicates_survivors():
    assert np.array_equal(estimate_rings(SCAN), RINGS)
    bl = BeamLoss()
    clean_rows = {tuple(p) for p in SCAN}
    previous: set[int] = set()
    for s in SEVERITIES:
        res = bl.apply(SCAN, s, seed=0)
        lost = set(res.record.details["rings_lost"])
        assert len(lost) == round(BeamLoss.LEVELS[s]["ring_share_lost"] * N_RINGS)
        assert previous <= lost  # one seed: the rings lost at a level stay lost above it
        previous = lost
        # whole rings: exactly the points of the lost rings are replaced
        assert np.array_equal(res.replaced, np.isin(RINGS, sorted(lost)))
        # replaced points duplicate surviving points, so the set of rings present shrinks
        survivors = {tuple(p) for p in SCAN[~res.replaced]}
        assert {tuple(p) for p in res.scan[res.replaced]} <= survivors <= clean_rows
        present = set(estimate_rings(res.scan).tolist())
        rings_present = {int(r) for r in np.unique(RINGS[~res.replaced])}
        assert len(present) == len(rings_present) == N_RINGS - len(lost)
    with pytest.raises(InputError, match="ring"):
        bl.apply(np.column_stack([SCAN[:, :2], np.zeros(len(SCAN))]), 1, seed=0)  # a flat scan


def test_range_noise_keeps_directions_and_matches_the_level_sigma():
    rn = RangeNoise()
    for s in SEVERITIES:
        res = rn.apply(SCAN, s, seed=1)
        assert on_own_ray(res.scan, SCAN)
        dr = np.linalg.norm(res.scan, axis=1) - RANGE
        sigma = RangeNoise.LEVELS[s]["sigma_m"]
        assert np.std(dr) == pytest.approx(sigma, rel=0.05)
        assert abs(np.mean(dr)) < 4 * sigma / np.sqrt(len(dr))
        assert res.share_replaced == 1.0


def test_crosstalk_replaces_the_level_share_with_uniform_ranges_on_own_rays():
    ct = Crosstalk()
    previous = np.zeros(len(SCAN), dtype=bool)
    for s in SEVERITIES:
        res = ct.apply(SCAN, s, seed=2)
        share = Crosstalk.LEVELS[s]["share"]
        assert abs(res.share_replaced - share) <= 1.0 / len(SCAN)
        assert np.all(res.replaced[previous])  # nested across levels for one seed
        previous = res.replaced
        new = res.scan[res.replaced]
        assert on_own_ray(new, SCAN[res.replaced])
        r_new = np.linalg.norm(new, axis=1)
        assert np.all((r_new >= 1.0) & (r_new <= 120.0))
    # uniform on 1..120 m: mean 60.5 m, std 34.4 m
    assert np.mean(r_new) == pytest.approx(60.5, abs=8.0)
    assert np.std(r_new) == pytest.approx(119 / np.sqrt(12), rel=0.15)
