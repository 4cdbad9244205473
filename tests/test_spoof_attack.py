"""The ``spoof`` attack: a scan made to agree with the map at a wrong pose.

What it shows: the displacement puts every point that can reach the map at the shifted pose
exactly onto a map point, and moves the others by exactly lambda towards it (in the map frame of a
rotated true pose); the attack keeps the budget, spends exactly its queries, and leads point-to-point
ICPs (differentiable and KISS-ICP) well beyond the uniform translation; the heading screen ranks a
street's own direction first; as ensemble members spoof and valley give exactly their own rows.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from icpbench.attacks.ensemble import MEMBERS, VALLEY_LINE_STEPS, EnsembleAttack, column
from icpbench.attacks.spoof import SpoofAttack, misfit, spoofed_displacement
from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.attacks.valley import ValleyAttack
from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.targets.kiss import KissICPTarget
from icpbench.targets.oracle import QueryOracle
from icpbench.targets.p2point import PointToPointICP

torch.set_num_threads(1)
LAM = 0.5


def _street() -> np.ndarray:
    """A wall along x (y = 2) and a cross wall (x = 5), 0.25 m grids, map frame."""
    g = np.arange(-10.0, 10.001, 0.25)
    h = np.arange(0.0, 2.001, 0.25)
    wall = np.array([(x, 2.0, z) for x in g for z in h])
    cross = np.array([(5.0, y, z) for y in np.arange(-2.0, 1.76, 0.25) for z in h])
    return np.concatenate([wall, cross])


@pytest.mark.parametrize("shift", [0.5, 3.0])
def test_spoofed_points_lie_on_the_map_at_the_shifted_pose_or_move_lambda_towards_it(shift):
    m = _street()
    index = MapIndex(m)
    yaw = math.radians(30.0)
    R = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0],
                  [0.0, 0.0, 1.0]])
    t = np.array([1.0, -2.0, 0.5])
    p_map = m[::3]  # scan points at the true pose
    scan = (p_map - t) @ R  # sensor frame: R^T (p - t)
    D = np.array([shift, 0.0, 0.0])
    lam = 1.0
    delta = spoofed_displacement(p_map, R, D, index, lam)
    norm = np.linalg.norm(delta, axis=1)
    assert norm.max() <= lam * (1 + 1e-12)
    moved = (scan + delta) @ R.T + t + D  # the attacked scan at the shifted pose, map frame
    dist, _ = index.query(moved)
    on_wall = (p_map[:, 1] == 2.0) & (p_map[:, 0] + shift <= 10.0)  # not slid off its end
    # the wall slides along D: every wall point lies on a map point at the shifted pose
    assert dist[on_wall].max() < 1e-9
    cross = (p_map[:, 0] == 5.0) & (p_map[:, 1] <= -1.25)  # the cross wall is their nearest
    if shift <= lam:
        assert dist[cross].max() < 1e-9 and np.allclose(norm[cross], shift)
    else:  # out of reach: lambda towards the cross wall, which stays shift - lambda away
        np.testing.assert_allclose(norm[cross], lam)
        np.testing.assert_allclose(dist[cross], shift - lam, atol=1e-9)


def test_the_misfit_screen_ranks_the_streets_own_direction_first():
    """Along the wall the whole wall can be put on the map at the shifted pose; across it it
    cannot, so the misfit is smallest near the street's direction (+-x) and largest across."""
    m = _street()
    index = MapIndex(m)
    p_map = m[::3]
    lam = 1.0
    heads = np.radians(np.arange(0.0, 360.0, 22.5))
    bad = np.array([misfit(p_map, 2 * lam * np.array([math.cos(h), math.sin(h), 0.0]), index, lam)
                    for h in heads])
    assert np.argmin(bad) in (15, 0, 1, 7, 8, 9)  # within 22.5 degrees of the street (+-x)
    assert np.argmax(bad) in (4, 12)  # across it (+-y): the wall cannot follow
    assert bad.min() < 0.5 * np.median(bad)
    assert misfit(p_map, np.zeros(3), index, lam) == 0.0  # every point is on the map already
    # the sweep queries the `directions` best of the screened fan
    assert SpoofAttack(directions=2, screen=16).screen == 16
    assert SpoofAttack(directions=8, screen=4).screen == 0  # a screen no wider than the sweep: none


@pytest.mark.parametrize("target", [PointToPointICP("lidar"), KissICPTarget("lidar")],
                         ids=["p2point", "kiss-icp"])
def test_spoof_keeps_the_budget_spends_its_queries_and_beats_the_uniform_translation(
        scene_pair, target):
    batch = scene_pair
    o = QueryOracle.prepared(target, batch)
    out = SpoofAttack(queries=12).run(batch, LAM, oracle=o, generator=0)
    assert float(out.stats["frac_over_budget"].max()) == 0.0
    d = torch.linalg.norm(out.scans.to(torch.float64) - batch.scans, dim=-1)
    assert float(d.max()) <= LAM * (1 + 1e-6)
    np.testing.assert_array_equal(out.extra["queries"].numpy(), [12, 12])
    err = o.errors(out.scans)
    np.testing.assert_allclose(err, out.extra["spoof_err"].numpy(), rtol=1e-9)
    uni = o.errors(UniformTranslationAttack().run(batch, LAM, generator=0).scans)
    # the target follows the spoofed pose well beyond lambda (measured: 2.2-2.6x uniform)
    assert np.all(err > 1.8 * uni) and np.all(err > 1.8 * LAM)
    assert np.all(out.extra["spoof_offset_m"].numpy() >= 2 * LAM)


def test_spoof_rejects_bad_settings_and_needs_an_oracle(scene_pair):
    batch = scene_pair
    for bad in ({"queries": 0}, {"directions": 0}, {"queries": 2.5}):
        with pytest.raises(InputError):
            SpoofAttack(**bad)
    with pytest.raises(InputError, match="oracle"):
        SpoofAttack().run(batch, LAM, generator=0)


def test_the_ensembles_spoof_and_valley_members_give_their_own_rows(scene_pair):
    """Both start from the clean scan with the seed they have alone, so the ensemble records
    exactly their own errors, keeps the largest and spends exactly their queries."""
    batch = scene_pair
    target = PointToPointICP("lidar")
    ens = EnsembleAttack(members="uniform,spoof,valley", spoof_queries=6, valley_queries=4)
    assert ens.settings()["members"] == ["uniform", "spoof", "valley"]
    o_ens, o_spoof, o_valley = (QueryOracle.prepared(target, batch) for _ in range(3))
    out = ens.run(batch, LAM, surrogate=None, generator=0, oracle=o_ens)
    spoof = SpoofAttack(queries=6).run(batch, LAM, generator=0, oracle=o_spoof)
    valley = ValleyAttack(queries=4, line_steps=VALLEY_LINE_STEPS).run(batch, LAM, generator=0,
                                                                      oracle=o_valley)
    np.testing.assert_allclose(out.extra[column("spoof")].numpy(),
                               spoof.extra["spoof_err"].numpy(), rtol=1e-9)
    np.testing.assert_allclose(out.extra[column("valley")].numpy(),
                               valley.extra["spoof_err"].numpy(), rtol=1e-9)
    final = QueryOracle.prepared(target, batch).errors(out.scans)
    recorded = np.stack([out.extra[column(m)].numpy() for m in ("uniform", "spoof", "valley")])
    np.testing.assert_allclose(final, recorded.max(axis=0), rtol=1e-9)
    winner = out.extra["winner"].numpy().astype(int)
    assert set(winner) <= {MEMBERS.index(m) for m in ("uniform", "spoof", "valley")}
    assert (winner != MEMBERS.index("uniform")).any()  # spoofing beats the translation here
    np.testing.assert_array_equal(out.extra["queries"].numpy(), [1 + 6 + 4] * len(batch))
