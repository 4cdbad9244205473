"""The one-step worst case of point-to-plane, point-to-point and GICP costs
(icpbench.core.cost_sensitivity).

What they show: (a) the closed form equals a brute-force maximum of real Gauss-Newton steps over
per-point displacement directions, for every cost; (b) for point-to-plane it is the sector attack's
worst case; (c) the direction grid finds the horizontal maximum of a dense grid; (d) a point-to-point
cost is first-order robust (one-step amplification near 1) where point-to-plane is not.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from icpbench.core import cost_sensitivity as cs
from icpbench.core import sector_math as sector
from icpbench.core.mapindex import MapIndex
from icpbench.datasets.synthetic_scene import scene_sample


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    th = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(th), r * np.sin(th), z], 1)


def _gn_step(q: np.ndarray, m: np.ndarray, W: np.ndarray) -> np.ndarray:
    """One damped Gauss-Newton step (P, 6) of sum r^T W r for point sets q (P, n, 3), written
    independently of the module (Jacobian rebuilt from the displaced points)."""
    P, n, _ = q.shape
    J = np.zeros((P, n, 3, 6))
    J[..., :3] = np.eye(3)
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    # -[q]x
    J[..., 0, 4], J[..., 0, 5] = -z, y
    J[..., 1, 3], J[..., 1, 5] = z, -x
    J[..., 2, 3], J[..., 2, 4] = -y, x
    JtW = np.einsum("pnai,nab->pnib", J, W)
    H = np.einsum("pnib,pnbj->pij", JtW, J)
    g = np.einsum("pnib,pnb->pi", JtW, q - m)
    lam = cs.DAMPING * np.trace(H, axis1=1, axis2=2) / 6 + cs.EPS
    return -np.linalg.solve(H + lam[:, None, None] * np.eye(6), g[..., None])[..., 0]


def _weights(kind: str, rng: np.random.Generator, n: int) -> np.ndarray:
    if kind == "point":
        return np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    if kind == "plane":
        nrm = rng.normal(size=(n, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        return nrm[:, :, None] * nrm[:, None, :]
    A = rng.normal(size=(n, 3, 3))
    return np.einsum("nij,nkj->nik", A, A) + 0.05 * np.eye(3)  # GICP: symmetric positive definite


# ------------------------------------------------------------------------------------------------
# (a) closed form == brute force over displacement directions, through real GN steps
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind,seed", [("point", 0), ("gicp", 1), ("plane", 2), ("gicp", 3)])
def test_closed_form_equals_brute_force(kind, seed):
    rng = np.random.default_rng(seed)
    n, moved, lam = 24, [3, 11, 17], 1e-4
    q = rng.uniform(-15, 15, (n, 3)) * np.array([1.0, 1.0, 0.3])
    W = _weights(kind, rng, n)
    m = q.copy()  # correspondences at zero residual: the clean step is 0
    S = cs.sensitivities(q, W)
    u = np.zeros(6)
    u[:2] = rng.normal(size=2)
    u /= np.linalg.norm(u)
    closed = lam * sum(np.linalg.norm(S[i].T @ u) for i in moved)
    lin = cs.LinearisedCost(index=np.arange(n), S=S, R=np.eye(3))
    best_dirs = lin.displacement(u, 1.0)[moved]  # the closed form's maximiser
    dirs = np.concatenate([_fibonacci_sphere(24), best_dirs])  # (27, 3) candidates per point
    combos = np.array(list(itertools.product(range(dirs.shape[0]), repeat=len(moved))))
    D = np.zeros((combos.shape[0], n, 3))
    for j, i in enumerate(moved):
        D[:, i] = lam * dirs[combos[:, j]]
    vals = _gn_step(q[None] + D, m, W) @ u
    assert vals.max() == pytest.approx(closed, rel=1e-3)
    # the maximum is reached by the closed form's directions, and nothing beats it
    k = int(np.argmax(vals))
    assert np.all(combos[k] >= 24) or vals.max() <= closed * (1 + 1e-3)
    assert np.all(vals <= closed * (1 + 1e-3))


# ------------------------------------------------------------------------------------------------
# (b) point-to-plane: the sector attack's worst case; (c) the direction grid; (d) amplification
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def scene():
    s = scene_sample(n_scan=1500, n_map=15000, seed=2)
    return s, MapIndex(s.map, s.map_normals)


def test_plane_cost_is_the_sector_worst_case(scene):
    s, m = scene
    scan = s.scan.astype(np.float64)
    lin = cs.linearise(scan, s.T_gt, m, cs.CostSpec("plane", 5.0, None))
    wc = sector.analyse(scan, s.T_gt, m, d_max=5.0).worst_case(1.0)
    for j in (0, 1):
        u = np.zeros(6)
        u[j] = 1.0
        assert lin.value(u) == pytest.approx(wc[j], rel=1e-7)  # same model; solves differ


@pytest.mark.parametrize("kind", ["plane", "point", "gicp"])
def test_direction_grid_finds_the_dense_maximum(scene, kind):
    s, m = scene
    lin = cs.linearise(s.scan.astype(np.float64), s.T_gt, m, cs.CostSpec(kind, 5.0, 1.0))
    u, val = lin.worst_xy(180)
    th = np.linspace(0, np.pi, 3600, endpoint=False)
    dense = max(lin.value(np.array([np.cos(t), np.sin(t), 0, 0, 0, 0])) for t in th[::10])
    assert val >= dense * (1 - 1e-3)
    assert val == pytest.approx(lin.value(u))
    d = lin.displacement(u, 0.7)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1)[np.linalg.norm(d, axis=1) > 0], 0.7)


def test_point_to_point_is_first_order_robust(scene):
    """One-step amplification (worst change of the horizontal estimate per metre of budget):
    point-to-point stays near 1 (every point can only drag the scan along), point-to-plane
    exceeds it (walls seen at grazing angles lever the estimate)."""
    s, m = scene
    scan = s.scan.astype(np.float64)
    amp = {k: cs.linearise(scan, s.T_gt, m, cs.CostSpec(k, 5.0, None)).worst_xy()[1]
           for k in ("point", "plane")}
    assert 0.99 <= amp["point"] < 1.3
    assert amp["plane"] > 1.5 * amp["point"]
