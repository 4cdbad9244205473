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

Settings: KISS-ICP's own choices for a scan-to-map registration (KISS-ICP paper, Vizzo et al.
RA-L 2023, Sec. III, and the defaults of its ``KISSConfig``), scaled with the preset's length unit
through the voxel size (``cfg`` is an :class:`~icpbench.targets.icp.ICPConfig`, the same presets
as ``p2plane`` and ``open3d``):

=========================  ===========================================================================
KISS setting               default, and why
=========================  ===========================================================================
``voxel_size``             ``cfg.d_max / 5``: ``lidar`` 1.0 m, KISS's ``max_range / 100`` for its
                           default 100 m range (the simulated sensors reach 100-120 m); ``objects``
                           0.06 (voxels of 0.05-0.15 all registered the clean objects to a median
                           0.003). KISS looks for neighbours only in the 27 voxels around a query, so
                           the voxel also bounds the capture range (docs/methods.md, "Black-box
                           targets").
``max_points_per_voxel``   20 (KISS's default): the map keeps points at least
                           ``voxel / sqrt(20)`` apart (0.22 m for lidar; the lidar-sim maps are
                           0.25 m voxel samples, so little is dropped).
``initial_threshold``      ``2 * voxel_size`` (lidar: 2.0 m, KISS's ``initial_threshold``). KISS's
                           adaptive threshold ``sigma`` starts there and only falls once the
                           odometry has seen motions above ``min_motion_th`` (0.1 m); one
                           registration against a given map has no motion history, so ``sigma``
                           stays at its start. (The library defaults of ``_align_points_to_map``
                           are not used: it has none.)
``max_corr``               ``3 * sigma`` (KISS's rule; lidar 6.0 m). Before 2026-11-26 this target
                           used ``min(d_max, voxel)`` = 1.0 m, a third of KISS's choice; pairs
                           beyond a voxel are only found within the 27 voxels.
``kernel``                 ``sigma / 3`` (the paper's rule, Sec. III-C; lidar 0.667). kiss-icp
                           1.2.2 and later pass ``sigma`` itself (commit c9f6931); on the 48 clean
                           lidar-sim test scans that gave 100% converged, median 3.0 cm, mean 27 cm
                           against 98%, 2.2 cm, 25 cm with ``sigma / 3`` (docs/methods.md). KISS's
                           weight ``kernel^2 / (kernel + r^2)^2`` is Geman-McClure's; the replica
                           (:mod:`icpbench.targets.kiss_replica`) writes it as
                           ``1 / (1 + r^2 / c^2)^2`` with ``c = sqrt(kernel)``. Before 2026-11-26:
                           ``cauchy_c^2`` = 1.0.
``convergence``            ``cfg.tol`` (1e-4, KISS's default): KISS tests ``||dx||`` (m and rad
                           mixed), the same quantity as our ICP.
``max_iterations``         500 (KISS's default; *not* the preset's cap: point-to-point needs 30-500
                           iterations on lidar-sim, highways the most).
``min_correspondences``    ``cfg.min_correspondences``.
=========================  ===========================================================================

Not used: KISS's odometry front end (deskewing, the scan's voxelisation at 0.5 and 1.5 voxel,
the map update). Every target registers the very scan an attack produced, all of its points.

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
  KISS neighbour (:class:`VoxelNeighbours`: KISS's 27-voxel search over ``_point_cloud()``,
  replicated) lies closer than ``max_corr`` are counted, exactly as KISS's data association does.
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

from icpbench.core.errors import InputError, PluginUnavailableError
from icpbench.core.registry import Range, check_ranges
from icpbench.core.types import validate_cloud
from icpbench.targets.base import Target
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
#: default initial_threshold = THRESHOLD_PER_VOXEL * voxel_size (KISS: 2.0 m at its 1.0 m voxel).
THRESHOLD_PER_VOXEL = 2.0
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


class VoxelNeighbours:
    """KISS-ICP's correspondence search in NumPy: the nearest of the points stored in the 27 voxels
    around a query (``VoxelHashMap::GetClosestNeighbor``), exact, vectorised.

    Every map point within ``voxel_size`` of a query lies in those 27 voxels, so for such queries
    the result is the exact nearest neighbour; farther ones may get a farther point, or none.

    Args:
        points: (K, 3) float64 points kept by KISS's voxel map (map frame).
        voxel_size: KISS's voxel edge; voxel of x is ``floor(x / voxel_size)`` per axis.
    """

    _SHIFTS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)],
                       dtype=np.int64)
    _CHUNK = 4096  # queries per block
    _RANGE = 1 << 20  # voxel coordinates are encoded within +-2^20

    def __init__(self, points: np.ndarray, voxel_size: float) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.voxel_size = float(voxel_size)
        vox = np.floor(self.points / self.voxel_size)
        if np.any(np.abs(vox) >= self._RANGE):
            raise InputError(f"map points must lie within {self._RANGE} voxels of the origin")
        codes = self._codes(vox.astype(np.int64))
        order = np.argsort(codes, kind="stable")
        # voxel keys (sorted) and, per voxel, its run start and length in ``order``
        self.keys, self.start, self.count = np.unique(codes[order], return_index=True,
                                                      return_counts=True)
        self.order = order
        self.stored = np.ascontiguousarray(self.points[order])  # (K, 3) in voxel order

    @staticmethod
    def _codes(v: np.ndarray) -> np.ndarray:
        """One int64 per voxel (K, 3) (each coordinate within +-2^20 voxels)."""
        off = 1 << 20
        return ((v[:, 0] + off) << 42) | ((v[:, 1] + off) << 21) | (v[:, 2] + off)

    def query(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (Q,) and row (Q,) of KISS's neighbour of each query (Q, 3); ``inf`` and K
        where none of the 27 voxels holds a point (or the query is not finite, or farther than
        2^20 voxels from the origin, where no map point is)."""
        d1, _, idx = self.query2(q)
        return d1, idx

    def query2(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`query`, with the distance of the second-nearest point of the 27 voxels
        (``inf`` if there is none): (d1 (Q,), d2 (Q,), idx (Q,))."""
        q = np.asarray(q, dtype=np.float64)
        Q, K = q.shape[0], self.points.shape[0]
        dist, dist2 = np.full(Q, np.inf), np.full(Q, np.inf)
        idx = np.full(Q, K, dtype=np.int64)
        with np.errstate(invalid="ignore", over="ignore"):  # far queries find nothing anyway
            ok = np.flatnonzero((np.abs(q) < (self._RANGE - 2) * self.voxel_size).all(axis=1))
        for lo in range(0, ok.size, self._CHUNK):
            sel = ok[lo:lo + self._CHUNK]
            vox = np.floor(q[sel] / self.voxel_size).astype(np.int64)
            codes = self._codes((vox[:, None, :] + self._SHIFTS[None]).reshape(-1, 3))
            pos = np.minimum(np.searchsorted(self.keys, codes), self.keys.size - 1)
            hit = self.keys[pos] == codes
            # the stored points of every (query, occupied voxel), flat, grouped by query
            hq = np.repeat(np.arange(sel.size), 27)[hit]
            cnt = self.count[pos[hit]]
            if cnt.size == 0:
                continue
            first = np.repeat(self.start[pos[hit]] - (np.cumsum(cnt) - cnt), cnt)
            rows = self.order[first + np.arange(int(cnt.sum()))]
            qi = np.repeat(hq, cnt)
            d2 = ((self.points[rows] - q[sel][qi]) ** 2).sum(1)
            seg = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])  # first candidate of each query
            who = qi[seg]
            best = np.minimum.reduceat(d2, seg)
            n_seg = np.diff(np.r_[seg, qi.size])
            at = np.flatnonzero(d2 == np.repeat(best, n_seg))
            _, one = np.unique(qi[at], return_index=True)  # the first minimum of each query
            idx[sel[who]] = rows[at[one]]
            dist[sel[who]] = np.sqrt(best)
            d2[at[one]] = np.inf
            dist2[sel[who]] = np.sqrt(np.minimum.reduceat(d2, seg))
        return dist, dist2, idx


@dataclass(frozen=True)
class KissMap:
    """A map prepared for KISS-ICP: the voxel hash map and KISS's 27-voxel search over its points."""

    voxel_map: Any  # kiss_icp_pybind._VoxelHashMap
    points: np.ndarray  # (K, 3) float64 points kept by the voxel map (K <= M), map frame
    search: VoxelNeighbours


def kept_points(map_points: np.ndarray, voxel_size: float, max_points_per_voxel: int
                ) -> tuple[Any, np.ndarray]:
    """KISS's voxel hash map of the (M, 3) map (map frame) and the (K, 3) float64 points it keeps
    (at most ``max_points_per_voxel`` per voxel, at least ``voxel / sqrt(max)`` apart)."""
    pts = validate_cloud(map_points, "map", min_points=6).astype(np.float64)
    vmap = kp._VoxelHashMap(voxel_size=voxel_size, max_distance=np.inf,
                            max_points_per_voxel=max_points_per_voxel)
    vmap._add_points(kp._Vector3dVector(np.ascontiguousarray(pts)))
    return vmap, np.asarray(vmap._point_cloud(), dtype=np.float64).reshape(-1, 3)


def _positive(name: str, value: float) -> float:
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a positive number, got {value}")
    return float(value)


def kiss_settings(cfg: ICPConfig, voxel_size: float | None, initial_threshold: float | None,
                  max_corr: float | None, kernel: float | None
                  ) -> tuple[float, float, float, float]:
    """KISS's ``(voxel_size, sigma, max_corr, kernel)`` from the preset ``cfg`` and the explicit
    values given (None: the default of the module docstring's table)."""
    if voxel_size is None:
        if cfg.d_max is None:
            raise InputError("KISS-ICP derives its voxel size from d_max: set d_max or voxel_size")
        voxel_size = cfg.d_max / VOXEL_PER_DMAX
    voxel_size = _positive("voxel_size", voxel_size)
    sigma = _positive("initial_threshold", THRESHOLD_PER_VOXEL * voxel_size
                      if initial_threshold is None else initial_threshold)
    max_corr = _positive("max_corr", 3.0 * sigma if max_corr is None else max_corr)
    kernel = _positive("kernel", sigma / 3.0 if kernel is None else kernel)
    return voxel_size, sigma, max_corr, kernel


class KissICPTarget(BlackBoxTarget):
    """KISS-ICP point-to-point registration of a scan to a fixed voxel map.

    Args:
        preset: ICP preset name (``"lidar"``, ``"objects"``, ``"*-train"``) or ``ICPConfig``; the
            defaults below are derived from it (table in the module docstring).
        voxel_size: voxel edge of the map (preset length units); bounds the neighbour search to 27
            voxels. Default ``d_max / 5``.
        max_points_per_voxel: points KISS keeps per voxel.
        initial_threshold: KISS's adaptive threshold ``sigma`` (its start value, see the module
            docstring). Default ``2 * voxel_size``.
        max_corr: maximum correspondence distance. Default ``3 * sigma``.
        kernel: KISS's robust-kernel parameter (weight ``kernel^2 / (kernel + r^2)^2``, units of
            r^2). Default ``sigma / 3``.
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
        "initial_threshold": Range(0.0, lo_open=True),
        "max_corr": Range(0.0, lo_open=True),
        "kernel": Range(0.0, lo_open=True),
        "max_iterations": Range(1, 1_000_000),
        "threads": Range(1, 1024),
    }
    description: ClassVar[str] = "KISS-ICP point-to-point registration to a voxel map (black box)"
    map_type: ClassVar[type] = KissMap

    def __init__(self, preset: ICPConfig | str | None = "lidar", *,
                 voxel_size: float | None = None, max_points_per_voxel: int = 20,
                 initial_threshold: float | None = None, max_corr: float | None = None,
                 kernel: float | None = None, max_iterations: int = 500, threads: int = 1,
                 **overrides: Any) -> None:
        check_ranges("target 'kiss-icp'", locals(), self.param_ranges)
        cfg = self.config = resolve_preset(preset, overrides, "KISS-ICP")
        self.voxel_size, self.sigma, self.max_corr, self.kernel = kiss_settings(
            cfg, voxel_size, initial_threshold, max_corr, kernel)
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
        vmap, kept = kept_points(map_points, self.voxel_size, self.max_points_per_voxel)
        return KissMap(voxel_map=vmap, points=kept, search=VoxelNeighbours(kept, self.voxel_size))

    def settings(self) -> dict[str, Any]:
        return {
            "library": "kiss-icp",
            "version": kiss_icp.__version__,
            "threads": self.threads,
            "voxel_size": self.voxel_size,
            "initial_threshold": self.sigma,
            "max_points_per_voxel": self.max_points_per_voxel,
            "max_corr": self.max_corr,
            "kernel": self.kernel,
            "max_iterations": self.max_iterations,
            "convergence": self.convergence,
            "min_correspondences": self.min_correspondences,
            "icp_config": config_dict(self.config),
        }

    def replica(self) -> Target:
        """The differentiable replica with these settings (:mod:`icpbench.targets.kiss_replica`)."""
        from icpbench.targets.kiss_replica import KissICPReplica

        return KissICPReplica(self.config, voxel_size=self.voxel_size,
                              max_points_per_voxel=self.max_points_per_voxel,
                              initial_threshold=self.sigma, max_corr=self.max_corr,
                              kernel=self.kernel, max_iterations=self.max_iterations)

    def exact_replica(self) -> Target:
        """The replica (:meth:`replica`), its forward pass compiled: the replica registers every
        scan as KISS does to rounding (0 mm and the same iteration counts on clean and attacked
        lidar-sim scans, results/replica-agreement; the ensemble's every member error equal to
        1e-6 m on the board's scans) at about half KISS's time, and the compiled pass
        (:class:`~icpbench.targets.point_forward.CompiledPointICP`) as the replica does at about
        0.4x the replica's, so it answers the attacks' queries (the rows stay KISS's own
        registrations)."""
        from icpbench.targets.point_forward import CompiledPointICP

        replica = self.replica()
        return CompiledPointICP(replica, replica.config, replica.kiss_map)

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
        d, _ = target.search.query(q)
        ok = d < self.max_corr
        w = self.kernel**2 / (self.kernel + d[ok] ** 2) ** 2
        return int(ok.sum()), point_to_point_hessian(q[ok], w)
