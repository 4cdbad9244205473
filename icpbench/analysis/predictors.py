"""Cheap predictors of a place's danger, computed from the clean scan and its map at the true pose.

Each predictor costs one nearest-neighbour query and a 6x6 eigen-decomposition (milliseconds), against
seconds per scan for an attack. All of them start from the point-to-plane system of our ICP at the
true pose (:class:`icpbench.targets.icp.ICPConfig` of the preset): every clean scan point ``p_i``
moved into the map frame by ``T_gt`` (``q_i = T_gt p_i``) is associated with its nearest map point
``m_i`` within the association gate ``d_max`` (lidar preset: 5 m) and that point's unit normal
``n_i``; its Jacobian row is ``a_i = [n_i, q_i x n_i]`` (twist [rho, phi], map frame, as in
:mod:`icpbench.core.sector_math`) and its weight the ICP's Cauchy weight
``w_i = 1 / (1 + (r_i / c)^2)`` of the clean residual ``r_i = n_i . (q_i - m_i)`` (lidar preset:
c = 1 m). The Hessian (Gauss-Newton normal matrix) is ``H = sum_i w_i a_i a_i^T``.

The predictors (:data:`PREDICTORS`; "danger" says which way is dangerous):

* ``hessian_min_eig``: smallest eigenvalue of the *scaled* Hessian ``S H S``,
  ``S = diag(1, 1, 1, 1/L, 1/L, 1/L)`` with ``L`` the RMS distance of the associated points from
  the sensor (metres). The rotation columns ``q x n`` carry metres; dividing them by ``L`` makes
  every entry dimensionless (a rotation of 1/L rad moves a typical point by about 1 m), so
  translation and rotation eigenvalues are comparable. Units: (weighted) correspondences. Small =
  dangerous (the degeneracy factor of Zhang, Kaess and Singh, "On degeneracy of optimization-based
  state estimation problems", ICRA 2016).
* ``hessian_cond``: condition number ``lambda_max / lambda_min`` of the same scaled Hessian.
  Large = dangerous.
* ``loc_trans_min``, ``loc_rot_min``: X-ICP-style localisability of the weakest translation and
  rotation direction (:mod:`icpbench.analysis.localisability`, Tuna et al., T-RO 2024). Small =
  dangerous.
* ``sector_xy``: the analytic sector estimate (Laconte et al., RA-L 2024;
  :meth:`icpbench.core.sector_math.SectorAnalysis.worst_case`) at budget lambda: the larger of the
  closed-form worst longitudinal and lateral errors of one linearised step, metres, as the ``sector``
  attack computes it (no Cauchy weights: the model the attack uses). Large = dangerous.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from icpbench.analysis.localisability import KAPPA, localisability
from icpbench.core import sector_math
from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Sample
from icpbench.targets.icp import icp_config

#: Predictor name -> (description, +1 if larger means more dangerous, -1 if smaller does).
PREDICTORS: dict[str, tuple[str, int]] = {
    "hessian_min_eig": ("smallest eigenvalue of the scaled point-to-plane Hessian", -1),
    "hessian_cond": ("condition number of the scaled point-to-plane Hessian", +1),
    "loc_trans_min": ("X-ICP localisability of the weakest translation direction", -1),
    "loc_rot_min": ("X-ICP localisability of the weakest rotation direction", -1),
    "sector_xy": ("analytic sector worst case max(x, y) at lambda [m]", +1),
}


@dataclass(frozen=True)
class PointToPlaneSystem:
    """The associated correspondences of a clean scan at its true pose.

    Attributes:
        points: (K, 3) associated scan points in the map frame (``T_gt p_i``), metres.
        normals: (K, 3) unit normals of their map points, map frame.
        residuals: (K,) clean point-to-plane residuals, metres.
        weights: (K,) Cauchy weights of the residuals (1 without a robust kernel).
        n_points: N, the scan's point count (associated or not).
    """

    points: np.ndarray
    normals: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    n_points: int

    @property
    def jacobian(self) -> np.ndarray:
        """(K, 6) rows ``[n_i, q_i x n_i]``."""
        return sector_math.jacobian(self.points, self.normals)

    @property
    def hessian(self) -> np.ndarray:
        """(6, 6) ``sum_i w_i a_i a_i^T``."""
        A = self.jacobian
        return (A * self.weights[:, None]).T @ A

    @property
    def lever_m(self) -> float:
        """L: RMS distance of the associated points from the sensor (metres). The map frame is the
        sensor's true frame for the lidar datasets (origin at the lidar), so it is ``|q_i|``."""
        return float(np.sqrt(np.mean(np.sum(self.points**2, axis=1))))

    def scaled_hessian(self) -> np.ndarray:
        """(6, 6) ``S H S`` with ``S = diag(1, 1, 1, 1/L, 1/L, 1/L)`` (dimensionless entries)."""
        s = np.array([1.0, 1.0, 1.0, *([1.0 / max(self.lever_m, 1e-9)] * 3)])
        return self.hessian * np.outer(s, s)


def point_to_plane_system(scan: np.ndarray, T_gt: np.ndarray, map_index: MapIndex, *,
                          d_max: float, cauchy_c: float | None) -> PointToPlaneSystem:
    """Associate a clean scan at its true pose (:func:`icpbench.core.sector_math.associate`).

    Args:
        scan: (N, 3) clean scan, sensor (scan) frame, metres.
        T_gt: (4, 4) true scan->map transform.
        map_index: the map with unit normals, map frame.
        d_max: association gate, metres.
        cauchy_c: Cauchy parameter c, metres (None: weights 1).

    Raises:
        InputError: bad input, or fewer than 6 correspondences.
    """
    assoc = sector_math.associate(scan, T_gt, map_index, d_max)
    if assoc.n_valid < 6:
        raise InputError(f"only {assoc.n_valid} scan points have a map point within {d_max} m at "
                         "the true pose; at least 6 are needed")
    v = assoc.valid
    r = assoc.residual[v]
    w = np.ones_like(r) if cauchy_c is None else 1.0 / (1.0 + (r / cauchy_c) ** 2)
    return PointToPlaneSystem(points=assoc.points_map[v], normals=assoc.normals_map[v],
                              residuals=r, weights=w, n_points=int(v.size))


def hessian_conditioning(system: PointToPlaneSystem) -> tuple[float, float]:
    """(smallest eigenvalue, condition number) of the scaled Hessian (see the module doc);
    the condition number is ``inf`` when the smallest eigenvalue is not positive."""
    eig = np.linalg.eigvalsh(system.scaled_hessian())
    lo, hi = float(eig[0]), float(eig[-1])
    return lo, (hi / lo if lo > 0 else float("inf"))


def place_predictors(scan: np.ndarray, T_gt: np.ndarray, map_index: MapIndex, *,
                     preset: str = "lidar", budget_m: float = 1.0,
                     kappa: float = KAPPA) -> dict[str, Any]:
    """Every predictor of :data:`PREDICTORS` for one clean scan, plus ``n_assoc`` (the share of
    scan points with a correspondence) and ``weak_dir_x``/``weak_dir_y``/``weak_dir_z`` (the
    weakest translation direction, map frame, sign fixed so that its largest component is
    positive).

    Args:
        scan: (N, 3) clean scan, scan frame, metres.
        T_gt: (4, 4) true scan->map transform.
        map_index: map with unit normals.
        preset: ICP preset whose ``d_max``, ``cauchy_c`` and damping are used.
        budget_m: lambda of the sector estimate, metres.
        kappa: localisability alignment threshold.
    """
    cfg = icp_config(preset)
    d_max = np.inf if cfg.d_max is None else float(cfg.d_max)
    system = point_to_plane_system(scan, T_gt, map_index, d_max=d_max, cauchy_c=cfg.cauchy_c)
    min_eig, cond = hessian_conditioning(system)
    loc = localisability(system.points, system.normals, system.weights, kappa)
    wc = sector_math.analyse(scan, T_gt, map_index, d_max=d_max,
                             damping=cfg.damping).worst_case(budget_m)
    weak = loc.weakest_translation()
    weak = weak * np.sign(weak[int(np.argmax(np.abs(weak)))])
    return {"hessian_min_eig": min_eig, "hessian_cond": cond, "loc_trans_min": loc.trans_min,
            "loc_rot_min": loc.rot_min, "sector_xy": float(max(wc[0], wc[1])),
            "n_assoc": len(system.weights) / system.n_points,
            "weak_dir_x": float(weak[0]), "weak_dir_y": float(weak[1]), "weak_dir_z": float(weak[2])}


def sample_predictors(sample: Sample, *, preset: str = "lidar", budget_m: float = 1.0,
                      kappa: float = KAPPA) -> dict[str, Any]:
    """:func:`place_predictors` of a dataset sample (its scan, ``T_gt`` and map with normals)."""
    index = MapIndex(sample.map, sample.map_normals)
    return place_predictors(np.asarray(sample.scan, dtype=np.float64),
                            np.asarray(sample.T_gt, dtype=np.float64), index, preset=preset,
                            budget_m=budget_m, kappa=kappa)
