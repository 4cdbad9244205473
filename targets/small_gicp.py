"""Target ``small-gicp``: small_gicp's GICP (or point-to-plane / point-to-point ICP) as a black box.

small_gicp (Koide, "small_gicp: Efficient and parallel algorithms for point cloud registration",
JOSS 2024) implements Generalized-ICP (Segal, Haehnel and Thrun, RSS 2009) and ICP variants with a
Levenberg-Marquardt optimiser. Per map (once, in :meth:`SmallGICPTarget.prepare`): a
``PointCloud``, its ``KdTree`` and, as the registration type needs, the map's normals (PLANE_ICP) or
covariances (GICP), estimated by small_gicp from ``num_neighbors`` nearest neighbours. The normals
given to ``prepare`` are *not* used: small_gicp's Python API has no setter for them. Per scan: a
``PointCloud`` and, for GICP, its own KD-tree and covariances; then ``small_gicp.align(map, scan,
map_tree, init_T_target_source=T_init, ...)``. No downsampling is applied to either cloud.

Unlike the other black-box libraries, small_gicp reports ``converged``, ``iterations``,
``num_inliers`` and the final 6x6 ``H``; they are passed through (the health check on ``H`` is the
same as in :mod:`icpbench.targets.icp`). Its stopping rule is its own: rotation increment below
``rotation_epsilon`` (rad) *and* translation increment below ``translation_epsilon`` (preset
length units).

Settings come from an ICP preset (``cfg``, an :class:`~icpbench.targets.icp.ICPConfig`, the same
presets as ``p2plane`` and ``open3d``):

===============================  ========================================================================
small_gicp                       from the preset
===============================  ========================================================================
``max_correspondence_distance``  ``cfg.d_max`` (``lidar`` 5 m, ``objects`` 0.3); required
``max_iterations``               ``cfg.max_iterations`` (``lidar`` 100, ``objects`` 150)
``min_correspondences``          ``cfg.min_correspondences`` (fewer inliers: ``too_few_correspondences``)
``cfg.cauchy_c``                 not available: small_gicp's Python API has no robust kernel (distance
                                 rejection only); ignored
``cfg.tol``                      not used: small_gicp keeps its own stopping rule (below) with its
                                 defaults 0.1 deg and 1e-3. Translating ``tol = 1e-4`` to both
                                 thresholds was measured to leave 3 of 8 clean ``objects`` samples
                                 ``not_converged`` after 100 iterations (Levenberg-Marquardt keeps
                                 taking tiny steps at the noise floor) without changing the pose
                                 error (median 0.0061 either way)
``cfg.damping``                  none (small_gicp runs its own Levenberg-Marquardt)
``cfg.soft_dmax``                not available (rejected)
===============================  ========================================================================

Measured with the defaults (GICP, 1 thread): ``lidar`` on
:func:`icpbench.datasets.synthetic_scene.scene_sample`
(0.2-0.3 m / 3-6 deg initial error) gives 0.5-2 cm in 4-6 iterations; ``objects`` on the
``objects`` test split gives a median 0.006 (p2plane: 0.003; the covariances of 20 neighbours of
a scan with 0.025 noise are biased) in 3-11 iterations.

Guards against known failures of small_gicp 1.0.1 (measured; docs/methods.md, "Black-box targets"):

* an **empty map segfaults** the process: :meth:`prepare` rejects maps with fewer than 6 points (and
  NaN/Inf map points) with :class:`~icpbench.core.errors.InputError`;
* a **single NaN/Inf scan point freezes** the optimiser at ``T_init`` (NaN pairs pass its distance
  rejector, so H is NaN): non-finite scan points are dropped before the call. The status does not
  change because of that; ``inlier_fraction`` is still relative to all N points, so dropped points
  count as outliers. Fewer than ``min_correspondences`` finite points give status
  ``too_few_correspondences`` with ``T = T_init``.

Note (docs/methods.md, "Black-box targets"): small_gicp's PLANE_ICP minimises the element-wise product
``n * r`` (3 residuals per point), not the textbook ``(n . r)^2`` of Open3D and our ``p2plane``.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import version
from typing import Any, ClassVar, Literal

import numpy as np
import small_gicp

from icpbench.core.errors import InputError
from icpbench.core.registry import Range, check_ranges
from icpbench.core.types import validate_cloud
from icpbench.targets.base import Target
from icpbench.targets.blackbox import BlackBoxTarget, OneResult, resolve_preset
from icpbench.targets.icp import ICP_RANGES, ICPConfig, config_dict

RegistrationType = Literal["GICP", "PLANE_ICP", "ICP"]


@dataclass(frozen=True)
class SmallGICPMap:
    """A map prepared for small_gicp: point cloud (with normals/covariances as needed) and KD-tree."""

    cloud: Any  # small_gicp.PointCloud
    tree: Any  # small_gicp.KdTree
    size: int


class SmallGICPTarget(BlackBoxTarget):
    """small_gicp registration of a scan to a fixed map.

    Args:
        preset: ICP preset name (``"lidar"``, ``"objects"``, ``"*-train"``) or ``ICPConfig``;
            gives ``d_max`` (max correspondence distance), ``max_iterations`` and
            ``min_correspondences`` (table in the module docstring).
        registration_type: ``"GICP"`` (default), ``"PLANE_ICP"`` or ``"ICP"``.
        rotation_epsilon: convergence threshold on the rotation increment (rad).
        translation_epsilon: convergence threshold on the translation increment (preset units).
        num_neighbors: neighbours used to estimate normals/covariances.
        threads: OpenMP threads passed to every small_gicp call.
        **overrides: ``ICPConfig`` fields to replace (e.g. ``d_max=1.0``, ``max_iterations=30``).
    """

    name: ClassVar[str] = "small-gicp"
    param_ranges: ClassVar[dict[str, Range]] = {
        **ICP_RANGES,
        "rotation_epsilon": Range(0.0, lo_open=True),
        "translation_epsilon": Range(0.0, lo_open=True),
        "num_neighbors": Range(1),
        "threads": Range(1, 1024),
    }
    description: ClassVar[str] = "small_gicp GICP (or PLANE_ICP / ICP) registration (black box)"
    map_type: ClassVar[type] = SmallGICPMap

    def __init__(self, preset: ICPConfig | str | None = "lidar", *,
                 registration_type: RegistrationType = "GICP",
                 rotation_epsilon: float = np.deg2rad(0.1), translation_epsilon: float = 1e-3,
                 num_neighbors: int = 20, threads: int = 1, **overrides: Any) -> None:
        check_ranges("target 'small-gicp'", locals(), self.param_ranges)
        cfg = self.config = resolve_preset(preset, overrides, "small_gicp")
        if registration_type not in ("GICP", "PLANE_ICP", "ICP"):
            raise InputError(
                f"registration_type must be 'GICP', 'PLANE_ICP' or 'ICP', got {registration_type!r}"
            )
        if cfg.d_max is None:
            raise InputError("small_gicp needs a finite max correspondence distance: set d_max")
        for nm, v in (("rotation_epsilon", rotation_epsilon),
                      ("translation_epsilon", translation_epsilon)):
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{nm} must be a positive number, got {v}")
        if num_neighbors < 5 or threads < 1:
            raise InputError("need num_neighbors >= 5 and threads >= 1")
        self.registration_type = registration_type
        self.max_corr = float(cfg.d_max)
        self.max_iterations = cfg.max_iterations
        self.rotation_epsilon = float(rotation_epsilon)
        self.translation_epsilon = float(translation_epsilon)
        self.num_neighbors = int(num_neighbors)
        self.threads = int(threads)
        self.min_correspondences = cfg.min_correspondences

    # -- Target API -------------------------------------------------------------------------
    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None = None) -> SmallGICPMap:
        """Build the map's cloud, KD-tree and normals/covariances (map frame); normals unused."""
        pts = validate_cloud(map_points, "map", min_points=6).astype(np.float64)
        cloud = small_gicp.PointCloud(np.ascontiguousarray(pts))
        tree = small_gicp.KdTree(cloud, num_threads=self.threads)
        if self.registration_type == "PLANE_ICP":
            small_gicp.estimate_normals(cloud, tree, self.num_neighbors, self.threads)
        elif self.registration_type == "GICP":
            small_gicp.estimate_covariances(cloud, tree, self.num_neighbors, self.threads)
        return SmallGICPMap(cloud=cloud, tree=tree, size=pts.shape[0])

    def settings(self) -> dict[str, Any]:
        return {
            "library": "small_gicp",
            "version": version("small_gicp"),
            "threads": self.threads,
            "registration_type": self.registration_type,
            "max_corr": self.max_corr,
            "max_iterations": self.max_iterations,
            "rotation_epsilon": self.rotation_epsilon,
            "translation_epsilon": self.translation_epsilon,
            "num_neighbors": self.num_neighbors,
            "min_correspondences": self.min_correspondences,
            "icp_config": config_dict(self.config),
        }

    def replica(self) -> Target | None:
        """The differentiable target that reproduces this one: GICP ->
        :class:`~icpbench.targets.gicp_replica.SmallGICPReplica`, ICP -> ``p2point`` without a
        kernel (same cost and gate; small_gicp's LM path and looser stop aside), PLANE_ICP -> None
        (its residual ``n * r`` element-wise has no counterpart here)."""
        if self.registration_type == "GICP":
            from icpbench.targets.gicp_replica import SmallGICPReplica

            return SmallGICPReplica(self.config, num_neighbors=self.num_neighbors,
                                    threads=self.threads)
        if self.registration_type == "ICP":
            from icpbench.targets.p2point import PointToPointICP

            return PointToPointICP(self.config.with_(cauchy_c=None))
        return None

    # -- internals --------------------------------------------------------------------------
    def _register_one(self, scan: np.ndarray, target: SmallGICPMap, T0: np.ndarray) -> OneResult:
        source = small_gicp.PointCloud(scan)
        if self.registration_type == "GICP":
            small_gicp.estimate_covariances(source, small_gicp.KdTree(source, num_threads=self.threads),
                                            self.num_neighbors, self.threads)
        res = small_gicp.align(
            target.cloud, source, target.tree, init_T_target_source=T0,
            registration_type=self.registration_type, max_correspondence_distance=self.max_corr,
            num_threads=self.threads, max_iterations=self.max_iterations,
            rotation_epsilon=self.rotation_epsilon, translation_epsilon=self.translation_epsilon,
        )
        return OneResult(np.array(res.T_target_source, dtype=np.float64), bool(res.converged),
                         int(res.iterations), int(res.num_inliers), np.asarray(res.H))
