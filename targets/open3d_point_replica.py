"""Open3D's point-to-point ``registration_icp`` replayed step by step, compiled, to answer queries.

Open3D's legacy ICP (Zhou, Park and Koltun, "Open3D: A Modern Library for 3D Data Processing",
2018; ``RegistrationICP`` in ``pipelines/registration/Registration.cpp``) with the
point-to-point estimator does, on one thread:

1. move a copy of the scan by the initial pose (unless it is the identity) and find, for every
   point, the nearest map point closer than ``max_correspondence_distance`` (a hybrid radius
   search for one neighbour); fitness = matches / points, inlier RMSE = the root mean square of
   their distances;
2. up to ``max_iteration`` times: the closed-form rigid fit of the matched pairs (Umeyama, "Least
   squares estimation of transformation parameters between two point patterns", TPAMI 1991,
   without scaling), applied to the pose (left) *and* to the moved copy; new matches; stop when
   fitness and RMSE both changed by less than their thresholds.

:class:`Open3DPointReplica` runs exactly that, with the matches from the compiled candidate lists
of :class:`~icpbench.targets.point_forward.NearestRows` (the exact nearest neighbour, gated as
Open3D gates) and the per-point sums in Numba, then the target's own convergence proxy and
health check (:class:`~icpbench.targets.open3d_icp.Open3DICP`). An earlier replica in NumPy
gave Open3D's poses to 6e-14 m but was no faster than Open3D (14.3 s against 13.1 s of CPU on 12
queries, 2026-11-29): the compiled lists are what make it worth having. It answers the
``open3d`` point-to-point target's queries (``Target.exact_replica``); rows stay Open3D's own.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numba
import numpy as np
import torch

from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Registration
from icpbench.targets.blackbox import OneResult, increment_norm, point_to_point_hessian
from icpbench.targets.open3d_icp import RELATIVE_FITNESS, Open3DICP
from icpbench.targets.point_forward import NearestRows

#: Eigen's ``isIdentity`` precision, which Open3D's ``RegistrationICP`` uses on the initial pose.
_IDENTITY_PRECISION = 1e-12


@numba.njit(cache=True)
def _move(P: np.ndarray, T: np.ndarray) -> None:
    """Apply T (4, 4) to the points P (N, 3) in place (as ``PointCloud::Transform``)."""
    for i in range(P.shape[0]):
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        P[i, 0] = T[0, 0] * x + T[0, 1] * y + T[0, 2] * z + T[0, 3]
        P[i, 1] = T[1, 0] * x + T[1, 1] * y + T[1, 2] * z + T[1, 3]
        P[i, 2] = T[2, 0] * x + T[2, 1] * y + T[2, 2] * z + T[2, 3]


@numba.njit(cache=True)
def _matches(P: np.ndarray, idx: np.ndarray, table: np.ndarray, bound2: float
             ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Matched pairs of the moved points P (N, 3) with rows idx (N,) closer than the gate
    (squared distance below ``bound2``): their count, summed squared distance, the mask (N,), the
    means of both sides (3,) and Umeyama's cross-covariance ``dst_demean src_demean^T / n``
    (3, 3)."""
    N, M = P.shape[0], table.shape[0]
    ok = np.zeros(N, dtype=np.bool_)
    n, err2 = 0, 0.0
    src, dst = np.zeros(3), np.zeros(3)
    for i in range(N):
        c = idx[i]
        if c >= M:
            continue
        d2 = 0.0
        for k in range(3):
            e = P[i, k] - table[c, k]
            d2 += e * e
        if d2 < bound2:
            ok[i] = True
            n += 1
            err2 += d2
            for k in range(3):
                src[k] += P[i, k]
                dst[k] += table[c, k]
    sigma = np.zeros((3, 3))
    if n == 0:
        return n, err2, ok, src, dst, sigma
    src /= n
    dst /= n
    for i in range(N):
        if ok[i]:
            c = idx[i]
            for a in range(3):
                da = table[c, a] - dst[a]
                for b in range(3):
                    sigma[a, b] += da * (P[i, b] - src[b])
    return n, err2, ok, src, dst, sigma / n


def _match(P: np.ndarray, rows: NearestRows, bound: float
           ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Open3D's matches of the moved points P (N, 3) (``rows`` tracks them at the identity pose,
    since P itself is moved): :func:`_matches` of their nearest rows within the gate ``bound``."""
    return _matches(P, rows.update(np.eye(3), np.zeros(3)), rows.table, bound * bound)


def _rigid_fit(n: int, src: np.ndarray, dst: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Umeyama's rigid transform (4, 4) taking the matched scan points onto the map points
    (identity without matches)."""
    T = np.eye(4)
    if n == 0:
        return T
    U, _, Vt = np.linalg.svd(sigma)
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    T[:3, :3] = (U * S) @ Vt
    T[:3, 3] = dst - T[:3, :3] @ src
    return T


class Open3DPointReplica(Open3DICP):
    """Open3D's point-to-point ICP replayed (module docstring), on the batch's ``MapIndex`` maps.

    Built by :meth:`Open3DICP.exact_replica` with the target's settings (``mode="point"``)."""

    name: ClassVar[str] = "open3d-point-replica"
    description: ClassVar[str] = "Open3D point-to-point registration_icp replayed, compiled"
    takes_map_index: ClassVar[bool] = True
    map_type: ClassVar[type] = MapIndex

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None = None) -> MapIndex:
        return MapIndex(map_points, map_normals)

    def register(self, scans: torch.Tensor, maps: Sequence[Any],
                 T_init: torch.Tensor) -> Registration:
        return super(Open3DICP, self).register(scans, maps, T_init)  # no Open3D thread cap

    def _register_one(self, scan: np.ndarray, target: MapIndex, T0: np.ndarray) -> OneResult:
        cfg = self.config
        bound = float(cfg.d_max)
        P = np.array(scan, dtype=np.float64)
        if not np.allclose(T0, np.eye(4), rtol=0.0, atol=_IDENTITY_PRECISION):
            _move(P, T0)
        rows = NearestRows(target, P, np.ones(len(P), dtype=bool), bound)
        n_pts = len(P)

        T = T0.copy()
        n, err2, ok, src, dst, sigma = _match(P, rows, bound)
        fitness, rmse = n / n_pts, (np.sqrt(err2 / n) if n else 0.0)
        for _ in range(cfg.max_iterations):
            step = _rigid_fit(n, src, dst, sigma)
            T = step @ T
            _move(P, step)
            n, err2, ok, src, dst, sigma = _match(P, rows, bound)
            f_new, r_new = n / n_pts, (np.sqrt(err2 / n) if n else 0.0)
            done = (abs(fitness - f_new) < RELATIVE_FITNESS
                    and abs(rmse - r_new) < self._relative_rmse())
            fitness, rmse = f_new, r_new
            if done:
                break
        if not np.all(np.isfinite(T)):
            return OneResult(T, False, -1, n, None)
        # the target's convergence proxy: one more Open3D iteration from T
        P = np.array(scan, dtype=np.float64)
        _move(P, T)
        m, _, _, m_src, m_dst, m_sigma = _match(
            P, NearestRows(target, P, np.ones(len(P), dtype=bool), bound), bound)
        T_extra = _rigid_fit(m, m_src, m_dst, m_sigma) @ T
        q = scan[ok] @ T[:3, :3].T + T[:3, 3]
        return OneResult(T, increment_norm(T, T_extra) < cfg.tol, -1, n,
                         point_to_point_hessian(q))

