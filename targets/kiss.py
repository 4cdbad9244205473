"""Target ``kiss-icp``: the registration core of KISS-ICP as a black-box scan-to-map aligner.

KISS-ICP (Vizzo et al., "KISS-ICP: In Defense of Point-to-Point ICP -- Simple, Accurate, and Robust
Registration If Done the Right Way", RA-L 2023) is an odometry pipeline; we use only its
registration step against a *given* map, through the pybind classes of ``kiss_icp`` 1.2/1.3:

* the map is a ``_VoxelHashMap(voxel_size, max_distance=inf, max_points_per_voxel)`` filled once
  with ``_add_points`` (KISS keeps at most ``max_points_per_voxel`` points per voxel and ignores the
  rest; no range cropping);
* each scan is aligned with ``_Registration._align_points_to_map(points, voxel_map, initial_guess,
  max_correspondance_distance, kernel)``: point-to-point Gauss-Newton, nearest neighbour among the
  points of the 27 voxels around each query, pairs farther than ``max_corr`` rejected, weight
  ``kernel^2 / (kernel + r^2)^2``, stop when ``||dx|| < convergence`` or after ``max_iterations``.

The odometry front end (deskewing, scan voxelisation, adaptive threshold, map update) is not used.

Settings come from an ICP preset (``cfg``, an :class:`~icpbench.targets.icp.ICPConfig`, the same
presets as ``p2plane`` and ``open3d``) unless given explicitly:

=======================  ===============================================================================
KISS setting             default derived from the preset
=======================  ===============================================================================
``voxel_size``           ``cfg.d_max / 5``: ``lidar`` 1.0 m (KISS's own choice for 100 m sensors),
                         ``objects`` 0.06. KISS looks for neighbours only in the 27 voxels around a
                         query, so whatever ``max_corr`` is, one iteration reaches 1-2 voxels: the
                         voxel bounds the capture range (docs/methods.md, "Black-box targets"). The ratio 5
                         keeps KISS's lidar voxel; on ``objects`` voxels of 0.05-0.15 all registered
                         the clean test split to a median 0.003, the lidar-scale settings (voxel 1,
                         kernel 1) only to 0.018. The voxel also thins the map: KISS keeps at most
                         ``max_points_per_voxel`` points per voxel, at least
                         ``voxel / sqrt(max_points)`` apart (0.22 m for lidar, 0.013 for objects).
``max_corr``             ``min(cfg.d_max, voxel_size)``: lidar 1.0 m, objects 0.06. Pairs farther than
                         a voxel are rarely found anyway, and with ``max_corr <= voxel_size`` the
                         inlier count below is exact.
``kernel``               ``cfg.cauchy_c ** 2``: lidar 1.0, objects 0.0225. KISS's weight
                         ``kernel^2 / (kernel + r^2)^2 = (1 / (1 + r^2 / kernel))^2`` is the *square* of
                         a Cauchy weight of scale ``sqrt(kernel)``, so this gives KISS the preset's
                         residual scale c (at ``r = c`` the weight is 1/4 instead of Cauchy's 1/2).
                         ``cauchy_c=None``: ``kernel = 1e6 * max_corr^2``, weights within 2e-6 of 1.
``convergence``          ``cfg.tol``: KISS tests ``||dx||`` (m and rad mixed), the same quantity.
``max_iterations``       500 (KISS's own; *not* the preset's cap: point-to-point needs 17-90 iterations
                         here, and a 30-iteration cap stops 0.2-0.3 m short on the lidar scene).
``min_correspondences``  ``cfg.min_correspondences``.
=======================  ===============================================================================

Measured with the defaults (1 thread, this repo's 2-core machine): the ``lidar`` preset on
:func:`icpbench.datasets.synthetic_scene.scene_sample` (2,000-point scans, 20,000-point map,
0.2-0.3 m / 3-6 deg
initial error) gives 1.7-3 cm translation error in 17-36 iterations (point-to-point bias from the
map sampling; p2plane: 0.2-0.7 cm); the ``objects`` preset on the ``objects`` test split gives a
median 0.003 (max 0.01) in 28-76 iterations (p2plane: median 0.003, max 0.006).

What KISS does not expose, and how this target obtains it:

* **iterations / converged**: the library returns only the pose. This target calls
  ``_align_points_to_map`` with a one-iteration ``_Registration`` in a Python loop, feeding back
  the pose; that is the library's own loop (each C++ iteration only transforms the scan by the
  current pose, associates, solves and applies ``exp(dx)``), so the result equals one call with
  ``max_iterations`` up to rounding (checked in the tests). ``dx`` is recovered as
  ``log(T_new T_old^-1)``; the loop stops exactly where KISS's would, which gives the exact
  iteration count and ``converged = ||dx|| < convergence`` before the cap.
* **inlier_fraction**: KISS reports no correspondences. At the final pose the scan points whose
  nearest stored map point (SciPy KD-tree over ``_point_cloud()``) lies within
  ``min(max_corr, voxel_size)`` are counted. Such a neighbour always lies in the 27 voxels that
  KISS searches, so this is exact when ``max_corr <= voxel_size`` (the default) and a lower bound
  of KISS's count otherwise.
* **singular**: the 6x6 point-to-point Gauss-Newton matrix with KISS's weights is rebuilt from
  those pairs and checked as in :mod:`icpbench.targets.icp`.

Non-finite scan points are dropped before calling KISS (it skips them anyway); fewer than
``min_correspondences`` finite points give status ``too_few_correspondences`` with ``T = T_init``.

Threads: the first ``_Registration`` made in a process fixes KISS's oneTBB thread count for the
whole process (a static ``tbb::global_control``). This module creates its registration objects at
construction; asking for a different count later in the same process raises ``InputError`` (run
such a target in another process).
"""


from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, ClassVar

import kiss_icp
import numpy as np
from kiss_icp.pybind import kiss_icp_pybind as kp
from scipy.spatial import cKDTree

from icpbench.core.errors import InputError, PluginUnavailableError
from icpbench.core.registry import Range, check_ranges
from icpbench.core.types import validate_cloud
from icpbench.targets.blackbox import (
    BlackBoxTarget,
    OneResult,
    increment_norm,
    point_to_point_hessian,
    resolve_preset,
)
from icpbench.targets.icp import ICP_RANGES, ICPConfig, config_dict

#: kiss-icp versions whose pybind signatures this module was written and tested against.
TESTED_VERSIONS = ((1, 2), (1, 4))  # [1.2, 1.4)
#: default voxel_size = d_max / VOXEL_PER_DMAX (module docstring).
VOXEL_PER_DMAX = 5.0
#: with cauchy_c=None: kernel = NO_KERNEL_SCALE * max_corr^2 (weights ~ 1 within max_corr).
NO_KERNEL_SCALE = 1e6
_threads_fixed: int | None = None  # thread count fixed by the first _Registration of this module


def _check_version(version: str) -> None:
    parts = tuple(int(x) for x in re.findall(r"\d+", version)[:2])
    lo, hi = TESTED_VERSIONS
    if not (lo <= parts < hi):
        raise PluginUnavailableError(
            f"kiss-icp {version} is not supported: the kiss-icp target uses private pybind classes "
            f"tested with versions >= {lo[0]}.{lo[1]} and < {hi[0]}.{hi[1]}; "
            "install e.g. `pip install 'kiss-icp>=1.2,<1.4'`"
        )


_check_version(kiss_icp.__version__)


@dataclass(frozen=True)
class KissMap:
    """A map prepared for KISS-ICP: the voxel hash map and a KD-tree over its stored points."""

    voxel_map: Any  # kiss_icp_pybind._VoxelHashMap
    points: np.ndarray  # (K, 3) float64 points kept by the voxel map (K <= M), map frame
    tree: cKDTree


def _positive(name: str, value: float) -> float:
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a positive number, got {value}")
    return float(value)


class KissICPTarget(BlackBoxTarget):
    """KISS-ICP point-to-point registration of a scan to a fixed voxel map.

    Args:
        preset: ICP preset name (``"lidar"``, ``"objects"``, ``"*-train"``) or ``ICPConfig``; the
            defaults below are derived from it (table in the module docstring).
        voxel_size: voxel edge of the map (preset length units); bounds the neighbour search to 27
            voxels. Default ``d_max / 5``.
        max_points_per_voxel: points KISS keeps per voxel.
        max_corr: maximum correspondence distance. Default ``min(d_max, voxel_size)``.
        kernel: KISS's robust-kernel parameter (weight ``kernel^2 / (kernel + r^2)^2``, units of
            r^2). Default ``cauchy_c ** 2``.
        max_iterations: iteration cap (KISS's default 500; the preset's cap is not used).
        threads: KISS/oneTBB threads, fixed process-wide by the first registration object.
        **overrides: ``ICPConfig`` fields replaced before deriving the defaults (e.g. ``d_max=2.0``,
            ``tol=1e-5`` for the convergence threshold, ``min_correspondences=10``).
    """

    name: ClassVar[str] = "kiss-icp"
    param_ranges: ClassVar[dict[str, Range]] = {
        **ICP_RANGES,
        "voxel_size": Range(0.0, lo_open=True),
        "max_points_per_voxel": Range(1),
        "max_corr": Range(0.0, lo_open=True),
        "kernel": Range(0.0, lo_open=True),
        "max_iterations": Range(1, 1_000_000),
        "threads": Range(1, 1024),
    }
    description: ClassVar[str] = "KISS-ICP point-to-point registration to a voxel map (black box)"
    map_type: ClassVar[type] = KissMap

    def __init__(self, preset: ICPConfig | str | None = "lidar", *,
                 voxel_size: float | None = None, max_points_per_voxel: int = 20,
                 max_corr: float | None = None, kernel: float | None = None,
                 max_iterations: int = 500, threads: int = 1, **overrides: Any) -> None:
        check_ranges("target 'kiss-icp'", locals(), self.param_ranges)
        cfg = self.config = resolve_preset(preset, overrides, "KISS-ICP")
        if voxel_size is None:
            if cfg.d_max is None:
                raise InputError("KISS-ICP derives its voxel size from d_max: set d_max or voxel_size")
            voxel_size = cfg.d_max / VOXEL_PER_DMAX
        self.voxel_size = _positive("voxel_size", voxel_size)
        if max_corr is None:
            max_corr = min(cfg.d_max or np.inf, self.voxel_size)
        self.max_corr = _positive("max_corr", max_corr)
        if kernel is None:
            kernel = (cfg.cauchy_c**2 if cfg.cauchy_c is not None
                      else NO_KERNEL_SCALE * self.max_corr**2)
        self.kernel = _positive("kernel", kernel)
        if max_points_per_voxel < 1 or max_iterations < 1 or threads < 0:
            raise InputError("max_points_per_voxel and max_iterations must be >= 1, threads >= 0")
        global _threads_fixed
        if _threads_fixed is not None and _threads_fixed != threads:
            raise InputError(
                f"KISS-ICP already fixed its thread count to {_threads_fixed} in this process; "
                f"a target with threads={threads} must run in a separate process"
            )
        self.max_points_per_voxel = int(max_points_per_voxel)
        self.max_iterations = int(max_iterations)
        self.convergence = cfg.tol
        self.threads = int(threads)
        self.min_correspondences = cfg.min_correspondences
        self._step = kp._Registration(max_num_iterations=1, convergence_criterion=self.convergence,
                                      max_num_threads=self.threads)
        _threads_fixed = self.threads

    # -- Target API -------------------------------------------------------------------------
    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None = None) -> KissMap:
        """Build the voxel hash map of the (M, 3) map (map frame); normals are not used."""
        pts = validate_cloud(map_points, "map", min_points=6).astype(np.float64)
        vmap = kp._VoxelHashMap(voxel_size=self.voxel_size, max_distance=np.inf,
                                max_points_per_voxel=self.max_points_per_voxel)
        vmap._add_points(kp._Vector3dVector(np.ascontiguousarray(pts)))
        kept = np.asarray(vmap._point_cloud(), dtype=np.float64).reshape(-1, 3)
        return KissMap(voxel_map=vmap, points=kept, tree=cKDTree(kept))

    def settings(self) -> dict[str, Any]:
        return {
            "library": "kiss-icp",
            "version": kiss_icp.__version__,
            "threads": self.threads,
            "voxel_size": self.voxel_size,
            "max_points_per_voxel": self.max_points_per_voxel,
            "max_corr": self.max_corr,
            "kernel": self.kernel,
            "max_iterations": self.max_iterations,
            "convergence": self.convergence,
            "min_correspondences": self.min_correspondences,
            "icp_config": config_dict(self.config),
        }

    # -- internals --------------------------------------------------------------------------
    def _register_one(self, scan: np.ndarray, target: KissMap, T0: np.ndarray) -> OneResult:
        vec = kp._Vector3dVector(scan)
        T, converged, it = T0.copy(), False, 0
        while it < self.max_iterations and not converged:
            T_new = np.asarray(self._step._align_points_to_map(
                points=vec, voxel_map=target.voxel_map, initial_guess=T,
                max_correspondance_distance=self.max_corr, kernel=self.kernel), dtype=np.float64)
            it += 1
            if not np.all(np.isfinite(T_new)):
                return OneResult(T_new, False, it, 0, None)
            converged = increment_norm(T, T_new) < self.convergence
            T = T_new
        n_in, H = self._inliers_and_hessian(scan, target, T)
        return OneResult(T, converged, it, n_in, H)

    def _inliers_and_hessian(self, pts: np.ndarray, target: KissMap,
                             T: np.ndarray) -> tuple[int, np.ndarray]:
        """Inlier count at pose T and the KISS-weighted 6x6 point-to-point GN matrix ([rho, phi])."""
        q = pts @ T[:3, :3].T + T[:3, 3]
        d, _ = target.tree.query(q, k=1, distance_upper_bound=min(self.max_corr, self.voxel_size))
        ok = np.isfinite(d)
        w = self.kernel**2 / (self.kernel + d[ok] ** 2) ** 2
        return int(ok.sum()), point_to_point_hessian(q[ok], w)
