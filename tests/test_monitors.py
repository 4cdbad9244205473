"""Integrity monitors: what each one flags on constructed scenes, the calibration rule, the
monitored oracle that hides detected errors from query attacks, and the plugin contract.

What it shows: a corridor (two parallel walls and a floor) trips the degeneracy monitor and a
box-like room does not; the odometry gate trips on a pose moved beyond it and not within it, and
its clean scores have the chi-3 quantile it states; the residual and inlier monitors pass a clean
registration of the room and flag the same scan registered 1 m off; calibration at 1% puts 1% of
1000 clean scores above the threshold; the monitored oracle returns NaN exactly for the flagged
candidates and counts them per sample and per monitor, and the search attack runs on it unchanged;
the registry lists the monitors, refuses an unknown one with the valid names and refuses settings
out of range.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Batch, Registration, Sample
from icpbench.harness.monitoring import calibrate, calibrated, clean_scores
from icpbench.monitors.base import Monitor, MonitorInput
from icpbench.monitors.degeneracy import DegeneracyMonitor
from icpbench.monitors.inliers import InlierMonitor
from icpbench.monitors.odometry import CHI3_99, OdometryMonitor, odometry_prior
from icpbench.monitors.oracle import MonitoredOracle
from icpbench.monitors.residual import ResidualMonitor
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

torch.set_num_threads(1)
STEP = 0.2  # map grid (metres)


def _plane(origin, u, v, lu: float, lv: float, normal, step: float, shift: float = 0.0):
    """Grid points (K, 3) on the rectangle origin + a u + b v (a in [0, lu], b in [0, lv]) and
    their unit normals (K, 3); ``shift`` offsets the grid inside the plane."""
    a = np.arange(shift, lu + 1e-9, step)
    b = np.arange(shift, lv + 1e-9, step)
    A, Bv = np.meshgrid(a, b, indexing="ij")
    p = np.asarray(origin, float) + A.reshape(-1, 1) * np.asarray(u, float) + \
        Bv.reshape(-1, 1) * np.asarray(v, float)
    return p, np.tile(np.asarray(normal, float), (p.shape[0], 1))


def _scene(kind: str, step: float = STEP, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Map points and inward normals (map frame, metres) of a 20 x 4 m corridor (floor and two
    walls along x, 3 m high, open ends) or a 10 x 10 m room (floor and four 3 m walls)."""
    ex, ey, ez = np.eye(3)
    if kind == "corridor":
        L, W = 20.0, 4.0
        parts = [_plane((0, 0, 0), ex, ey, L, W, ez, step, shift),
                 _plane((0, 0, 0), ex, ez, L, 3.0, ey, step, shift),
                 _plane((0, W, 0), ex, ez, L, 3.0, -ey, step, shift)]
    else:
        L = W = 10.0
        parts = [_plane((0, 0, 0), ex, ey, L, W, ez, step, shift),
                 _plane((0, 0, 0), ex, ez, L, 3.0, ey, step, shift),
                 _plane((0, W, 0), ex, ez, L, 3.0, -ey, step, shift),
                 _plane((0, 0, 0), ey, ez, W, 3.0, ex, step, shift),
                 _plane((L, 0, 0), ey, ez, W, 3.0, -ex, step, shift)]
    centre = np.array([L / 2, W / 2, 0.0])
    return np.vstack([p for p, _ in parts]) - centre, np.vstack([n for _, n in parts])


def _T(yaw_deg: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


T_GT = _T(20.0, [0.4, -0.3, 1.8])


def _problem(kind: str, noise_m: float = 0.01, seed: int = 0) -> tuple[np.ndarray, MapIndex]:
    """A scan (sensor frame; another grid of the same surfaces with noise) and the map of ``kind``;
    ``T_GT`` maps the scan into the map frame."""
    m, n = _scene(kind)
    world, _ = _scene(kind, step=0.35, shift=0.07)
    world = world + np.random.default_rng(seed).normal(0.0, noise_m, world.shape)
    inv = np.linalg.inv(T_GT)
    return world @ inv[:3, :3].T + inv[:3, 3], MapIndex(m, n)


def _moved(T: np.ndarray, d) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += d
    return out


# -- degeneracy -----------------------------------------------------------------------------------
def test_a_corridor_trips_the_degeneracy_monitor_and_a_box_room_does_not():
    mon = DegeneracyMonitor()
    scan, corridor = _problem("corridor")
    bad = mon.check(MonitorInput(scan=scan, map=corridor, T_hat=T_GT))
    scan, room = _problem("room")
    good = mon.check(MonitorInput(scan=scan, map=room, T_hat=T_GT))
    assert bad.alarm and bad.score > 1e6  # nothing constrains x along the corridor
    assert not good.alarm and 3.0 <= good.score < 6.0  # walls facing x and y alike, and the floor


# -- odometry -------------------------------------------------------------------------------------
def test_a_pose_beyond_the_odometry_gate_trips_it_and_one_within_does_not():
    mon = OdometryMonitor()  # sigma = 0.1 + 0.01 * 10 = 0.2 m; gate 3.368 sigma = 0.67 m
    scan, room = _problem("room")
    prior = mon.motion_prior(T_GT, "room/0")
    assert prior.sigma_m == pytest.approx(0.2)
    assert prior.seed == odometry_prior(T_GT, "room/0").seed  # seeded by the sample id
    np.testing.assert_array_equal(prior.T_pred, mon.motion_prior(T_GT, "room/0").T_pred)
    assert not np.array_equal(prior.T_pred, mon.motion_prior(T_GT, "room/1").T_pred)
    inside = MonitorInput(scan=scan, map=room, T_hat=T_GT, prior=prior, sample_id="room/0")
    within = mon.check(inside)
    beyond = mon.check(MonitorInput(scan=scan, map=room, T_hat=_moved(T_GT, [2.0, 0.0, 0.0]),
                                    prior=prior, sample_id="room/0"))
    assert within.score == pytest.approx(
        np.linalg.norm(prior.T_pred[:3, 3] - T_GT[:3, 3]) / 0.2)
    assert not within.alarm and beyond.alarm
    with pytest.raises(InputError, match="needs a motion prior"):
        mon.score(MonitorInput(scan=scan, map=room, T_hat=T_GT))


def test_odometry_scores_of_perfect_poses_follow_the_stated_noise_model():
    """1000 sample ids, the pose exact: the scores are chi-3 distributed, ~1% above 3.368."""
    mon = OdometryMonitor(distance_m=50.0)
    scan, room = _problem("room")
    ids = [f"room/{i}" for i in range(1000)]
    inputs = [MonitorInput(scan=scan[:10], map=room, T_hat=T_GT, sample_id=i) for i in ids]
    s = clean_scores(mon, inputs, T_gt=[T_GT] * len(ids))
    assert mon.motion_prior(T_GT, "x").sigma_m == pytest.approx(0.1 + 0.01 * 50.0)
    assert abs(np.mean(s > CHI3_99) - 0.01) <= 0.01  # binomial sd of 1000 draws at 1%: 0.003
    assert np.median(s) == pytest.approx(1.538, abs=0.1)  # chi-3 median


# -- residual and inliers -------------------------------------------------------------------------
@pytest.mark.parametrize("monitor", [ResidualMonitor(), InlierMonitor()], ids=lambda m: m.name)
def test_residual_and_inliers_pass_a_clean_registration_and_flag_one_1m_off(monitor):
    scan, room = _problem("room")
    clean = monitor.check(MonitorInput(scan=scan, map=room, T_hat=T_GT))
    off = monitor.check(MonitorInput(scan=scan, map=room, T_hat=_moved(T_GT, [0.8, 0.6, 0.0])))
    assert not clean.alarm, clean
    assert off.alarm, off
    assert off.score > 3 * clean.score


def test_a_diverged_pose_is_always_flagged_and_a_map_without_normals_refused():
    scan, room = _problem("room")
    T = T_GT.copy()
    T[0, 3] = np.nan
    for mon in (ResidualMonitor(), InlierMonitor(), DegeneracyMonitor(), OdometryMonitor()):
        assert mon.score(MonitorInput(scan=scan, map=room, T_hat=T)) == math.inf
    with pytest.raises(InputError, match="no normals"):
        ResidualMonitor().score(MonitorInput(scan=scan, map=MapIndex(room.points), T_hat=T_GT))
    with pytest.raises(InputError, match=r"scan must be a non-empty \(N, 3\)"):
        MonitorInput(scan=np.zeros((4, 2)), map=room, T_hat=T_GT)


# -- calibration ----------------------------------------------------------------------------------
def test_calibration_at_1_percent_puts_1_percent_of_1000_clean_scores_above():
    s = np.random.default_rng(3).gamma(2.0, 0.05, 1000)  # a residual-like score, metres
    rec = calibrate(ResidualMonitor(), s, false_alarm_rate=0.01)
    assert rec.monitor == "residual" and rec.n == 1000 and rec.false_alarm_rate == 0.01
    assert np.mean(s > rec.threshold) == pytest.approx(0.01, abs=0.002)
    assert rec.observed_rate == np.mean(s > rec.threshold)
    assert rec.threshold == pytest.approx(np.quantile(s, 0.99), rel=0.05)
    assert rec.as_dict()["settings"] == {"gate_m": 1.0}
    mon = calibrated(ResidualMonitor(), rec)
    assert mon.threshold == rec.threshold and mon.gate_m == 1.0
    with pytest.raises(InputError, match="needs at least 100 clean scores"):
        calibrate(ResidualMonitor(), s[:50], 0.01)
    with pytest.raises(InputError, match="between 0 and 1"):
        calibrate(ResidualMonitor(), s, 1.5)
    with pytest.raises(InputError, match="are NaN"):
        calibrate(ResidualMonitor(), np.r_[s, np.nan], 0.01)
    with pytest.raises(InputError, match="infinite"):
        calibrate(DegeneracyMonitor(), np.r_[np.full(980, 5.0), np.full(20, np.inf)], 0.01)
    with pytest.raises(InputError, match="calibration of 'residual' given to monitor 'inliers'"):
        calibrated(InlierMonitor(), rec)


# -- the monitored oracle -------------------------------------------------------------------------
class _Gullible(Target):
    """A target that explains any rigid shift s (sensor frame) of the clean scan by moving its
    pose: ``T_hat = T_gt`` with ``t - R mean(s)`` (one iteration, converged, every point an inlier).
    A rigid move is then invisible to the residual and inlier checks, as for a perfect ICP."""

    name: ClassVar[str] = "gullible"
    differentiable: ClassVar[bool] = True

    def __init__(self, batch: Batch) -> None:
        self.batch = batch
        self.which = {id(m): b for b, m in enumerate(batch.maps)}

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray) -> Any:
        return MapIndex(map_points, map_normals)

    def register(self, scans: torch.Tensor, maps: Any, T_init: torch.Tensor) -> Registration:
        out = []
        for k, m in enumerate(maps):
            b = self.which[id(m)]
            T = self.batch.T_gt[b].clone()
            s = (scans[k].to(torch.float64) - self.batch.scans[b].to(torch.float64)).mean(0)
            T[:3, 3] -= T[:3, :3] @ s
            out.append(T)
        K = len(maps)
        return Registration(T=torch.stack(out), converged=torch.ones(K, dtype=torch.bool),
                            iterations=torch.ones(K, dtype=torch.int64),
                            inlier_fraction=torch.ones(K, dtype=torch.float64), status=["ok"] * K)


def _room_batch() -> Batch:
    scan, room = _problem("room")
    samples = [Sample(id=f"room/{i}", scan=scan.astype(np.float32), map=room.points.astype(np.float32),
                      map_normals=room.normals.astype(np.float32), T_gt=T_GT) for i in range(2)]
    return Batch.from_samples(samples)


def test_the_monitored_oracle_returns_nan_exactly_for_flagged_candidates_and_counts_them():
    batch = _room_batch()
    target = _Gullible(batch)
    monitors = [ResidualMonitor(), OdometryMonitor()]
    oracle = MonitoredOracle(target, batch, batch.maps, monitors)
    plain = QueryOracle(target, batch, batch.maps)
    clean = batch.scans
    ey = torch.tensor([0.0, 1.0, 0.0], dtype=clean.dtype)
    half = torch.zeros_like(clean[0])
    half[: clean.shape[1] // 2] = 3.0 * ey  # half the scan moved 3 m: the pose moves 1.5 m
    cands = torch.stack([clean[0], clean[1] + 0.05 * ey, clean[0] + 3.0 * ey, clean[1] + half])
    index = [0, 1, 0, 1]
    T, err, status = oracle.register(cands, index)
    T0, err0, _ = plain.register(cands, index)
    np.testing.assert_array_equal(T, T0)  # the same registration
    np.testing.assert_allclose(err0, [0.0, 0.05, 3.0, 1.5], atol=1e-3)  # N is odd
    res, odo = oracle.last_scores["residual"], oracle.last_scores["odometry"]
    flagged = (res > monitors[0].threshold) | (odo > monitors[1].threshold)
    np.testing.assert_array_equal(flagged, [False, False, True, True])
    np.testing.assert_array_equal(oracle.last_flagged, flagged)
    np.testing.assert_array_equal(np.isnan(err), flagged)  # NaN exactly where flagged
    np.testing.assert_array_equal(err[~flagged], err0[~flagged])
    assert res[2] < monitors[0].threshold < res[3]  # a rigid move fits the map: only odometry sees it
    np.testing.assert_array_equal(oracle.queries, [2, 2])
    np.testing.assert_array_equal(oracle.flagged, [1, 1])
    np.testing.assert_array_equal(oracle.alarms["residual"], [0, 1])
    np.testing.assert_array_equal(oracle.alarms["odometry"], [1, 1])
    assert np.isnan(oracle.errors(clean[:1] + 3.0 * ey, [0])).all()
    np.testing.assert_array_equal(oracle.flagged, [2, 1])
    rec = oracle.record()
    assert rec["flagged"] == [2, 1] and rec["queries"] == [3, 2]
    assert rec["priors"]["odometry"][0]["sigma_m"] == pytest.approx(0.2)
    assert set(rec["priors"]) == {"odometry"}
    assert oracle.name == "gullible" and oracle.target is target and oracle.batch is batch
    with pytest.raises(InputError, match="names must differ"):
        MonitoredOracle(target, batch, batch.maps, [OdometryMonitor(), OdometryMonitor()])


def test_the_search_attack_maximises_the_undetected_error_through_the_monitored_oracle():
    """An attack that only queries runs on the monitored oracle unchanged; its result's error is
    the one the oracle reported, never a flagged one."""
    batch = _room_batch()
    target = _Gullible(batch)
    attack = registry.attacks.get("search")(queries=8)
    oracle = MonitoredOracle(target, batch, batch.maps, [OdometryMonitor(threshold=6.0)])
    out = attack.run(batch, 0.5, generator=0, oracle=oracle)
    np.testing.assert_array_equal(out.extra["queries"].numpy(), [8, 8])
    found = out.extra["search_err"].numpy()
    check = MonitoredOracle(target, batch, batch.maps, [OdometryMonitor(threshold=6.0)])
    again = check.errors(out.scans)
    np.testing.assert_allclose(again, found, atol=1e-9)  # the error kept is an undetected one
    assert np.all(np.isfinite(found)) and check.flagged.sum() == 0


# -- plugin contract ------------------------------------------------------------------------------
def test_the_registry_lists_the_monitors_and_refuses_an_unknown_one_with_the_valid_names():
    names = registry.monitors.names()
    assert {"residual", "inliers", "degeneracy", "odometry"} <= set(names)
    for n in ("residual", "inliers", "degeneracy", "odometry"):
        cls = registry.monitors.get(n)
        assert issubclass(cls, Monitor) and cls.name == n and cls.description
        assert "threshold" in cls.param_types()
    with pytest.raises(InputError, match=r"unknown monitor 'residuals'; valid monitors: .*degeneracy, "
                                         r"inliers, odometry, residual"):
        registry.monitors.get("residuals")
    from typer.testing import CliRunner

    from icpbench.cli import app

    out = CliRunner().invoke(app, ["list"]).output
    assert "monitors (icpbench.monitors):" in out and "odometry" in out


@pytest.mark.parametrize("name, settings, needle", [
    ("residual", {"gate_m": -1.0}, r"setting 'gate_m' of monitor 'residual' must be > 0"),
    ("residual", {"threshold": "nan"}, "must be a finite number"),
    ("inliers", {"threshold": 1.5}, r"setting 'threshold' of monitor 'inliers' must be >= 0 and < 1"),
    ("degeneracy", {"threshold": 2.0}, r"must be >= 3"),
    ("odometry", {"drift": 2.0}, r"setting 'drift' of monitor 'odometry' must be >= 0 and <= 1"),
    ("odometry", {"sigma": 0.1}, r"unknown setting\(s\) 'sigma' for monitor 'odometry'; valid: "
                                 "distance_m, drift, seed, sigma0_m, threshold"),
])
def test_settings_out_of_range_are_refused(name, settings, needle):
    with pytest.raises(InputError, match=needle):
        registry.monitors.check_params(name, settings)
    if "sigma" not in settings:  # building the monitor directly checks the same ranges
        with pytest.raises(InputError):
            registry.monitors.get(name)(**{k: float(v) for k, v in settings.items()})
    ok = registry.monitors.check_params("odometry", {"distance_m": "25", "seed": "3"})
    assert ok == {"distance_m": 25.0, "seed": 3}
    assert OdometryMonitor(**ok).motion_prior(T_GT, "a").sigma_m == pytest.approx(0.35)


def test_monitor_score_and_check_are_final():
    with pytest.raises(TypeError, match="overrides Monitor.score, which is final"):
        class _Overrides(Monitor):  # noqa: F841 - the class statement itself must fail
            name = "overrides"

            def _score(self, inp):
                return 0.0

            def score(self, inp):
                return 0.0


# -- the drift attack: the edge of an odometry gate ----------------------------------------------
def _gate_optimum(prior, t_gt: np.ndarray, radius: float) -> float:
    """The largest horizontal error |e| with |e - n| <= radius, e horizontal, n = t_pred - t_gt."""
    n = prior.T_pred[:3, 3] - t_gt[:3, 3]
    return float(np.linalg.norm(n[:2]) + math.sqrt(radius**2 - n[2] ** 2))


def test_drift_finds_the_edge_of_the_odometry_gate_and_returns_no_flagged_scan():
    """A rigid shift fits the map, so only the gate can see it; the drift attack's heading and
    length search reaches within 10% of the analytic edge of the gate (|n_xy| + sqrt(r^2 - n_z^2)
    along the prediction's offset n), where the plain rigid shift by lambda is flagged."""
    batch = _room_batch()
    target = _Gullible(batch)
    gate = OdometryMonitor()  # sigma 0.2 m, r = 3.368 sigma = 0.674 m
    budget = 2.0
    oracle = MonitoredOracle(target, batch, batch.maps, [gate, ResidualMonitor()])
    out = registry.attacks.get("drift")(queries=40).run(batch, budget, generator=0, oracle=oracle)
    found = out.extra["drift_err"].numpy()
    best = [_gate_optimum(oracle.priors["odometry"][b], T_GT, CHI3_99 * 0.2) for b in range(2)]
    assert np.all(found <= np.array(best) + 1e-9)
    assert np.all(found >= 0.9 * np.array(best)), (found, best)
    check = MonitoredOracle(target, batch, batch.maps, [gate, ResidualMonitor()])
    np.testing.assert_allclose(check.errors(out.scans), found, atol=1e-9)  # not flagged
    assert check.flagged.sum() == 0
    shift = (out.scans - batch.scans).to(torch.float64)
    np.testing.assert_allclose(shift - shift[:, :1], 0.0, atol=1e-6)  # one rigid vector per scan
    np.testing.assert_allclose(shift[:, 0].norm(dim=-1).numpy(), out.extra["drift_m"].numpy(),
                               atol=1e-6)
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    uniform = registry.attacks.get("uniform")().run(batch, budget, generator=0).scans
    assert np.isnan(check.errors(uniform)).all()  # the plain shift by lambda is caught


def test_drift_without_monitors_shifts_by_lambda_and_the_ensemble_adds_it_only_when_monitored():
    batch = _room_batch()
    target = _Gullible(batch)
    plain = QueryOracle(target, batch, batch.maps)
    out = registry.attacks.get("drift")(queries=10).run(batch, 0.5, generator=0, oracle=plain)
    np.testing.assert_allclose(out.extra["drift_err"].numpy(), 0.5, atol=1e-9)
    np.testing.assert_array_equal(out.extra["queries"].numpy(), [10, 10])
    monitored = MonitoredOracle(target, batch, batch.maps, [OdometryMonitor()])
    ens = registry.attacks.get("ensemble")
    assert "drift" not in ens().active_for(plain)
    assert ens().active_for(monitored)[-2:] == ("drift", "refine")
    assert ens(members="uniform,search").active_for(monitored) == ("uniform", "search")
    run = ens(members="uniform,drift").run(batch, 2.0, generator=0, oracle=monitored)
    err = run.extra["err_drift"].numpy()
    assert np.all(err > 0.5) and np.isnan(run.extra["err_uniform"].numpy()).all()
    check = MonitoredOracle(target, batch, batch.maps, [OdometryMonitor()])
    np.testing.assert_allclose(check.errors(run.scans), err, atol=1e-9)
