"""Compiled forward pass of point-to-point ICP, to answer query attacks' registrations sooner.

The query attacks (``spoof``, ``valley``, the search) register thousands of candidate scans per
scan with the evaluated target; for ``p2point`` and KISS-ICP's replica those registrations run
:func:`icpbench.targets.icp.icp` in PyTorch, where each iteration is some forty small tensor
operations plus the KD-tree search. Measured on attacked ``lidar-sim`` scans (2026-11-29, one
thread): about 4 ms of each iteration was tensor overhead beside 2.6 ms of tree search, so the
tree was not the larger part. This module runs the *same* iteration (the same correspondences,
weights, normal equations, damped solve, left update and stopping test, in float64) with the
per-point work compiled by Numba, one pass over the points per step, and returns what ``icp``
returns to rounding (poses equal to about 1e-15 m, the same iteration counts; tests compare).

Correspondences. Each point keeps its ``K`` nearest map points (:data:`CANDIDATES`) from the
last tree search at ``ref`` and the K-th distance ``r_K``: every other map point is at least
``r_K`` from ``ref``, so at least ``r_K - |q - ref|`` from the point's position q. The nearest
listed point is therefore the exact nearest neighbour while it is closer than that, and the point
needs no tree search; when every listed point and that bound lie beyond the correspondence gate,
the point has no correspondence either way. Points the lists cannot decide are searched again
(about 15% per iteration on attacked scans, against about half with the two-neighbour slack of
``icp``'s cache, whose lookups are cheaper: 2x fewer tree seconds in all, measured). A map with
a neighbour rule of its own (KISS-ICP's replica map,
:class:`~icpbench.targets.kiss_replica.KissReplicaMap`: KISS's 27-voxel search) states how near
its rule is the exact neighbour (``MapIndex.exact_within``, one voxel); the lists answer only
nearer than that. The other points take that rule itself, compiled here (:func:`_voxel_rows`,
for a map that names its voxel search, ``MapIndex.voxel_search``), or else the map's
``nearest2``, with the two-distance slack of :class:`icpbench.targets.icp._Correspondences`.
Such a point that moves past its slack is not searched again while a lower bound of its exact
distance (the last search's, less the way it moved since) keeps it a voxel away: the assignment
runs the voxel rule for it in place (:func:`_assign`). On the query registrations of an attacked
``town`` scan that left 0.6x the tree searches and took 0.75x the time (2026-11-30).

Only forward passes: no gradient, no ``nn_reuse_m``, the hard gate, float64 scans. The class
:class:`CompiledPointICP` wraps a differentiable point-to-point target as its exact replica
(``Target.exact_replica``), so only queries go through here; every reported row is still the
target's own registration. The differentiable point-to-point ICP itself takes its rows from
:class:`NearestRows` too (``icp``'s correspondence search with ``lists``: the same rows, fewer
searches), which is what the gradient attacks' surrogate registrations gain.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numba
import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Registration
from icpbench.targets.base import Target
from icpbench.targets.icp import ICPConfig, health

#: Nearest map points kept per scan point (measured on attacked lidar-sim scans against
#: ``p2point``'s own pass: 4 -> 1.81x, 8 -> 1.97x, 16 -> 1.95x, 32 -> 1.83x faster).
CANDIDATES = 8
#: Relative margin of the far rule (as ``icp``'s cache: far above the rounding of a distance).
_FAR_MARGIN = 1e-4
#: Absolute margin (metres) on every certificate (as ``icp``'s cache).
_MARGIN_M = 1e-9
_KERNELS = {"none": 0, "cauchy": 1, "geman_mcclure": 2, "huber": 3}
#: The voxel arguments of :func:`_assign` and :func:`_voxel_rows` (``keys``, ``start``, ``count``,
#: ``order``, ``stored``, ``voxel``) for a map without KISS's voxel rule (``voxel`` 0: off).
NO_VOXELS = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
             np.zeros(0, np.int64), np.zeros((0, 3)), 0.0)


def voxel_arguments(v: Any) -> tuple[Any, ...]:
    """The voxel arguments of :func:`_assign` and :func:`_voxel_rows` for KISS's voxel map ``v``
    (:class:`~icpbench.targets.kiss.VoxelNeighbours`)."""
    return (v.keys, v.start, v.count, v.order, v.stored, float(v.voxel_size))


@numba.njit(cache=True)
def _transform(P: np.ndarray, R: np.ndarray, t: np.ndarray, i: int) -> tuple[float, float, float]:
    """Map-frame position of scan point i of P (N, 3) at the pose (R (3, 3), t (3,))."""
    x, y, z = P[i, 0], P[i, 1], P[i, 2]
    return (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0],
            R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1],
            R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2])


@numba.njit(cache=True)
def _assign(P: np.ndarray, finite: np.ndarray, R: np.ndarray, t: np.ndarray, ref: np.ndarray,
            cand: np.ndarray, r_k: np.ndarray, by_slack: np.ndarray, slack2: np.ndarray,
            table: np.ndarray, bound: float, exact_within: float, idx: np.ndarray,
            need: np.ndarray, low: np.ndarray, keys: np.ndarray, start: np.ndarray,
            count: np.ndarray, order: np.ndarray, stored: np.ndarray, voxel: float,
            Q: np.ndarray | None = None) -> int:
    """Set idx (N,) where a point's row is decided without a search, else need (N,) True;
    returns the number of points to search again (module docstring). The points are P (N, 3)
    at the pose (R, t), or, if given, at the map-frame positions Q (3, N) (as rows of
    coordinates).

    A point ``by_slack`` keeps its row while it moved less than its slack (``slack2``: squared;
    0: ask again). The others take the nearest of their K listed map points ``cand`` (N, K) when
    it is nearer than every unlisted one (at least ``r_k - moved``) and than ``exact_within``
    (where the map's rule is the exact neighbour), or when all of them lie beyond the gate
    ``bound``.

    With KISS's voxel map (``voxel`` > 0: its ``keys``, ``start``, ``count``, ``order`` and
    ``stored``, as :func:`_voxel_rows` takes them), a point on the map's own rule that moved past
    its slack is answered here, without a tree search, while ``low`` (N,), a lower bound of its
    exact nearest distance at ``ref``, less the way it moved, still puts it a voxel
    (``exact_within``) or more from the map: there the map's rule is KISS's voxel rule
    (:func:`_voxel_nearest`), or beyond the gate no row counts. The rows are those of the search
    (tests compare); ``low`` then becomes the larger of that bound and the one the 27 voxels give
    (every map point outside them is at least a voxel plus the distance to the voxel's faces
    away)."""
    N, K, M = P.shape[0], cand.shape[1], table.shape[0]
    far = bound * (1.0 + _FAR_MARGIN)
    n_need = 0
    for i in range(N):
        need[i] = False
        if not finite[i]:
            continue
        if Q is None:
            qx, qy, qz = _transform(P, R, t, i)
        else:
            qx, qy, qz = Q[0, i], Q[1, i], Q[2, i]
        dx, dy, dz = qx - ref[i, 0], qy - ref[i, 1], qz - ref[i, 2]
        moved2 = dx * dx + dy * dy + dz * dz
        if by_slack[i]:
            if moved2 < slack2[i]:
                continue
            lo = low[i] - math.sqrt(moved2) - _MARGIN_M  # NaN (never asked): search
            if voxel > 0.0 and lo >= exact_within:
                ref[i, 0], ref[i, 1], ref[i, 2] = qx, qy, qz
                if lo > bound:  # the far rule: the row (whichever) stays gated
                    slack = lo - far
                    slack2[i] = slack * slack if slack > 0.0 else 0.0
                    low[i] = lo
                    continue
                best, second, at, wall = _voxel_nearest(qx, qy, qz, keys, start, count, stored,
                                                        voxel)
                idx[i] = order[at] if at >= 0 else stored.shape[0]
                slack2[i] = _voxel_slack2(best, second, wall)
                low[i] = max(lo, min(math.sqrt(best), voxel + wall))
                continue
            need[i] = True
            n_need += 1
            continue
        room = r_k[i] - math.sqrt(moved2)  # every unlisted map point is at least this far
        if not room > 0.0:
            need[i] = True
            n_need += 1
            continue
        best, best_j = np.inf, M
        for j in range(K):
            c = cand[i, j]
            if c >= M:
                break
            ex, ey, ez = qx - table[c, 0], qy - table[c, 1], qz - table[c, 2]
            d2 = ex * ex + ey * ey + ez * ez
            if d2 < best:
                best, best_j = d2, c
        d = math.sqrt(best)
        if (d < room - _MARGIN_M and d < exact_within - _MARGIN_M) or (d >= far and room >= far):
            idx[i] = best_j
        else:
            need[i] = True
            n_need += 1
    return n_need


@numba.njit(cache=True)
def _normal_equations(P: np.ndarray, finite: np.ndarray, R: np.ndarray, t: np.ndarray,
                      idx: np.ndarray, table: np.ndarray, bound2: float, kernel: int, c2: float
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """IRLS point-to-point normal equations at the pose (R, t): H (6, 6), g (6,) and the inlier
    count, the same sums as :func:`icpbench.targets.icp._point_normal_equations` (rows
    ``[rho, phi]``, residual ``e = q - m``, hard gate ``|e|^2 < bound2``, robust weight
    ``kernel`` of scale ``c2 = c^2``)."""
    M = table.shape[0]
    sw = s0 = s1 = s2 = sqq = 0.0
    A = np.zeros((3, 3))
    g = np.zeros(6)
    n_in = 0
    for i in range(P.shape[0]):
        c = idx[i]
        if not finite[i] or c >= M:
            continue
        qx, qy, qz = _transform(P, R, t, i)
        ex, ey, ez = qx - table[c, 0], qy - table[c, 1], qz - table[c, 2]
        d2 = ex * ex + ey * ey + ez * ez
        if not d2 < bound2:
            continue
        if kernel == 1:
            w = 1.0 / (1.0 + d2 / c2)
        elif kernel == 2:
            u = 1.0 / (1.0 + d2 / c2)
            w = u * u
        elif kernel == 3:
            w = math.sqrt(c2) / math.sqrt(d2) if d2 > c2 else 1.0
        else:
            w = 1.0
        if w > 0.0:
            n_in += 1
        wx, wy, wz = w * qx, w * qy, w * qz
        sw += w
        s0 += wx
        s1 += wy
        s2 += wz
        sqq += wx * qx + wy * qy + wz * qz
        A[0, 0] += wx * qx
        A[0, 1] += wx * qy
        A[0, 2] += wx * qz
        A[1, 1] += wy * qy
        A[1, 2] += wy * qz
        A[2, 2] += wz * qz
        g[0] += w * ex
        g[1] += w * ey
        g[2] += w * ez
        g[3] += wy * ez - wz * ey
        g[4] += wz * ex - wx * ez
        g[5] += wx * ey - wy * ex
    # H = [[sw I, -[s]x], [[s]x, sqq I - A]] with s = (s0, s1, s2) the weighted point sum
    Sx = np.array([[0.0, -s2, s1], [s2, 0.0, -s0], [-s1, s0, 0.0]])
    H = np.zeros((6, 6))
    for a in range(3):
        H[a, a] = sw
        for b in range(3):
            H[3 + a, b] = Sx[a, b]
            H[a, 3 + b] = -Sx[a, b]
            H[3 + a, 3 + b] = (sqq if a == b else 0.0) - (A[a, b] if a <= b else A[b, a])
    return H, g, n_in


def _left_update(delta: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``exp(delta) T`` for a twist delta (6,) = [rho, phi] and T = (R, t) (as
    :func:`icpbench.core.se3.se3_exp`, including its small-angle branches below 1e-4 rad)."""
    phi = delta[3:]
    sq = float(phi @ phi)
    if sq < 1e-8:
        a, b, c = 1.0 - sq / 6.0, 0.5 - sq / 24.0, 1.0 / 6.0 - sq / 120.0
    else:
        th = math.sqrt(sq)
        a, b, c = math.sin(th) / th, (1.0 - math.cos(th)) / sq, (th - math.sin(th)) / th**3
    x, y, z = phi
    Kx = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    KK = Kx @ Kx
    dR = np.eye(3) + a * Kx + b * KK
    dt = (np.eye(3) + b * Kx + c * KK) @ delta[:3]
    return dR @ R, dR @ t + dt


def register_point(scan: np.ndarray, map_index: MapIndex, T_init: np.ndarray, cfg: ICPConfig
                   ) -> tuple[np.ndarray, bool, int, int, np.ndarray]:
    """One point-to-point ICP registration, the iteration of :func:`icpbench.targets.icp.icp`.

    Args:
        scan: (N, 3) float64 scan points, sensor frame, metres (non-finite points are ignored).
        map_index: the map (map frame); candidate lists where its ``nearest2`` is the exact
            neighbour (``exact_within``), its own ``nearest2`` with the slack elsewhere.
        T_init: (4, 4) initial scan->map transform.
        cfg: the ICP settings (hard gate ``d_max``, no ``nn_reuse_m``).

    Returns:
        (T (4, 4) float64, converged, iterations, inliers at the last iteration, the last
        normal-equation matrix H (6, 6)).
    """
    if cfg.soft_dmax or cfg.nn_reuse_m != 0:
        raise InputError("the compiled point-to-point pass has no soft gate and no nn_reuse_m")
    finite = np.isfinite(scan).all(axis=1)
    P = np.ascontiguousarray(np.where(finite[:, None], scan, 0.0), dtype=np.float64)
    R, t = T_init[:3, :3].astype(np.float64), T_init[:3, 3].astype(np.float64)
    bound = np.inf if cfg.d_max is None else float(cfg.d_max)
    c2 = np.inf if cfg.cauchy_c is None or cfg.kernel == "none" else float(cfg.cauchy_c) ** 2
    kernel = _KERNELS[cfg.kernel] if np.isfinite(c2) else 0
    rows = NearestRows(map_index, P, finite, bound)
    H = np.zeros((6, 6))
    n_in, converged, iterations = 0, False, cfg.max_iterations
    eye6 = np.eye(6)
    for it in range(cfg.max_iterations):
        idx = rows.update(R, t)
        H, g, n_in = _normal_equations(P, finite, R, t, idx, rows.table, bound * bound,
                                       kernel, c2)
        lam = cfg.damping * np.trace(H) / 6.0 + 1e-12
        delta = -np.linalg.solve(H + lam * eye6, g)
        R, t = _left_update(delta, R, t)
        if np.linalg.norm(delta) < cfg.tol:
            converged, iterations = True, it + 1
            break
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    T[3] = T_init[3]
    return T, converged, iterations, n_in, H


class NearestRows:
    """The map row of every scan point across ICP iterations (module docstring): candidate lists
    where the map's rule is the exact neighbour, the map's ``nearest2`` with the slack elsewhere.

    Args:
        map_index: the map (map frame).
        P: (N, 3) float64 scan points (non-finite ones zeroed) the poses are applied to.
        finite: (N,) which points count.
        bound: the correspondence gate (metres; inf: none): beyond it a row only needs to be
            known to be too far.
    """

    def __init__(self, map_index: MapIndex, P: np.ndarray, finite: np.ndarray,
                 bound: float) -> None:
        N = P.shape[0]
        self.map_index, self.P, self.finite, self.bound = map_index, P, finite, float(bound)
        self.table = np.ascontiguousarray(map_index.points, dtype=np.float64)
        M = self.table.shape[0]
        self.exact_within = float(map_index.exact_within)
        self.K = min(CANDIDATES, M)
        self.order = np.lexsort(np.floor(P).T[::-1])  # 1 m voxels: coherent tree searches
        self.ref = np.full((N, 3), np.nan)  # where each point was last searched
        self.idx = np.full(N, M, dtype=np.int64)  # its row (M: none)
        self.need = np.zeros(N, dtype=bool)
        self.cand = np.full((N, self.K), M, dtype=np.int64)
        self.r_k = np.full(N, -np.inf)  # every unlisted map point is at least this far from ref
        self.by_slack = np.full(N, not self.exact_within > 0.0)  # rows by the map's own rule
        self.slack2 = np.zeros(N)  # squared distance a point may move with the same row
        # KISS's 27-voxel rule, compiled (_voxel_rows, _assign), where the map has one and lists
        # decide the exact neighbour within a voxel; otherwise the map's own nearest2
        v = map_index.voxel_search if self.exact_within > 0.0 else None
        self.has_voxels = v is not None
        self._voxel_args = (voxel_arguments(v) if v is not None else NO_VOXELS)
        self.low = np.full(N, np.nan)  # a lower bound of the exact nearest distance at ref
        self.searched = 0  # points searched again (for profiling)
        self._eye, self._zero = np.eye(3), np.zeros(3)  # (unused with positions)

    def update(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Rows (N,) int64 (M: none) of the points at the pose (R (3, 3), t (3,))."""
        n_need = _assign(self.P, self.finite, R, t, self.ref, self.cand, self.r_k, self.by_slack,
                         self.slack2, self.table, self.bound, self.exact_within, self.idx,
                         self.need, self.low, *self._voxel_args)
        if n_need:
            sel = self.order[self.need[self.order]]
            self._search(sel, self.P[sel] @ R.T + t)
        return self.idx

    def update_at(self, Q: np.ndarray) -> np.ndarray:
        """Rows (N,) int64 (M: none) of the points at map-frame positions Q (3, N) float64."""
        n_need = _assign(self.P, self.finite, self._eye, self._zero, self.ref, self.cand,
                         self.r_k, self.by_slack, self.slack2, self.table, self.bound,
                         self.exact_within, self.idx, self.need, self.low, *self._voxel_args, Q)
        if n_need:
            sel = self.order[self.need[self.order]]
            self._search(sel, np.ascontiguousarray(Q[:, sel].T))
        return self.idx

    def _search(self, sel: np.ndarray, q: np.ndarray) -> None:
        """Search the points ``sel`` (S,) again at their map-frame positions q (S, 3)."""
        self.ref[sel] = q
        self.searched += len(sel)
        if not self.exact_within > 0.0:  # the map's own rule everywhere
            _search_slack(self.map_index, q, sel, self.bound, self.slack2, self.idx)
            return
        d1 = _search_lists(self.map_index, q, sel, self.K, self.cand, self.r_k, self.idx)
        if self.has_voxels:
            _voxel_rows(q, sel, d1, *self._voxel_args, self.bound, self.exact_within, self.idx,
                        self.slack2, self.by_slack, self.low)
            return
        own = ~(d1 < self.exact_within)  # rows from the map's own rule
        self.by_slack[sel] = own
        if own.any():
            _search_slack(self.map_index, q[own], sel[own], self.bound, self.slack2, self.idx)


def _search_lists(map_index: MapIndex, q: np.ndarray, sel: np.ndarray, K: int,
                  cand: np.ndarray, r_k: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Fresh K-nearest lists of the points ``sel`` at map-frame positions q (S, 3); returns
    their nearest distances (S,) (inf where the tree found nothing)."""
    M = len(map_index)
    rows, d2 = map_index.tree.batch_knn_search(np.ascontiguousarray(q), K,
                                               num_threads=map_index.workers)
    d1 = np.empty(len(sel))
    # "none" comes back as 2**64 - 1, -1 as int64
    _take_lists(np.ascontiguousarray(rows).view(np.int64), np.asarray(d2, dtype=np.float64), sel,
                M, M > K, cand, r_k, idx, d1)
    return d1


@numba.njit(cache=True)
def _take_lists(rows: np.ndarray, d2: np.ndarray, sel: np.ndarray, M: int, partial: bool,
                cand: np.ndarray, r_k: np.ndarray, idx: np.ndarray, d1: np.ndarray) -> None:
    """Store a tree's K-nearest answer, rows (S, K) int64 and squared distances d2 (S, K), as the
    lists of the points ``sel`` (S,): ``cand`` rows (M where none), ``idx`` the nearest, ``r_k``
    the K-th distance, which bounds every unlisted map point (inf when the map has K points or
    fewer, ``partial`` False: all listed; -inf for an incomplete answer: ask again), and ``d1``
    (S,) the nearest distance (inf: none)."""
    K = rows.shape[1]
    for s in range(sel.shape[0]):
        i = sel[s]
        bad = False
        for j in range(K):
            r = rows[s, j]
            bad = r < 0 or r >= M or not np.isfinite(d2[s, j])
            cand[i, j] = M if bad else r
        idx[i] = cand[i, 0]
        if bad:
            r_k[i] = -np.inf
        else:
            r_k[i] = math.sqrt(d2[s, K - 1]) if partial else np.inf
        d1[s] = np.inf if cand[i, 0] == M else math.sqrt(d2[s, 0])


@numba.njit(cache=True, inline="always")
def _voxel_nearest(qx: float, qy: float, qz: float, keys: np.ndarray, start: np.ndarray,
                   count: np.ndarray, stored: np.ndarray, voxel: float
                   ) -> tuple[float, float, int, float]:
    """KISS's neighbour of the map-frame position (qx, qy, qz) (``VoxelHashMap::GetClosestNeighbor``:
    the nearest of the points stored in the 27 voxels around it; on ties the first in
    :class:`~icpbench.targets.kiss.VoxelNeighbours`' order): the squared distances of the nearest
    and second-nearest of those points (inf: none), the nearest's position in ``stored`` (-1:
    none) and the distance (metres) from the position to its voxel's faces.

    The voxel map is :class:`~icpbench.targets.kiss.VoxelNeighbours`': ``keys`` (V,) sorted voxel
    codes, ``start``/``count`` (V,) runs of its ``stored`` (K, 3) points. The three voxels of a
    column share x and y and have consecutive codes, so one binary search finds them."""
    V = keys.shape[0]
    off = 1 << 20  # the voxel code of VoxelNeighbours._codes: (x + off) << 42 | (y + off) << 21 | ...
    best, second, at = np.inf, np.inf, -1
    fx, fy, fz = qx / voxel, qy / voxel, qz / voxel
    vx, vy, vz = math.floor(fx), math.floor(fy), math.floor(fz)
    if max(abs(qx), abs(qy), abs(qz)) < (off - 2) * voxel:  # else no stored point is near
        for a in range(-1, 2):
            for b in range(-1, 2):
                low = ((int(vx) + a + off) << 42) | ((int(vy) + b + off) << 21) \
                    | (int(vz) - 1 + off)
                lo, hi = 0, V
                while lo < hi:  # the first code >= the column's lowest voxel
                    mid = (lo + hi) // 2
                    if keys[mid] < low:
                        lo = mid + 1
                    else:
                        hi = mid
                while lo < V and keys[lo] <= low + 2:
                    for r in range(start[lo], start[lo] + count[lo]):
                        ex, ey, ez = stored[r, 0] - qx, stored[r, 1] - qy, stored[r, 2] - qz
                        e2 = ex * ex + ey * ey + ez * ez
                        if e2 < best:
                            second, best, at = best, e2, r
                        elif e2 < second:
                            second = e2
                    lo += 1
    wall = voxel * min(fx - vx, 1.0 - (fx - vx), fy - vy, 1.0 - (fy - vy),
                       fz - vz, 1.0 - (fz - vz))
    return best, second, at, wall


@numba.njit(cache=True, inline="always")
def _voxel_slack2(best: float, second: float, wall: float) -> float:
    """The squared distance a point may move and keep KISS's neighbour (:func:`_voxel_nearest`'s
    answer): while it keeps its voxel (so the same 27 voxels) and the nearest of their points,
    ``min(distance to the voxel's faces, half the gap to the second)``."""
    gap = 0.5 * (math.sqrt(second) - math.sqrt(best)) if best < np.inf else np.inf
    slack = max(min(wall, gap), 1e-12) - _MARGIN_M
    return slack * slack if slack > 0.0 else 0.0


@numba.njit(cache=True)
def _voxel_rows(q: np.ndarray, sel: np.ndarray, d1: np.ndarray, keys: np.ndarray,
                start: np.ndarray, count: np.ndarray, order: np.ndarray, stored: np.ndarray,
                voxel: float, bound: float, exact_within: float, idx: np.ndarray,
                slack2: np.ndarray, by_slack: np.ndarray, low: np.ndarray) -> None:
    """After a search of the points ``sel`` (S,) at map-frame positions q (S, 3), whose exact
    nearest map point lies ``d1`` (S,) away: those a voxel (``exact_within``) or more away take
    KISS's neighbour (:func:`_voxel_nearest`; ``by_slack`` True, the others False), with a slack
    no looser than :meth:`~icpbench.targets.kiss_replica.KissReplicaMap.nearest2`'s:

    * exact neighbour beyond the gate ``bound``: every row is gated while the point moves less
      than ``d1 - bound (1 + margin)`` (``idx`` keeps the exact neighbour);
    * else the row holds while the point keeps its voxel and its nearest (:func:`_voxel_slack2`).

    ``low`` (N,) takes ``d1`` (:func:`_assign`'s bound). ``order`` (K,) names the map row of each
    ``stored`` point. Replaces :class:`~icpbench.targets.kiss.VoxelNeighbours`' NumPy search, a
    third of KISS-ICP's query time (one ``town`` scan's ensemble, 2026-11-30: 14.6 of 28.8 s of
    registrations).
    """
    K = stored.shape[0]
    far = bound * (1.0 + _FAR_MARGIN)
    for s in range(sel.shape[0]):
        i = sel[s]
        low[i] = d1[s]
        by_slack[i] = not d1[s] < exact_within
        if not by_slack[i]:  # the lists name the exact neighbour
            continue
        if d1[s] > bound:  # the far rule: no row counts, whichever
            slack = d1[s] - far
            slack2[i] = slack * slack if slack > 0.0 else 0.0
            continue
        best, second, at, wall = _voxel_nearest(q[s, 0], q[s, 1], q[s, 2], keys, start, count,
                                                stored, voxel)
        idx[i] = order[at] if at >= 0 else K
        slack2[i] = _voxel_slack2(best, second, wall)


def _search_slack(map_index: MapIndex, q: np.ndarray, sel: np.ndarray, bound: float,
                  slack2: np.ndarray, idx: np.ndarray) -> None:
    """The map's own ``nearest2`` for the points ``sel`` (S, 3), with ``icp``'s slack rule."""
    d1, d2, rows = map_index.nearest2(q)
    idx[sel] = rows
    with np.errstate(invalid="ignore"):
        slack = np.where(d2 > d1, 0.5 * (d2 - d1) - _MARGIN_M, -np.inf)
    if np.isfinite(bound):  # beyond the bound: no weight until it comes this close
        far = np.isfinite(d1) & (d1 > bound)
        slack[far] = np.maximum(slack[far], d1[far] - bound * (1.0 + _FAR_MARGIN))
    slack2[sel] = np.maximum(slack, 0.0) ** 2


class CompiledPointICP(Target):
    """A differentiable point-to-point target's forward pass, compiled (module docstring).

    Args:
        of: the target it answers for (its ``name`` and ``settings`` are reported).
        config: that target's ICP settings (``mode="point"``).
        map_of: the map the target registers against, from a batch's ``MapIndex`` (KISS's
            replica: its thinned voxel map); None: the ``MapIndex`` itself.
    """

    takes_map_index: ClassVar[bool] = True

    def __init__(self, of: Target, config: ICPConfig,
                 map_of: Callable[[MapIndex], MapIndex] | None = None) -> None:
        if config.soft_dmax or config.nn_reuse_m != 0:
            raise InputError(f"{of.name!r} has a soft gate or nn_reuse_m: no compiled pass")
        self.of = of
        self.config = config
        self.map_of = map_of
        self.name = f"{of.name}-compiled"  # type: ignore[misc]

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None = None) -> MapIndex:
        return MapIndex(map_points, map_normals, workers=self.config.kdtree_workers)

    def register(self, scans: torch.Tensor, maps: Sequence[MapIndex],
                 T_init: torch.Tensor) -> Registration:
        """Register scans (B, N, 3), sensor frame, to the batch's maps from T_init (B, 4, 4);
        no gradient. Scans that are not float64 go to the wrapped target (its arithmetic)."""
        if scans.dtype != torch.float64:
            return self.of.register(scans, maps, T_init)
        x, T0 = scans.detach().numpy(), T_init.detach().to(torch.float64).numpy()
        out = [register_point(x[b], self.map_of(m) if self.map_of else m, T0[b], self.config)
               for b, m in enumerate(maps)]
        T = torch.as_tensor(np.stack([o[0] for o in out]))
        converged = torch.tensor([o[1] for o in out])
        n_in = torch.tensor([o[3] for o in out], dtype=torch.long)
        status = health(torch.as_tensor(np.stack([o[4] for o in out])), n_in, converged, T,
                        self.config)
        return Registration(
            T=T,
            converged=converged & torch.tensor([s == "ok" for s in status]),
            iterations=torch.tensor([o[2] for o in out], dtype=torch.long),
            inlier_fraction=n_in.to(torch.float64) / max(scans.shape[1], 1),
            status=status)

    def settings(self) -> dict[str, Any]:
        return {"compiled_forward_of": self.of.name, **self.of.settings()}
