"""The ``valley`` attack: a spoofed pose whose model cost falls all the way from the true pose.

What it shows: every candidate keeps the budget; the per-point choice reaches the brute-force
relaxation of the line's largest climb to within one point's range; on a street with a cross wall the chosen
displacement climbs less along the line than the plain spoof displacement; against point-to-point
ICP the attack keeps the budget, spends exactly its queries and leads the target farther than
``spoof`` with the same queries.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import linprog

from icpbench.attacks.spoof import SpoofAttack, spoofed_displacement
from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.attacks.valley import ValleyAttack, candidates, choose, line_climbs, rho, valley_displacement
from icpbench.core.cost_sensitivity import CostSpec
from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.targets.oracle import QueryOracle
from icpbench.targets.p2point import PointToPointICP

torch.set_num_threads(1)
LAM = 0.5
COST = CostSpec("point", d_max=5.0, cauchy_c=1.0)


def _street() -> tuple[np.ndarray, np.ndarray]:
    """A wall along x (y = 2, normal y) and a cross wall (x = 5, normal x), 0.25 m grids."""
    g = np.arange(-10.0, 10.001, 0.25)
    h = np.arange(0.0, 2.001, 0.25)
    wall = np.array([(x, 2.0, z) for x in g for z in h])
    cross = np.array([(5.0, y, z) for y in np.arange(-2.0, 1.76, 0.25) for z in h])
    normals = np.concatenate([np.tile([0.0, 1.0, 0.0], (len(wall), 1)),
                              np.tile([1.0, 0.0, 0.0], (len(cross), 1))])
    return np.concatenate([wall, cross]), normals


def test_every_candidate_keeps_the_budget():
    m, n = _street()
    index = MapIndex(m, n)
    cand = candidates(m[::2], np.array([3.0, 1.0, 0.0]), index, 1.0)
    assert cand.shape == (14, len(m[::2]), 3)
    assert np.linalg.norm(cand, axis=-1).max() <= 1.0 + 1e-12
    np.testing.assert_array_equal(cand[0], 0.0)  # "no move" is always a choice


def test_the_model_cost_is_gated_and_cauchy():
    r = np.array([0.0, 1.0, 5.0, 9.0])
    np.testing.assert_allclose(rho(r, COST), [0.0, 0.5 * np.log(2.0), 0.5 * np.log(26.0),
                                              0.5 * np.log(26.0)])
    np.testing.assert_allclose(rho(r, CostSpec("point", d_max=2.0)), [0.0, 0.5, 2.0, 2.0])


@pytest.mark.parametrize("kernel", ["cauchy", "huber", "geman_mcclure"])
def test_each_kernels_cost_has_the_icps_weight_as_its_slope(kernel):
    # rho'(r) = r w(r), with w the ICP's own weight (icpbench.targets.icp.kernel_weight): the
    # model cost is the one whose IRLS steps the target takes
    from icpbench.targets.icp import kernel_weight

    spec = CostSpec("point", d_max=5.0, cauchy_c=0.7, kernel=kernel)
    r = np.array([0.05, 0.3, 0.69, 0.71, 1.4, 3.0])
    h = 1e-6
    slope = (spec.rho(r + h) - spec.rho(r - h)) / (2 * h)
    w_icp = kernel_weight(torch.tensor(r * r), kernel, 0.49)[0].numpy()
    np.testing.assert_allclose(slope, r * w_icp, rtol=1e-6)
    np.testing.assert_allclose(spec.weight(r), w_icp, rtol=1e-12)
    assert spec.rho(np.zeros(1))[0] == 0.0
    with pytest.raises(InputError, match="kernel"):
        CostSpec("point", d_max=5.0, cauchy_c=0.7, kernel="tukey")


def test_the_kernel_model_acts_on_geman_mcclure_kernels_only_by_default():
    from icpbench.core.cost_sensitivity import acting_kernel_model, cost_of
    from icpbench.targets.kiss import KissICPTarget
    from icpbench.targets.p2plane import PointToPlaneICP

    kiss = KissICPTarget("lidar")
    assert cost_of(kiss, kernel_model="cauchy") == CostSpec("point", kiss.max_corr, None)  # v2's
    for model in ("geman-mcclure", "own"):
        gm = cost_of(kiss, kernel_model=model)
        assert gm.kernel == "geman_mcclure" and np.isclose(gm.cauchy_c ** 2, kiss.kernel)
    huber = PointToPlaneICP("lidar", kernel="huber")
    cauchy_icp = PointToPlaneICP("lidar")
    assert cost_of(huber).kernel == "cauchy" and cost_of(huber, kernel_model="own").kernel == "huber"
    assert cost_of(huber, kernel_model="geman-mcclure") == cost_of(huber)
    assert cost_of(PointToPlaneICP("lidar", kernel="none"), kernel_model="own").cauchy_c is None
    with pytest.raises(InputError, match="kernel_model"):
        cost_of(kiss, kernel_model="tukey")
    # a model acts as "cauchy" wherever it gives Cauchy's plan; None is a setting from before v3
    assert acting_kernel_model("geman-mcclure", kiss) == "geman-mcclure"
    assert acting_kernel_model(None, kiss) == "cauchy"
    assert acting_kernel_model("geman-mcclure", huber) == "cauchy"
    assert acting_kernel_model("own", huber) == "own"
    assert acting_kernel_model("own", cauchy_icp) == "cauchy"  # its own kernel is Cauchy's
    # the setting is recorded, and a setting recorded before it acts as "cauchy"
    assert ValleyAttack().settings()["kernel_model"] == "geman-mcclure"
    assert ValleyAttack.settings_on({"queries": 16}, huber) == {"queries": 16,
                                                                 "kernel_model": "cauchy"}
    with pytest.raises(InputError, match="kernel_model"):
        ValleyAttack(kernel_model=True)
    p_map = _street()[0][::3]
    index = MapIndex(*_street())
    D = np.array([2.0, 0.0, 0.0])
    cauchy = valley_displacement(p_map, np.eye(3), D, index, 0.6, CostSpec("point", 5.0, 0.3))
    gm_plan = valley_displacement(p_map, np.eye(3), D, index, 0.6,
                                  CostSpec("point", 5.0, 0.3, "geman_mcclure"))
    assert np.linalg.norm(gm_plan, axis=1).max() <= 0.6 * (1 + 1e-12)
    assert np.any(np.abs(cauchy - gm_plan) > 1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_the_choice_comes_within_one_points_range_of_the_linear_programme(seed):
    # the mixed relaxation, solved in full by HiGHS, bounds every choice from below; rounding the
    # few fractional points of its solution costs at most a point's range per step
    rng = np.random.default_rng(seed)
    C, K, N = 3, 4, 300
    climbs = rng.normal(size=(C, K, N)) + 0.3 * rng.normal(size=(C, K, 1))
    pick = choose(climbs)
    got = climbs[pick, :, np.arange(N)].sum(axis=0).max()
    a_ub = np.c_[climbs.transpose(1, 0, 2).reshape(K, C * N), -np.ones(K)]
    a_eq = np.zeros((N, C * N + 1))
    for c in range(C):
        a_eq[np.arange(N), c * N + np.arange(N)] = 1.0
    lp = linprog(np.r_[np.zeros(C * N), 1.0], A_ub=a_ub, b_ub=np.zeros(K), A_eq=a_eq,
                 b_eq=np.ones(N), bounds=[(0.0, None)] * (C * N) + [(None, None)]).fun
    assert lp - 1e-6 <= got <= lp + np.ptp(climbs, axis=0).max()


def test_the_chosen_displacement_climbs_less_than_the_spoof_along_the_line():
    m, n = _street()
    index = MapIndex(m, n)
    p_map = m[::3]
    D = np.array([2.0, 0.0, 0.0])
    lam = 0.6
    eye = np.eye(3)
    ours = valley_displacement(p_map, eye, D, index, lam, COST)
    spoof = spoofed_displacement(p_map, eye, D, index, lam)
    assert np.linalg.norm(ours, axis=1).max() <= lam * (1 + 1e-12)

    def largest_climb(delta):
        return line_climbs(p_map, delta[None], D, index, COST)[0].sum(axis=1).max()

    # the cross wall pulls a spoofed scan back once the pose passes lambda; the choice keeps the
    # cost from climbing as much anywhere on the line
    assert largest_climb(ours) < 0.8 * largest_climb(spoof)  # measured: 0.73


@pytest.mark.parametrize("steps", [1, 4, 8])
def test_the_lines_climbs_add_up_to_the_cost_between_its_ends_at_any_number_of_steps(steps):
    # the climbs telescope: on any number of steps they sum to the model cost at D minus the
    # cost at the true pose, per candidate and point, so a coarser line changes where the
    # climbs are looked at, not what they add up to
    m, n = _street()
    index = MapIndex(m, n)
    p_map = m[::3] + np.array([0.0, -0.4, 0.1])
    D = np.array([1.5, 0.5, 0.0])
    cand = candidates(p_map, D, index, 0.6)
    climbs = line_climbs(p_map, cand, D, index, COST, steps)
    assert climbs.shape == (len(cand), steps, len(p_map))
    ends = np.stack([rho(index.query(p_map + c + a * D)[0], COST) for c in cand for a in (0, 1)])
    np.testing.assert_allclose(climbs.sum(axis=1), (ends[1::2] - ends[0::2]), atol=1e-12)


def test_the_climbs_skip_lookups_beyond_the_gate_and_equal_every_step_looked_up():
    # points far off the street: a step whose predecessor lay more than a step beyond the gate is
    # not looked up, and the climbs equal, to the bit, those with every step looked up
    m, n = _street()
    cost = CostSpec("point", d_max=1.0, cauchy_c=0.5)
    rng = np.random.default_rng(0)
    p_map = np.concatenate([m[::3] + np.array([0.0, -0.4, 0.1]),
                            rng.uniform(-12, 12, (300, 3)) + np.array([0.0, -8.0, 0.0])])
    D = np.array([1.5, 0.5, 0.0])
    cand = candidates(p_map, D, MapIndex(m, n), 0.6)

    class Counted(MapIndex):
        asked = 0

        def query(self, q, max_dist=np.inf):
            Counted.asked += len(q)
            return super().query(q, max_dist)

    index = Counted(m)
    climbs = line_climbs(p_map, cand, D, index, cost, 4)
    a = np.arange(5) / 4
    q = (p_map[None, None] + cand[:, None] + a[None, :, None, None] * D)
    every = np.diff(rho(MapIndex(m).query(q.reshape(-1, 3))[0], cost).reshape(len(cand), 5, -1),
                    axis=1)
    assert np.array_equal(climbs, every) and climbs.flags.c_contiguous
    assert 0 < Counted.asked < 0.9 * q.size // 3


def test_valley_plans_on_its_line_steps_and_refuses_bad_ones(scene_pair):
    with pytest.raises(InputError, match="line_steps"):
        ValleyAttack(line_steps=0)
    with pytest.raises(InputError, match="line_steps"):
        ValleyAttack(line_steps=2.5)
    att = ValleyAttack(queries=3, line_steps=4)
    assert att.settings()["line_steps"] == 4
    p_map = _street()[0][::3]
    index = MapIndex(*_street())
    D = np.array([2.0, 0.0, 0.0])
    coarse = valley_displacement(p_map, np.eye(3), D, index, 0.6, COST, steps=4)
    assert np.linalg.norm(coarse, axis=1).max() <= 0.6 * (1 + 1e-12)
    # the plan is made on 4 steps: it differs from the 8-step one (the default) on some points
    fine = valley_displacement(p_map, np.eye(3), D, index, 0.6, COST)
    assert np.any(np.abs(coarse - fine) > 1e-9)
    out = att.run(scene_pair, LAM, oracle=QueryOracle.prepared(PointToPointICP("lidar"), scene_pair),
                  generator=0)
    assert out.extra["queries"].tolist() == [3, 3]
    assert (out.scans.to(torch.float64) - scene_pair.scans).norm(dim=-1).max() <= LAM * (1 + 1e-6)


def test_valley_keeps_the_budget_spends_its_queries_and_leads_farther_than_spoof(scene_pair):
    batch = scene_pair
    target = PointToPointICP("lidar")
    o, o_spoof = QueryOracle.prepared(target, batch), QueryOracle.prepared(target, batch)
    out = ValleyAttack(queries=12).run(batch, LAM, oracle=o, generator=0)
    moved = (out.scans.to(torch.float64) - batch.scans).norm(dim=-1)
    assert moved.max().item() <= LAM * (1 + 1e-6) and out.stats["frac_over_budget"].max() == 0
    assert out.extra["queries"].tolist() == [12, 12]
    err = o.errors(out.scans)  # the recorded error is the target's on the returned scans
    assert np.allclose(err, out.extra["spoof_err"].numpy(), rtol=1e-9, atol=0.0)
    spoof = SpoofAttack(queries=12).run(batch, LAM, oracle=o_spoof, generator=0)
    uni = o.errors(UniformTranslationAttack().run(batch, LAM, generator=0).scans)
    assert err.mean() > 1.1 * spoof.extra["spoof_err"].numpy().mean()
    assert np.all(err > 2 * uni)
