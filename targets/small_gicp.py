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
``rotation_epsilon`` (rad) *and* translation increment below ``translation_epsilon`` (m).

Guards against known failures of small_gicp 1.0.1 (measured, see ``research/targets.md`` §5):

* an **empty map segfaults** the process: :meth:`prepare` rejects maps with fewer than 6 points (and
  NaN/Inf map points) with :class:`~icpbench.errors.InputError`;
* a **single NaN/Inf scan point freezes** the optimiser at ``T_init`` (NaN pairs pass its distance
  rejector, so H is NaN): non-finite scan points are dropped before the call. The status does not
  change because of that; ``inlier_fraction`` is still relative to all N points, so dropped points
  count as outliers. Fewer than ``min_correspondences`` finite points give status
  ``too_few_correspondences`` with ``T = T_init``.

Note (``research/targets.md`` §6): small_gicp's PLANE_ICP minimises the element-wise product
``n * r`` (3 residuals per point), not the textbook ``(n . r)^2`` of Open3D and our ``p2plane``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from importlib.metadata import version
from typing import Any, ClassVar, Literal

import numpy as np
import small_gicp
import torch

from icpbench.errors import InputError
from icpbench.targets.base import Target
from icpbench.types import Registration, validate_cloud

RegistrationType = Literal["GICP", "PLANE_ICP", "ICP"]


@dataclass(frozen=True)
class SmallGICPMap:
    """A map prepared for small_gicp: point cloud (with normals/covariances as needed) and KD-tree."""

    cloud: Any  # small_gicp.PointCloud
    tree: Any  # small_gicp.KdTree
    size: int


class SmallGICPTarget(Target):
    """small_gicp registration of a scan to a fixed map.

    Args:
        registration_type: ``"GICP"`` (default), ``"PLANE_ICP"`` or ``"ICP"``.
        max_corr: maximum correspondence distance (metres).
        max_iterations: iteration cap.
        rotation_epsilon: convergence threshold on the rotation increment (rad).
        translation_epsilon: convergence threshold on the translation increment (m).
        num_neighbors: neighbours used to estimate normals/covariances.
        threads: OpenMP threads passed to every small_gicp call.
        min_correspondences: fewer inliers than this marks ``too_few_correspondences``.
    """

    name: ClassVar[str] = "small-gicp"
    description: ClassVar[str] = "small_gicp GICP (or PLANE_ICP / ICP) registration (black box)"
    differentiable: ClassVar[bool] = False

    def __init__(self, registration_type: RegistrationType = "GICP", max_corr: float = 1.0,
                 max_iterations: int = 100, rotation_epsilon: float = np.deg2rad(0.1),
                 translation_epsilon: float = 1e-3, num_neighbors: int = 20, threads: int = 1,
                 min_correspondences: int = 6) -> None:
        if registration_type not in ("GICP", "PLANE_ICP", "ICP"):
            raise InputError(
                f"registration_type must be 'GICP', 'PLANE_ICP' or 'ICP', got {registration_type!r}"
            )
        for nm, v in (("max_corr", max_corr), ("rotation_epsilon", rotation_epsilon),
                      ("translation_epsilon", translation_epsilon)):
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{nm} must be a positive number, got {v}")
        if max_iterations < 1 or num_neighbors < 5 or threads < 1:
            raise InputError("need max_iterations >= 1, num_neighbors >= 5 and threads >= 1")
        self.registration_type = registration_type
        self.max_corr = float(max_corr)
        self.max_iterations = int(max_iterations)
        self.rotation_epsilon = float(rotation_epsilon)
        self.translation_epsilon = float(translation_epsilon)
        self.num_neighbors = int(num_neighbors)
        self.threads = int(threads)
        self.min_correspondences = int(min_correspondences)

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

    def register(self, scans: torch.Tensor, maps: Sequence[SmallGICPMap],
                 T_init: torch.Tensor) -> Registration:
        """Register each scan (N, 3), sensor frame, to its prepared map; returns float64 T (B, 4, 4)."""
        S, T0 = _batch_to_numpy(scans, maps, T_init, SmallGICPMap, "SmallGICPTarget.prepare")
        B, N = S.shape[:2]
        Ts, conv, iters, inl, status = [], [], [], [], []
        for b in range(B):
            T, c, it, n_in, H = self._register_one(S[b], maps[b], T0[b])
            s = _status(T, n_in, H, c, self.min_correspondences)
            Ts.append(T)
            conv.append(s == "ok")
            iters.append(it)
            inl.append(n_in / max(N, 1))
            status.append(s)
        return Registration(
            T=torch.as_tensor(np.stack(Ts), dtype=torch.float64),
            converged=torch.tensor(conv, dtype=torch.bool),
            iterations=torch.tensor(iters, dtype=torch.long),
            inlier_fraction=torch.tensor(inl, dtype=torch.float64),
            status=status,
        )

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
        }

    # -- internals --------------------------------------------------------------------------
    def _register_one(self, scan: np.ndarray, target: SmallGICPMap,
                      T0: np.ndarray) -> tuple[np.ndarray, bool, int, int, np.ndarray | None]:
        """Returns (T (4, 4), converged, iterations, inliers, H (6, 6) or None if not run)."""
        pts = np.ascontiguousarray(scan[np.isfinite(scan).all(axis=1)])
        if pts.shape[0] < self.min_correspondences:
            return T0.copy(), False, 0, 0, None
        source = small_gicp.PointCloud(pts)
        if self.registration_type == "GICP":
            small_gicp.estimate_covariances(source, small_gicp.KdTree(source, num_threads=self.threads),
                                            self.num_neighbors, self.threads)
        res = small_gicp.align(
            target.cloud, source, target.tree, init_T_target_source=T0,
            registration_type=self.registration_type, max_correspondence_distance=self.max_corr,
            num_threads=self.threads, max_iterations=self.max_iterations,
            rotation_epsilon=self.rotation_epsilon, translation_epsilon=self.translation_epsilon,
        )
        T = np.array(res.T_target_source, dtype=np.float64)
        return T, bool(res.converged), int(res.iterations), int(res.num_inliers), np.asarray(res.H)


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
