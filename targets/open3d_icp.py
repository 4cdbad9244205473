"""Target ``open3d``: Open3D's ``registration_icp`` (legacy pipeline) as a black-box ICP.

Point-to-plane (default) or point-to-point ICP from Open3D (Zhou, Park and Koltun, "Open3D: A Modern
Library for 3D Data Processing", 2018), driven with the *same* settings as our differentiable
:class:`~icpbench.targets.p2plane.PointToPlaneICP` so transfer results are comparable. The settings
map as follows (``cfg`` is an :class:`~icpbench.targets.icp.ICPConfig`):

==========================  =========================================================================
ours                        Open3D
==========================  =========================================================================
``cfg.d_max`` (hard gate)   ``max_correspondence_distance`` (1-NN hybrid radius search)
``cfg.cauchy_c``            ``TransformationEstimationPointToPlane(CauchyLoss(k=c))``: the same weight
                            ``1 / (1 + (r / c)^2)`` on the point-to-plane residual; ``None``: no kernel
``cfg.max_iterations``      ``ICPConvergenceCriteria.max_iteration``
``cfg.tol`` (on ||delta||)  ``relative_fitness = 1e-6`` and ``relative_rmse`` = ``0.001 * tol``
                            (point-to-plane) or ``tol**2`` (point-to-point), metres. Open3D stops when
                            its inlier RMSE (of 3-D NN distances) changes by less than that *and* the
                            inlier count is unchanged (fitness moves in steps of 1/N, so 1e-6 means
                            "no change" for N < 10^6). Open3D has no test on the pose increment, so
                            the factors were calibrated: near convergence point-to-plane gave
                            |d rmse| = 0.005-0.02 x ||delta|| on the synthetic lidar scene (the RMSE
                            is not the minimised cost, so its change is first order in the step),
                            but less on the ``objects`` data, where 0.01 x tol stopped 11 of 16 clean
                            samples with a step still above tol; with 0.001 x tol exactly the 14 of
                            16 that p2plane converges on converge (lidar: 8 of 8 either way, at the
                            same cost). Point-to-point gave |d rmse| = 0.5-2 x ||delta||^2 (the
                            RMSE *is* the minimised cost).
update ``T <- exp(d^) T``   ``T <- [R_zyx(phi) | rho] T`` (Euler-angle rotation of the 6-vector); the
                            first-order step and therefore the fixed point are the same
``cfg.damping``             none (Open3D solves the undamped normal equations)
``cfg.soft_dmax``           not available (rejected)
==========================  =========================================================================

What Open3D does not expose, and the documented proxies used here:

* **iterations**: the legacy API does not report them; ``Registration.iterations`` is ``-1``
  ("unknown") for every sample that reached the library.
* **converged**: after the main call, one more Open3D iteration is run from its result (fixed 1
  iteration); the sample counts as converged when that extra increment satisfies our own test
  ``||log(T_extra T^-1)|| < tol`` (m and rad mixed, as in :mod:`icpbench.targets.icp`), i.e. the
  result is a fixed point of Open3D's iteration to within ``tol``. The returned pose is the one of
  the main call. This costs one iteration plus one KD-tree build of the map (Open3D rebuilds the
  map's KD-tree on every call: about 32 ms for 100k points on one core).
* **singular**: the 6x6 Gauss-Newton matrix at the final pose is rebuilt in NumPy from Open3D's
  final correspondence set (with the same kernel weights) and checked exactly like our ICP does.

Non-finite scan points are dropped before calling Open3D (it would skip them anyway); fewer than
``cfg.min_correspondences`` finite points give status ``too_few_correspondences`` with ``T = T_init``.
``inlier_fraction`` is the number of final correspondences over N (all points, dropped ones
included), as in our ICP.

Threads: Open3D uses a process-wide oneTBB cap set by ``open3d.utility.set_max_threads(n)``; this
target sets it (default 1) before every call and records it in :meth:`settings`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
import open3d as o3d
import torch

from icpbench.core.errors import InputError
from icpbench.core.registry import Range, check_ranges
from icpbench.core.types import Registration, validate_cloud
from icpbench.targets.base import Target
from icpbench.targets.blackbox import (
    BlackBoxTarget,
    OneResult,
    increment_norm,
    point_to_point_hessian,
    resolve_preset,
)
from icpbench.targets.icp import ICP_RANGES, ICPConfig, config_dict

_reg = o3d.pipelines.registration

#: Open3D's relative-fitness threshold (its own default); see the module docstring.
RELATIVE_FITNESS = 1e-6
#: point-to-plane: relative_rmse = RMSE_PER_STEP * tol; see the module docstring.
RMSE_PER_STEP = 1e-3

#: Point-to-point settings replacing the preset's when ``mode="point"`` is built from a preset
#: name (explicit settings win); see the class docstring.
POINT_PRESET_DEFAULTS: dict[str, dict[str, Any]] = {
    "lidar": {"cauchy_c": None, "d_max": 1.0, "max_iterations": 500},
    "objects": {"cauchy_c": None, "max_iterations": 500},
}


@dataclass(frozen=True)
class Open3DMap:
    """A map prepared for Open3D: the point cloud (with normals) and NumPy copies (map frame)."""

    cloud: Any  # open3d.geometry.PointCloud
    points: np.ndarray  # (M, 3) float64
    normals: np.ndarray | None  # (M, 3) float64 unit normals (point-to-plane), else None


class Open3DICP(BlackBoxTarget):
    """Open3D ``registration_icp`` (point-to-plane or point-to-point), configured like ``p2plane``.

    Args:
        preset: an ICP preset name (``"lidar"``, ``"objects"``, ``"*-train"``) or an ``ICPConfig``;
            same meaning as for :class:`~icpbench.targets.p2plane.PointToPlaneICP`.
        mode: ``"plane"`` (point-to-plane, needs map normals) or ``"point"`` (point-to-point; Open3D
            has no robust kernel for it, so ``cauchy_c`` must be ``None``). From a preset name,
            point-to-point gets its own defaults (:data:`POINT_PRESET_DEFAULTS`): no kernel, 500
            iterations (point-to-point creeps along weak directions: 21% of the 48 clean
            lidar-sim test scans were unconverged at the preset's 100) and, on ``lidar``, a 1 m
            gate instead of 5 m, since the gate is its only outlier rejection (with 5 m and 100
            iterations the median clean error was 18 cm, with 1 m and 500 iterations 3.2 cm;
            docs/methods.md, "Per-target settings").
        threads: Open3D's process-wide thread cap (``open3d.utility.set_max_threads``); 0 = auto.
        **overrides: ``ICPConfig`` fields to replace (e.g. ``d_max=2.0``, ``cauchy_c=None``).
    """

    name: ClassVar[str] = "open3d"
    param_ranges: ClassVar[dict[str, Range]] = {
        **ICP_RANGES,
        "threads": Range(1, 1024),
    }
    description: ClassVar[str] = (
        "Open3D registration_icp point-to-plane (or point-to-point), black box, same settings as p2plane"
    )
    map_type: ClassVar[type] = Open3DMap

    def __init__(self, preset: ICPConfig | str | None = "lidar", *,
                 mode: Literal["plane", "point"] = "plane", threads: int = 1,
                 **overrides: Any) -> None:
        check_ranges("target 'open3d'", locals(), self.param_ranges)
        if mode == "point" and isinstance(preset, str) and preset in POINT_PRESET_DEFAULTS:
            for key, value in POINT_PRESET_DEFAULTS[preset].items():
                overrides.setdefault(key, value)
        self.config = resolve_preset(preset, overrides, "Open3D")
        if mode not in ("plane", "point"):
            raise InputError(f"mode must be 'plane' or 'point', got {mode!r}")
        if self.config.d_max is None:
            raise InputError("Open3D needs a finite max correspondence distance: set d_max")
        if mode == "point" and self.config.cauchy_c is not None:
            raise InputError(
                "Open3D's point-to-point estimator has no robust kernel: pass cauchy_c=None"
            )
        if threads < 0:
            raise InputError(f"threads must be >= 0 (0 = automatic), got {threads}")
        self.mode = mode
        self.threads = threads
        self.min_correspondences = self.config.min_correspondences

    # -- Target API -------------------------------------------------------------------------
    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None) -> Open3DMap:
        """Wrap the map (M, 3) and its unit normals (M, 3), map frame, in an Open3D point cloud."""
        pts = validate_cloud(map_points, "map", min_points=6).astype(np.float64)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        nrm = None
        if self.mode == "plane":
            if map_normals is None:
                raise InputError("Open3D point-to-plane needs map normals: pass Sample.map_normals")
            nrm = np.asarray(map_normals, dtype=np.float64)
            if nrm.shape != pts.shape or not np.all(np.isfinite(nrm)):
                raise InputError(
                    f"map normals must be a finite array of shape {pts.shape}, got {nrm.shape}"
                )
            cloud.normals = o3d.utility.Vector3dVector(nrm)
        return Open3DMap(cloud=cloud, points=pts, normals=nrm)

    def register(self, scans: torch.Tensor, maps: Sequence[Open3DMap],
                 T_init: torch.Tensor) -> Registration:
        """As :meth:`BlackBoxTarget.register`, after setting Open3D's thread cap."""
        o3d.utility.set_max_threads(self.threads)
        return super().register(scans, maps, T_init)

    def settings(self) -> dict[str, Any]:
        return {
            "library": "open3d",
            "version": o3d.__version__,
            "mode": self.mode,
            "threads": self.threads,
            "relative_fitness": RELATIVE_FITNESS,
            "relative_rmse": self._relative_rmse(),
            **config_dict(self.config),
        }

    def replica(self) -> Target:
        """The differentiable target with the same settings: ``p2plane`` (point-to-plane) or
        ``p2point`` (point-to-point), built on this target's ``ICPConfig``. They minimise the same
        cost with the same correspondences, gate and kernel and stop at the same fixed point
        (measured: docs/methods.md, "Differentiable replicas of the black boxes")."""
        from icpbench.targets.p2plane import PointToPlaneICP
        from icpbench.targets.p2point import PointToPointICP

        return (PointToPlaneICP if self.mode == "plane" else PointToPointICP)(self.config)

    def exact_replica(self) -> Target | None:
        """Point-to-point: Open3D's iteration replayed with compiled correspondences
        (:class:`~icpbench.targets.open3d_point_replica.Open3DPointReplica`), which answers the
        query attacks' registrations; point-to-plane: None."""
        if self.mode != "point":
            return None
        from icpbench.targets.open3d_point_replica import Open3DPointReplica

        return Open3DPointReplica(self.config, mode="point", threads=self.threads)

    # -- internals --------------------------------------------------------------------------
    def _relative_rmse(self) -> float:
        """Open3D's RMSE-change threshold standing in for our step tolerance (module docstring)."""
        tol = self.config.tol
        return RMSE_PER_STEP * tol if self.mode == "plane" else tol**2

    def _estimator(self) -> Any:
        if self.mode == "point":
            return _reg.TransformationEstimationPointToPoint(False)
        if self.config.cauchy_c is None:
            return _reg.TransformationEstimationPointToPlane()
        return _reg.TransformationEstimationPointToPlane(_reg.CauchyLoss(k=self.config.cauchy_c))

    def _register_one(self, scan: np.ndarray, target: Open3DMap, T0: np.ndarray) -> OneResult:
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan))
        cfg, est = self.config, self._estimator()
        crit = _reg.ICPConvergenceCriteria(relative_fitness=RELATIVE_FITNESS,
                                           relative_rmse=self._relative_rmse(),
                                           max_iteration=cfg.max_iterations)
        res = _reg.registration_icp(source, target.cloud, cfg.d_max, T0, est, crit)
        T = np.array(res.transformation, dtype=np.float64)
        corr = np.asarray(res.correspondence_set, dtype=np.int64).reshape(-1, 2)
        if not np.all(np.isfinite(T)):
            return OneResult(T, False, -1, corr.shape[0], None)
        one = _reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
        T_extra = np.asarray(_reg.registration_icp(source, target.cloud, cfg.d_max, T, est, one)
                             .transformation)
        converged = increment_norm(T, T_extra) < cfg.tol
        return OneResult(T, converged, -1, corr.shape[0], self._hessian(scan, target, T, corr))

    def _hessian(self, pts: np.ndarray, target: Open3DMap, T: np.ndarray,
                 corr: np.ndarray) -> np.ndarray:
        """6x6 Gauss-Newton matrix (order [rho, phi]) at pose T from Open3D's correspondences."""
        q = pts[corr[:, 0]] @ T[:3, :3].T + T[:3, 3]
        if self.mode == "point":  # unweighted point-to-point
            return point_to_point_hessian(q)
        n = target.normals[corr[:, 1]]
        r = np.einsum("ij,ij->i", q - target.points[corr[:, 1]], n)
        w = np.ones_like(r) if self.config.cauchy_c is None else 1 / (1 + (r / self.config.cauchy_c) ** 2)
        J = np.concatenate([n, np.cross(q, n)], axis=1)  # (K, 6)
        return (J * w[:, None]).T @ J
