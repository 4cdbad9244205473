"""The monitors as a gradient attack sees them: differentiable scores, the penalty, penalised PGD.

Checks that each built-in monitor's differentiable score equals its score of the same
registration, that its gradient matches finite differences (residual, odometry) or points the way
the exact score moves (the soft counts), and that projected gradient ascent with the penalty
returns a candidate the monitored oracle accepts where plain ascent is caught.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import pytest
import torch
from test_monitors import T_GT, _gate_optimum, _problem, _room_batch

from icpbench.attacks.pgd import PGDAttack
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.monitors.base import Monitor, MonitorInput
from icpbench.monitors.degeneracy import DegeneracyMonitor
from icpbench.monitors.differentiable import DiffInput
from icpbench.monitors.inliers import InlierMonitor
from icpbench.monitors.odometry import OdometryMonitor, odometry_prior
from icpbench.monitors.oracle import MonitoredOracle
from icpbench.monitors.penalty import MonitorPenalty
from icpbench.monitors.residual import ResidualMonitor
from icpbench.targets.oracle import QueryOracle

torch.set_num_threads(1)

MONITORS = [ResidualMonitor(), InlierMonitor(gate_m=0.2), DegeneracyMonitor(), OdometryMonitor()]


def _offset(d) -> np.ndarray:
    T = T_GT.copy()
    T[:3, 3] += d
    return T


def _diff(scan: np.ndarray, T: np.ndarray, room, prior) -> DiffInput:
    return DiffInput(torch.tensor(scan, requires_grad=True), torch.tensor(T, requires_grad=True),
                     room, prior, "room")


@pytest.mark.parametrize("monitor", MONITORS, ids=lambda m: m.name)
@pytest.mark.parametrize("d", [(0.0, 0.0, 0.0), (0.3, -0.2, 0.05), (0.0, 0.9, 0.0)])
def test_a_differentiable_score_equals_the_monitors_score_of_the_same_registration(monitor, d):
    scan, room = _problem("room")
    T, prior = _offset(d), odometry_prior(T_GT, "room")
    exact = monitor.score(MonitorInput(scan=scan, map=room, T_hat=T, prior=prior))
    x = _diff(scan, T, room, prior)
    s = monitor.differentiable_score(x)
    assert float(s.detach()) == pytest.approx(exact, rel=1e-9, abs=1e-12)
    gs, gT = torch.autograd.grad(s, (x.scan, x.T_hat), allow_unused=True)
    for g in (gs, gT):
        assert g is None or bool(torch.isfinite(g).all())


@pytest.mark.parametrize("monitor", [ResidualMonitor(), OdometryMonitor()], ids=lambda m: m.name)
def test_residual_and_odometry_gradients_match_central_differences(monitor):
    """With the pairs held (steps of 1e-6 m move no point to another nearest map point), the
    gradient with respect to the pose's translation and to scan points is the score's."""
    scan, room = _problem("room")
    T, prior = _offset((0.3, -0.2, 0.05)), odometry_prior(T_GT, "room")
    x = _diff(scan, T, room, prior)
    gs, gT = torch.autograd.grad(monitor.differentiable_score(x), (x.scan, x.T_hat),
                                 allow_unused=True)
    h = 1e-6

    def score(scan_, T_):
        return monitor.score(MonitorInput(scan=scan_, map=room, T_hat=T_, prior=prior))

    for k in range(3):
        Tp, Tm = T.copy(), T.copy()
        Tp[k, 3] += h
        Tm[k, 3] -= h
        fd = (score(scan, Tp) - score(scan, Tm)) / (2 * h)
        assert float(gT[k, 3]) == pytest.approx(fd, rel=1e-4, abs=1e-7)
    if monitor.name == "residual":
        for i in (0, 500, 1500):
            for k in range(3):
                sp, sm = scan.copy(), scan.copy()
                sp[i, k] += h
                sm[i, k] -= h
                fd = (score(sp, T) - score(sm, T)) / (2 * h)
                assert float(gs[i, k]) == pytest.approx(fd, rel=1e-4, abs=1e-8)


@pytest.mark.parametrize("monitor", [InlierMonitor(gate_m=0.2), DegeneracyMonitor(gate_m=0.3)],
                         ids=lambda m: m.name)
def test_the_soft_counts_slope_the_way_the_exact_score_moves(monitor):
    """A count of points within a gate has no gradient; its logistic stand-in's slope along a
    pose shift agrees in sign with the exact score's change over a 0.1 m step."""
    scan, room = _problem("room")
    direction = np.array([1.0, 0.0, 0.0])
    T = _offset(0.25 * direction)
    x = _diff(scan, T, room, None)
    (gT,) = torch.autograd.grad(monitor.differentiable_score(x), (x.T_hat,))
    slope = float(gT[:3, 3] @ torch.as_tensor(direction))

    def score(d):
        return monitor.score(MonitorInput(scan=scan, map=room, T_hat=_offset(d * direction)))

    change = score(0.35) - score(0.15)
    assert abs(change) > 1e-3 and np.sign(slope) == np.sign(change), (slope, change)


def test_the_penalty_is_zero_inside_the_margin_and_marks_candidates_past_a_threshold():
    batch = _room_batch()
    gate = OdometryMonitor()  # sigma 0.2 m
    prior = gate.motion_prior(T_GT, batch.samples[0].id)
    pen = MonitorPenalty([gate, _Opaque()], batch.maps, {"odometry": [prior, prior]},
                         [s.id for s in batch.samples])
    assert pen.blind == ("opaque",) and [m.name for m in pen.seen] == ["odometry"]
    t_pred = prior.T_pred[:3, 3]
    T = np.stack([_offset(t_pred - T_GT[:3, 3]), _offset(t_pred - T_GT[:3, 3] + [1.0, 0, 0])])
    T = torch.tensor(T, requires_grad=True)
    p, feasible = pen(batch.scans.to(torch.float64), T)
    np.testing.assert_array_equal(feasible, [True, False])
    assert float(p[0].detach()) == 0.0  # on the prediction: no penalty
    expected = 10.0 * (1.0 / 0.2 / gate.threshold - 0.95)  # 1 m = 5 sigma past 0.95 threshold
    assert float(p[1].detach()) == pytest.approx(expected, rel=1e-9)
    (g,) = torch.autograd.grad(p.sum(), T)
    assert float(g[1, 0, 3]) > 0 and float(g[0].abs().sum()) == 0.0
    T_bad = T.detach().clone()
    T_bad[0, 0, 3] = math.nan
    _, feasible = pen(batch.scans.to(torch.float64), T_bad)
    assert not feasible[0]
    with pytest.raises(InputError, match="margin"):
        MonitorPenalty([gate], batch.maps, {}, ["a", "b"], margin=1.0)
    with pytest.raises(InputError, match="no differentiable score"):
        scan, room = _problem("room")
        _Opaque().differentiable_score(_diff(scan, T_GT, room, None))


def test_penalised_gradient_ascent_stays_within_the_odometry_gate_where_plain_ascent_does_not():
    """Plain projected ascent through p2plane moves the pose past the gate; with the monitors'
    penalty it returns a candidate the monitored oracle accepts, with an error of at least half
    the gate's analytic edge for a pure shift."""
    batch = _room_batch()
    target = registry.targets.get("p2plane")()
    gate = OdometryMonitor(threshold=4.0, sigma0_m=0.05, drift=0.0)  # radius 0.2 m
    monitors = [gate, ResidualMonitor()]
    oracle = MonitoredOracle(target, batch, batch.maps, monitors)
    assert np.isfinite(oracle.errors(batch.scans)).all()  # the clean scans pass
    pgd = PGDAttack(steps=10, step_size=0.1, backprop="implicit", icp_iterations=100)
    plain = pgd.refine(batch, batch.scans, 1.0, surrogate=target).to(torch.float64)
    penalised = pgd.refine(batch, batch.scans, 1.0, surrogate=target,
                           penalty=oracle.penalty()).to(torch.float64)
    seen = QueryOracle(target, batch, batch.maps)
    assert np.all(seen.errors(plain) > 1.0)
    check = MonitoredOracle(target, batch, batch.maps, monitors)
    assert np.isnan(check.errors(plain)).all()  # caught
    err = check.errors(penalised)
    # a level shift reaches at most the gate's analytic edge; the ascent may also move the pose
    # vertically onto the prediction's error and rotate it, so it is only asked to pass half
    edge = np.array([_gate_optimum(oracle.priors["odometry"][b], T_GT, 0.2) for b in range(2)])
    assert np.all(np.isfinite(err)) and np.all(err >= 0.5 * edge), (err, edge)
    assert np.all(check.last_scores["odometry"] <= gate.threshold)
    disp = torch.linalg.norm(penalised - batch.scans.to(torch.float64), dim=-1)
    assert float(disp.max()) <= 1.0 + 1e-9


def test_the_ensemble_refines_from_the_best_undetected_scan_under_monitors():
    batch = _room_batch()
    target = registry.targets.get("p2plane")()
    monitors = [OdometryMonitor(threshold=4.0, sigma0_m=0.05, drift=0.0), ResidualMonitor()]
    oracle = MonitoredOracle(target, batch, batch.maps, monitors)
    ens = registry.attacks.get("ensemble")(members="uniform,refine")
    out = ens.run(batch, 1.0, surrogate=target, generator=0, oracle=oracle)
    assert np.isnan(out.extra["err_uniform"].numpy()).all()  # a rigid 1 m shift is caught
    err = out.extra["err_refine"].numpy()
    assert np.all(np.isfinite(err)) and np.all(err > 0.1)
    check = MonitoredOracle(target, batch, batch.maps, monitors)
    np.testing.assert_allclose(check.errors(out.scans.to(torch.float64)), err, atol=1e-6)


class _Opaque(Monitor):
    """A monitor without a differentiable score."""

    name: ClassVar[str] = "opaque"

    def __init__(self, *, threshold: float = 1.0) -> None:
        super().__init__(threshold=threshold)

    def _score(self, inp: MonitorInput) -> float:
        return 0.0
