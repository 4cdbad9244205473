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
Its relation ``max_corr = 3 sigma, kernel = sigma`` is kept by the defaults (sigma = 1/3 m).

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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import kiss_icp
import numpy as np
import torch
from kiss_icp.pybind import kiss_icp_pybind as kp
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from icpbench.errors import InputError, PluginUnavailableError
from icpbench.targets.base import Target
from icpbench.types import Registration, validate_cloud

#: kiss-icp versions whose pybind signatures this module was written and tested against.
TESTED_VERSIONS = ((1, 2), (1, 4))  # [1.2, 1.4)
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


@dataclass(frozen=True)
class _One:
    T: np.ndarray
    iterations: int
    converged: bool
    n_inliers: int
    H: np.ndarray | None


class KissICPTarget(Target):
    """KISS-ICP point-to-point registration of a scan to a fixed voxel map.

    Args:
        voxel_size: voxel edge of the map (metres); also bounds the neighbour search (27 voxels).
        max_points_per_voxel: points KISS keeps per voxel.
        max_corr: maximum correspondence distance (metres).
        kernel: KISS's robust-kernel scale (weight ``kernel^2 / (kernel + r^2)^2``, r in metres).
        max_iterations: iteration cap (KISS default 500).
        convergence: stop when the increment norm ``||dx||`` (m and rad mixed) is below this.
        threads: KISS/oneTBB threads, fixed process-wide by the first registration object.
        min_correspondences: fewer inliers than this marks ``too_few_correspondences``.
    """

    name: ClassVar[str] = "kiss-icp"
    description: ClassVar[str] = "KISS-ICP point-to-point registration to a voxel map (black box)"
    differentiable: ClassVar[bool] = False

    def __init__(self, voxel_size: float = 1.0, max_points_per_voxel: int = 20,
                 max_corr: float = 1.0, kernel: float = 1.0 / 3.0, max_iterations: int = 500,
                 convergence: float = 1e-4, threads: int = 1, min_correspondences: int = 6) -> None:
        for nm, v in (("voxel_size", voxel_size), ("max_corr", max_corr), ("kernel", kernel),
                      ("convergence", convergence)):
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{nm} must be a positive number, got {v}")
        if max_points_per_voxel < 1 or max_iterations < 1 or threads < 0:
            raise InputError("max_points_per_voxel and max_iterations must be >= 1, threads >= 0")
        global _threads_fixed
        if _threads_fixed is not None and _threads_fixed != threads:
            raise InputError(
                f"KISS-ICP already fixed its thread count to {_threads_fixed} in this process; "
                f"a target with threads={threads} must run in a separate process"
            )
        self.voxel_size = float(voxel_size)
        self.max_points_per_voxel = int(max_points_per_voxel)
        self.max_corr = float(max_corr)
        self.kernel = float(kernel)
        self.max_iterations = int(max_iterations)
        self.convergence = float(convergence)
        self.threads = int(threads)
        self.min_correspondences = int(min_correspondences)
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

    def register(self, scans: torch.Tensor, maps: Sequence[KissMap],
                 T_init: torch.Tensor) -> Registration:
        """Register each scan (N, 3), sensor frame, to its prepared map; returns float64 T (B, 4, 4)."""
        S, T0 = _batch_to_numpy(scans, maps, T_init, KissMap, "KissICPTarget.prepare")
        outs = [self._register_one(S[b], maps[b], T0[b]) for b in range(S.shape[0])]
        N = S.shape[1]
        status = [_status(o.T, o.n_inliers, o.H, o.converged, self.min_correspondences)
                  for o in outs]
        return Registration(
            T=torch.as_tensor(np.stack([o.T for o in outs]), dtype=torch.float64),
            converged=torch.tensor([s == "ok" for s in status], dtype=torch.bool),
            iterations=torch.tensor([o.iterations for o in outs], dtype=torch.long),
            inlier_fraction=torch.tensor([o.n_inliers / max(N, 1) for o in outs], dtype=torch.float64),
            status=status,
        )

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
        }

    # -- internals --------------------------------------------------------------------------
    def _register_one(self, scan: np.ndarray, target: KissMap, T0: np.ndarray) -> _One:
        pts = np.ascontiguousarray(scan[np.isfinite(scan).all(axis=1)])
        if pts.shape[0] < self.min_correspondences:
            return _One(T=T0.copy(), iterations=0, converged=False, n_inliers=0, H=None)
        vec = kp._Vector3dVector(pts)
        T, converged, it = T0.copy(), False, 0
        while it < self.max_iterations and not converged:
            T_new = np.asarray(self._step._align_points_to_map(
                points=vec, voxel_map=target.voxel_map, initial_guess=T,
                max_correspondance_distance=self.max_corr, kernel=self.kernel), dtype=np.float64)
            it += 1
            if not np.all(np.isfinite(T_new)):
                return _One(T=T_new, iterations=it, converged=False, n_inliers=0, H=None)
            converged = _increment_norm(T, T_new) < self.convergence
            T = T_new
        n_in, H = self._inliers_and_hessian(pts, target, T)
        return _One(T=T, iterations=it, converged=converged, n_inliers=n_in, H=H)

    def _inliers_and_hessian(self, pts: np.ndarray, target: KissMap,
                             T: np.ndarray) -> tuple[int, np.ndarray]:
        """Inlier count at pose T and the KISS-weighted 6x6 point-to-point GN matrix ([rho, phi])."""
        q = pts @ T[:3, :3].T + T[:3, 3]
        d, idx = target.tree.query(q, k=1, distance_upper_bound=min(self.max_corr, self.voxel_size))
        ok = np.isfinite(d)
        q, r2 = q[ok], d[ok] ** 2
        w = self.kernel**2 / (self.kernel + r2) ** 2
        H = np.zeros((6, 6))
        H[:3, :3] = w.sum() * np.eye(3)
        s = (w[:, None] * q).sum(0)
        Hx = np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]])
        H[:3, 3:] = -Hx
        H[3:, :3] = Hx
        H[3:, 3:] = (w * (q * q).sum(1)).sum() * np.eye(3) - (w[:, None] * q).T @ q
        return int(ok.sum()), H


# -- helpers (the same small helpers appear in each black-box target module, so that a missing
#    optional library only disables its own plugin) ----------------------------------------------
def _batch_to_numpy(scans: torch.Tensor, maps: Sequence[Any], T_init: torch.Tensor, map_type: type,
                    prepare_name: str) -> tuple[np.ndarray, np.ndarray]:
    """Check a batch and return float64 scans (B, N, 3) and T_init (B, 4, 4) as NumPy arrays."""
    if not isinstance(scans, torch.Tensor) or scans.ndim != 3 or scans.shape[-1] != 3:
        raise InputError(f"scans must be a (B, N, 3) tensor, got {getattr(scans, 'shape', type(scans))}")
    B = scans.shape[0]
    if len(maps) != B:
        raise InputError(f"got {len(maps)} maps for a batch of {B} scans")
    if tuple(T_init.shape) != (B, 4, 4):
        raise InputError(f"T_init must have shape ({B}, 4, 4), got {tuple(T_init.shape)}")
    for m in maps:
        if not isinstance(m, map_type):
            raise InputError(f"maps must come from {prepare_name}(...), got {type(m).__name__}")
    T0 = T_init.detach().cpu().to(torch.float64).numpy()
    if not np.all(np.isfinite(T0)):
        raise InputError("T_init has NaN or Inf entries")
    return scans.detach().cpu().to(torch.float64).numpy(), T0


def _increment_norm(T_from: np.ndarray, T_to: np.ndarray) -> float:
    """``||log(T_to T_from^-1)||`` of the left increment ``[rho, phi]`` (m and rad mixed), the
    quantity our ICP and KISS test against their tolerance (NumPy: ~40x cheaper than torch here)."""
    D = T_to @ np.linalg.inv(T_from)
    phi = Rotation.from_matrix(D[:3, :3]).as_rotvec()
    th = float(np.linalg.norm(phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    # inverse left Jacobian of SO(3); series 1/12 + th^2/720 near 0
    c = 1 / 12 + th**2 / 720 if th < 1e-4 else 1 / th**2 - (1 + np.cos(th)) / (2 * th * np.sin(th))
    rho = (np.eye(3) - 0.5 * K + c * K @ K) @ D[:3, 3]
    return float(np.sqrt(rho @ rho + th**2))


def _status(T: np.ndarray, n_inliers: int, H: np.ndarray | None, converged: bool,
            min_inliers: int) -> str:
    """ok / nonfinite / too_few_correspondences / singular / not_converged (as in targets/icp.py)."""
    if not np.all(np.isfinite(T)):
        return "nonfinite"
    if n_inliers < min_inliers or H is None:
        return "too_few_correspondences"
    ev = np.linalg.eigvalsh(np.nan_to_num(H))
    if ev[0] <= 1e-10 * max(ev[-1], 1e-300):
        return "singular"
    return "ok" if converged else "not_converged"
