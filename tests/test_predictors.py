"""Cheap danger predictors on scenes whose answer is known: a corridor (translation along its axis
unconstrained) and a closed box room (every direction constrained)."""

import numpy as np
import pytest

from icpbench.analysis.localisability import localisability
from icpbench.analysis.predictors import (
    hessian_conditioning,
    place_predictors,
    point_to_plane_system,
)
from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex

RNG = np.random.default_rng(0)


def planes(spec, n_per_plane=1500, rng=RNG):
    """Points and unit normals on axis-aligned rectangles.

    spec: list of (axis of the normal, offset along it, the half-extents of the two other axes).
    """
    pts, nrm = [], []
    for axis, offset, half in spec:
        uv = rng.uniform(-1.0, 1.0, size=(n_per_plane, 2)) * np.asarray(half)
        p = np.insert(uv, axis, offset, axis=1)
        n = np.zeros(3)
        n[axis] = -np.sign(offset) if offset else 1.0  # facing the sensor at the origin
        pts.append(p)
        nrm.append(np.tile(n, (n_per_plane, 1)))
    return np.vstack(pts), np.vstack(nrm)


# a 60 m corridor along x, 4 m wide, 3 m high: floor, ceiling and two side walls, open ends
CORRIDOR = [(1, -2.0, (30, 1.5)), (1, 2.0, (30, 1.5)), (2, -1.5, (30, 2)), (2, 1.5, (30, 2))]
# a closed 10 x 8 x 3 m room
ROOM = [(0, -5.0, (4, 1.5)), (0, 5.0, (4, 1.5)), (1, -4.0, (5, 1.5)), (1, 4.0, (5, 1.5)),
        (2, -1.5, (5, 4)), (2, 1.5, (5, 4))]


def scene(spec):
    pts, nrm = planes(spec)
    scan = pts[RNG.choice(len(pts), 2000, replace=False)] + RNG.normal(0, 0.005, (2000, 3))
    return scan, MapIndex(pts, nrm)


CORRIDOR_SCAN, CORRIDOR_MAP = scene(CORRIDOR)
ROOM_SCAN, ROOM_MAP = scene(ROOM)
T_ID = np.eye(4)


def test_corridor_axis_is_the_unconstrained_direction():
    p = place_predictors(CORRIDOR_SCAN, T_ID, CORRIDOR_MAP)
    sysm = point_to_plane_system(CORRIDOR_SCAN, T_ID, CORRIDOR_MAP, d_max=5.0, cauchy_c=1.0)
    loc = localisability(sysm.points, sysm.normals, sysm.weights)
    # nothing faces along x: the x localisability and the smallest eigenvalue vanish
    assert loc.along([1, 0, 0]) == 0.0
    assert abs(p["weak_dir_x"]) > 0.999
    assert p["loc_trans_min"] == 0.0
    assert p["hessian_min_eig"] < 1e-9
    # y and z are held by ~half the correspondences each (two walls / floor and ceiling)
    assert loc.along([0, 1, 0]) > 0.4 * len(sysm.weights)
    assert loc.along([0, 0, 1]) > 0.4 * len(sysm.weights)
    # the analytic sector estimate is blind to it: faults along the normals (none has an x part)
    # cannot move the linearised pose along x, so it sees only the lateral worst case, about lambda
    assert p["sector_xy"] == pytest.approx(1.0, abs=0.05)
    assert place_predictors(CORRIDOR_SCAN, T_ID, CORRIDOR_MAP, budget_m=2.0)["sector_xy"] == \
        pytest.approx(2 * p["sector_xy"])
    assert p["hessian_cond"] > 1e12


def test_box_room_is_well_conditioned():
    p = place_predictors(ROOM_SCAN, T_ID, ROOM_MAP)
    k = 2000 * p["n_assoc"]
    assert p["n_assoc"] > 0.99
    assert p["loc_trans_min"] > 0.15 * k  # each axis faced by two of the six planes
    assert p["loc_rot_min"] > 0.05 * k
    assert p["hessian_min_eig"] > 0.02 * k
    assert p["hessian_cond"] < 50
    # the worst faults push every point of the two x (or y) walls by lambda: the room moves lambda
    assert p["sector_xy"] == pytest.approx(1.0, abs=0.1)


def test_room_is_safer_than_corridor_on_every_predictor():
    c = place_predictors(CORRIDOR_SCAN, T_ID, CORRIDOR_MAP)
    r = place_predictors(ROOM_SCAN, T_ID, ROOM_MAP)
    assert c["hessian_cond"] > 1e6 * r["hessian_cond"]
    assert c["hessian_min_eig"] < 1e-6 * r["hessian_min_eig"]
    assert c["loc_trans_min"] < 1e-3 * r["loc_trans_min"]


def test_cauchy_weights_follow_the_residuals():
    # a point 1 m off its plane (residual = c) gets weight 1/2
    scan = np.vstack([ROOM_SCAN[:50], [[0.0, 0.0, -0.5]]])  # 1 m above the floor at z = -1.5
    sysm = point_to_plane_system(scan, T_ID, ROOM_MAP, d_max=5.0, cauchy_c=1.0)
    floor_pt = np.argmin(np.linalg.norm(sysm.points - [0, 0, -0.5], axis=1))
    assert sysm.residuals[floor_pt] == pytest.approx(1.0, abs=0.02)
    assert sysm.weights[floor_pt] == pytest.approx(0.5, abs=0.01)
    lo, cond = hessian_conditioning(sysm)
    assert lo > 0 and np.isfinite(cond)


def test_bad_input_raises():
    with pytest.raises(InputError, match="at least 6"):
        point_to_plane_system(ROOM_SCAN + 100.0, T_ID, ROOM_MAP, d_max=5.0, cauchy_c=1.0)
    with pytest.raises(InputError):
        localisability(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(InputError, match="kappa"):
        localisability(np.ones((4, 3)), np.ones((4, 3)), kappa=2.0)
