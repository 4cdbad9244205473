"""Target ``small-gicp-replica``: small_gicp's GICP registration as a differentiable ICP.

small_gicp's GICP (Koide, "small_gicp: Efficient and parallel algorithms for point cloud
registration", JOSS 2024) minimises the Generalized-ICP cost (Segal, Haehnel and Thrun, RSS 2009)
``sum_i e_i^T (C_m,i + R C_s,i R^T)^-1 e_i`` with ``e_i = m_i - (R p_i + t)``, ``m_i`` the nearest
map point of the transformed scan point (pairs farther than ``max_correspondence_distance``
rejected) and Levenberg-Marquardt steps on the Gauss-Newton system in which the precision matrix
is evaluated at the current pose and held. This target runs the same fixed-point iteration with
:func:`icpbench.targets.icp.icp` (``mode="gicp"``, :func:`icpbench.targets.icp._gicp_normal_equations`):

* **map covariances** are small_gicp's own: ``small_gicp.estimate_covariances`` on the map, read
  back with ``PointCloud.covs()`` (built once per ``MapIndex`` and cached);
* **scan covariances** are computed here the way small_gicp computes them
  (``estimate_local_features``): the ``num_neighbors`` nearest scan points of each scan point
  (itself included; small_gicp's KD-tree), their covariance ``(sum p p^T - mean sum p^T) / k``,
  its eigenvectors U and ``C = U diag(1e-3, 1, 1) U^T = I - 0.999 n n^T`` (n: the smallest
  eigenvector). The tests check them against small_gicp's. They are differentiable functions of
  the scan points (``scan_cov_grad=True``, default): an attack that moves a point also turns the
  local planes its neighbours see, and small_gicp's pose responds to that through every precision
  matrix of the neighbourhood, a first-order effect of the same size as the residual's own; the
  neighbour *choice* is held, like the correspondences (piecewise constant). Off, they are
  constants of the attacked scan (the gradient of a GICP whose scan covariances were given);
* **stopping**: small_gicp stops when the rotation step is below 0.1 deg *and* the translation step
  below 1e-3; the replica iterates to ``||delta|| < tol`` (1e-4), so it lands on the fixed point
  small_gicp stops near (within about its last step). LM's damping changes the path, not the
  fixed point.

No robust kernel (small_gicp's Python ``align`` has none) and a hard gate ``d < d_max``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.map_cache import PerMapCache
from icpbench.core.mapindex import MapIndex
from icpbench.core.registry import Range, check_ranges
from icpbench.core.types import Registration
from icpbench.targets.base import Target
from icpbench.targets.icp import ICP_RANGES, ICPConfig, config_dict, icp

#: small_gicp's eigenvalues of a regularised covariance (``CovarianceSetter``).
PLANE_EIGENVALUES = (1e-3, 1.0, 1.0)
#: Entries of a symmetric 3x3 matrix in the covariance tables: xx yy zz xy xz yz.
_ROWS, _COLS = (0, 1, 2, 0, 0, 1), (0, 1, 2, 1, 2, 2)


class CovarianceMap(MapIndex):
    """Map points (M, 3) with GICP covariances (M, 3, 3), map frame; the correspondence table rows
    are ``[point | xx yy zz xy xz yz]``."""

    def __init__(self, points: np.ndarray, covariances: np.ndarray) -> None:
        super().__init__(points)
        cov = np.asarray(covariances, dtype=np.float64)
        if cov.shape != (len(self), 3, 3):
            raise InputError(f"covariances must have shape ({len(self)}, 3, 3), got {cov.shape}")
        self.covariances = cov

    def nearest2(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`MapIndex.nearest2`, with a tie (a duplicated map point: ``d2 == d1``) given a
        1e-12 m gap, so the correspondence cache asks such a query again once it moves (with no
        gap at all it would keep the row)."""
        d1, d2, idx = super().nearest2(q)
        tie = np.isfinite(d1) & (d2 <= d1)
        d2[tie] = d1[tie] + 1e-12
        return d1, d2, idx

    def table(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        if dtype not in self._table:
            six = self.covariances[:, _ROWS, _COLS]
            self._table[dtype] = torch.as_tensor(
                np.vstack([np.hstack([self.points, six]), np.zeros((1, 9))]), dtype=dtype)
        return self._table[dtype]


def map_covariances(points: np.ndarray, num_neighbors: int, threads: int = 1) -> np.ndarray:
    """small_gicp's covariances (M, 3, 3) of the (M, 3) map points (``estimate_covariances``)."""
    import small_gicp

    cloud = small_gicp.PointCloud(np.ascontiguousarray(points, dtype=np.float64))
    tree = small_gicp.KdTree(cloud, num_threads=threads)
    small_gicp.estimate_covariances(cloud, tree, num_neighbors, threads)
    return np.asarray(cloud.covs())[:, :3, :3].copy()


def scan_covariances(scans: torch.Tensor, finite: torch.Tensor, num_neighbors: int,
                     grad: bool = True) -> torch.Tensor:
    """GICP covariances of the scan points, computed as small_gicp computes them (module docstring).

    Args:
        scans: (B, N, 3) scan points, sensor frame (may require grad).
        finite: (B, N) bool, the points that take part (others get the identity).
        num_neighbors: k of the k nearest neighbours (the point itself included).
        grad: keep the graph to the scan points (the neighbour choice carries none).

    Returns:
        (B, 6, N) entries ``xx yy zz xy xz yz`` in the scans' dtype (sensor frame).
    """
    import small_gicp

    B, N, _ = scans.shape
    dtype = scans.dtype
    eye6 = torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=dtype)
    cols = []
    with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
        for b in range(B):
            out = eye6[:, None].repeat(1, N)
            sel = np.flatnonzero(finite[b].numpy())
            if sel.size >= 5:  # small_gicp: fewer than 5 neighbours give the identity
                pts = scans[b, torch.as_tensor(sel)]
                p_np = np.ascontiguousarray(pts.detach().to(torch.float64).numpy())
                k = min(num_neighbors, sel.size)
                idx, _ = small_gicp.KdTree(p_np, num_threads=1).batch_knn_search(p_np, k, num_threads=1)
                nb = pts[torch.as_tensor(np.asarray(idx, dtype=np.int64))]  # (F, k, 3)
                mean = nb.mean(1)
                C = nb.transpose(1, 2) @ nb / k - mean[:, :, None] * mean[:, None, :]
                n = torch.linalg.eigh(C)[1][..., 0]  # eigenvector of the smallest eigenvalue
                lo, hi = PLANE_EIGENVALUES[0], PLANE_EIGENVALUES[1]
                cov = hi * torch.eye(3, dtype=dtype) - (hi - lo) * n[:, :, None] * n[:, None, :]
                out = out.index_copy(1, torch.as_tensor(sel), cov[:, _ROWS, _COLS].T)
            cols.append(out)
    return torch.stack(cols)


class SmallGICPReplica(Target):
    """Differentiable replica of :class:`~icpbench.targets.small_gicp.SmallGICPTarget` (GICP).

    Args:
        preset: ICP preset name or ``ICPConfig``: ``d_max`` (max correspondence distance),
            ``max_iterations``, ``tol`` (the replica's own stop), ``backprop``.
        num_neighbors: neighbours of the covariance estimates (small_gicp's 20).
        scan_cov_grad: differentiate the scan covariances (module docstring).
        threads: small_gicp threads for the map covariances.
        **overrides: ``ICPConfig`` fields (``cauchy_c`` is ignored: GICP has no kernel).
    """

    name: ClassVar[str] = "small-gicp-replica"
    description: ClassVar[str] = "small_gicp GICP replicated in PyTorch (differentiable)"
    differentiable: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        **ICP_RANGES, "num_neighbors": Range(5), "threads": Range(1, 1024)}

    def __init__(self, preset: ICPConfig | str | None = "lidar", *, num_neighbors: int = 20,
                 scan_cov_grad: bool = True, threads: int = 1, **overrides: Any) -> None:
        check_ranges("target 'small-gicp-replica'", locals(), self.param_ranges)
        from icpbench.targets.blackbox import resolve_preset

        cfg = resolve_preset(preset, overrides, "small-gicp-replica")
        if cfg.d_max is None:
            raise InputError("small_gicp needs a finite max correspondence distance: set d_max")
        if num_neighbors < 5 or threads < 1:
            raise InputError("need num_neighbors >= 5 and threads >= 1")
        self.config = cfg.with_(cauchy_c=None, nn_reuse_m=0.0)
        self.num_neighbors = int(num_neighbors)
        self.scan_cov_grad = bool(scan_cov_grad)
        self.threads = int(threads)
        self._maps: PerMapCache[CovarianceMap] = PerMapCache()

    def with_settings(self, **changes: Any) -> SmallGICPReplica:
        out = SmallGICPReplica(self.config.with_(**changes), num_neighbors=self.num_neighbors,
                               scan_cov_grad=self.scan_cov_grad, threads=self.threads)
        out._maps = self._maps
        return out

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None = None) -> MapIndex:
        return MapIndex(map_points, map_normals, workers=self.config.kdtree_workers)

    def covariance_map(self, m: MapIndex) -> CovarianceMap:
        """The map with small_gicp's covariances (built once per ``MapIndex`` object, cached)."""
        return self._maps.get(m, lambda m: CovarianceMap(
            m.points, map_covariances(m.points, self.num_neighbors, self.threads)))

    def register(self, scans: torch.Tensor, maps: Sequence[MapIndex],
                 T_init: torch.Tensor) -> Registration:
        """Register scans (B, N, 3), sensor frame, to the batch's maps from T_init (B, 4, 4)."""
        if not isinstance(scans, torch.Tensor) or scans.ndim != 3 or scans.shape[-1] != 3:
            raise InputError(f"scans must be a (B, N, 3) tensor, got {getattr(scans, 'shape', None)}")
        cmaps = [self.covariance_map(m) for m in maps]
        finite = torch.isfinite(scans.detach()).all(-1)
        clean = torch.where(finite[..., None], scans, torch.zeros((), dtype=scans.dtype))
        cov = scan_covariances(clean, finite, self.num_neighbors, self.scan_cov_grad)
        return icp(scans, cmaps, T_init, self.config, mode="gicp", scan_cov=cov)

    def settings(self) -> dict[str, Any]:
        return {"replica_of": "small-gicp", "registration_type": "GICP", "mode": "gicp",
                "num_neighbors": self.num_neighbors, "scan_cov_grad": self.scan_cov_grad,
                **config_dict(self.config)}
