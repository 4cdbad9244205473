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
``cfg.tol`` (on ||delta||)  ``relative_fitness = 1e-6`` and ``relative_rmse`` = ``0.01 * tol``
                            (point-to-plane) or ``tol**2`` (point-to-point), metres. Open3D stops when
                            its inlier RMSE (of 3-D NN distances) changes by less than that *and* the
                            inlier count is unchanged (fitness moves in steps of 1/N, so 1e-6 means
                            "no change" for N < 10^6). Open3D has no test on the pose increment, so
                            the factor was calibrated on the synthetic scene: near convergence
                            point-to-plane gave |d rmse| = 0.005-0.02 x ||delta|| (the RMSE is not
                            the minimised cost, so its change is first order in the step; for the
                            paper's tol = 1e-4 this is Open3D's own default 1e-6), point-to-point
                            gave |d rmse| = 0.5-2 x ||delta||^2 (the RMSE *is* the minimised cost).
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
from scipy.spatial.transform import Rotation

from icpbench.errors import InputError
from icpbench.targets.base import Target
from icpbench.targets.icp import ICPConfig, config_dict, icp_config
from icpbench.types import Registration, validate_cloud

_reg = o3d.pipelines.registration

#: Open3D's relative-fitness threshold (its own default); see the module docstring.
RELATIVE_FITNESS = 1e-6
#: point-to-plane: relative_rmse = RMSE_PER_STEP * tol; see the module docstring.
RMSE_PER_STEP = 1e-2


@dataclass(frozen=True)
class Open3DMap:
    """A map prepared for Open3D: the point cloud (with normals) and NumPy copies (map frame)."""

    cloud: Any  # open3d.geometry.PointCloud
    points: np.ndarray  # (M, 3) float64
    normals: np.ndarray | None  # (M, 3) float64 unit normals (point-to-plane), else None


@dataclass(frozen=True)
class _One:
    """Raw outcome of one sample before the health check."""

    T: np.ndarray
    n_inliers: int
    step: float  # norm of the convergence-check increment (inf if not run)
    H: np.ndarray | None
    iterations: int = -1  # -1: Open3D ran (count unknown); 0: not called


class Open3DICP(Target):
    """Open3D ``registration_icp`` (point-to-plane or point-to-point), configured like ``p2plane``.

    Args:
        config: an ICP preset name (``"lidar"``, ``"objects"``, ``"*-train"``) or an ``ICPConfig``;
            same meaning as for :class:`~icpbench.targets.p2plane.PointToPlaneICP`.
        mode: ``"plane"`` (point-to-plane, needs map normals) or ``"point"`` (point-to-point; Open3D
            has no robust kernel for it, so ``cauchy_c`` must be ``None``).
        threads: Open3D's process-wide thread cap (``open3d.utility.set_max_threads``); 0 = auto.
        **overrides: ``ICPConfig`` fields to replace (e.g. ``d_max=2.0``, ``cauchy_c=None``).
    """

    name: ClassVar[str] = "open3d"
    description: ClassVar[str] = (
        "Open3D registration_icp point-to-plane (or point-to-point), black box, same settings as p2plane"
    )
    differentiable: ClassVar[bool] = False

    def __init__(self, config: ICPConfig | str | None = "lidar", *,
                 mode: Literal["plane", "point"] = "plane", threads: int = 1,
                 **overrides: Any) -> None:
        self.config = icp_config(config, **overrides)
        if mode not in ("plane", "point"):
            raise InputError(f"mode must be 'plane' or 'point', got {mode!r}")
        if self.config.d_max is None:
            raise InputError("Open3D needs a finite max correspondence distance: set d_max")
        if self.config.soft_dmax:
            raise InputError("Open3D has no smooth d_max gate: use soft_dmax=False")
        if mode == "point" and self.config.cauchy_c is not None:
            raise InputError(
                "Open3D's point-to-point estimator has no robust kernel: pass cauchy_c=None"
            )
        if threads < 0:
            raise InputError(f"threads must be >= 0 (0 = automatic), got {threads}")
        self.mode = mode
        self.threads = threads

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
        """Register each scan (N, 3), sensor frame, to its prepared map; returns float64 T (B, 4, 4)."""
        S, T0 = _batch_to_numpy(scans, maps, T_init, Open3DMap, "Open3DICP.prepare")
        o3d.utility.set_max_threads(self.threads)
        outs = [self._register_one(S[b], maps[b], T0[b]) for b in range(S.shape[0])]
        return self._assemble(outs, T0, S.shape[1])

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

    def _register_one(self, scan: np.ndarray, target: Open3DMap, T0: np.ndarray) -> _One:
        pts = scan[np.isfinite(scan).all(axis=1)]
        if pts.shape[0] < self.config.min_correspondences:
            return _One(T=T0.copy(), n_inliers=0, step=np.inf, H=None, iterations=0)
        source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        cfg, est = self.config, self._estimator()
        crit = _reg.ICPConvergenceCriteria(relative_fitness=RELATIVE_FITNESS,
                                           relative_rmse=self._relative_rmse(),
                                           max_iteration=cfg.max_iterations)
        res = _reg.registration_icp(source, target.cloud, cfg.d_max, T0, est, crit)
        T = np.array(res.transformation, dtype=np.float64)
        corr = np.asarray(res.correspondence_set, dtype=np.int64).reshape(-1, 2)
        if not np.all(np.isfinite(T)):
            return _One(T=T, n_inliers=corr.shape[0], step=np.inf, H=None)
        one = _reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
        T_extra = np.asarray(_reg.registration_icp(source, target.cloud, cfg.d_max, T, est, one)
                             .transformation)
        step = _increment_norm(T, T_extra)
        return _One(T=T, n_inliers=corr.shape[0], step=step, H=self._hessian(pts, target, T, corr))

    def _hessian(self, pts: np.ndarray, target: Open3DMap, T: np.ndarray,
                 corr: np.ndarray) -> np.ndarray:
        """6x6 Gauss-Newton matrix (order [rho, phi]) at pose T from Open3D's correspondences."""
        q = pts[corr[:, 0]] @ T[:3, :3].T + T[:3, 3]
        m = target.points[corr[:, 1]]
        if self.mode == "plane":
            n = target.normals[corr[:, 1]]
            r = np.einsum("ij,ij->i", q - m, n)
            w = np.ones_like(r) if self.config.cauchy_c is None else 1 / (1 + (r / self.config.cauchy_c) ** 2)
            J = np.concatenate([n, np.cross(q, n)], axis=1)  # (K, 6)
            return (J * w[:, None]).T @ J
        # point-to-point, unweighted: sum_k [I, -[q]x]^T [I, -[q]x]
        K = q.shape[0]
        H = np.zeros((6, 6))
        H[:3, :3] = K * np.eye(3)
        s = q.sum(0)
        Hx = np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]])
        H[:3, 3:] = -Hx
        H[3:, :3] = Hx
        H[3:, 3:] = (q * q).sum() * np.eye(3) - q.T @ q
        return H

    def _assemble(self, outs: list[_One], T0: np.ndarray, N: int) -> Registration:
        status = [_status(o.T, o.n_inliers, o.H, o.step < self.config.tol,
                          self.config.min_correspondences) for o in outs]
        return Registration(
            T=torch.as_tensor(np.stack([o.T for o in outs]), dtype=torch.float64),
            converged=torch.tensor([s == "ok" for s in status], dtype=torch.bool),
            iterations=torch.tensor([o.iterations for o in outs], dtype=torch.long),
            inlier_fraction=torch.tensor([o.n_inliers / max(N, 1) for o in outs], dtype=torch.float64),
            status=status,
        )


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
