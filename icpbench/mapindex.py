"""A map prepared once for nearest-neighbour queries: points, normals and a KD-tree.

Nearest neighbours come from SciPy's ``cKDTree`` (measured ~500x faster than a dense ``torch.cdist``
at lidar sizes on the 2-core CPU: 10k queries into 50k points in 6 ms versus 3.3 s).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from icpbench.errors import InputError


class MapIndex:
    """Map points (M, 3), unit normals (M, 3) and a KD-tree over the points (map frame, metres)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray | None = None,
                 workers: int = 1) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
            raise InputError(f"map must be a non-empty (M, 3) array, got shape {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise InputError("map has NaN or Inf coordinates")
        self.points = pts
        self.normals = None
        if normals is not None:
            nrm = np.ascontiguousarray(normals, dtype=np.float64)
            if nrm.shape != pts.shape:
                raise InputError(f"map normals have shape {nrm.shape}, expected {pts.shape}")
            self.normals = nrm
        self.workers = workers
        self.tree = cKDTree(pts)
        self._torch: dict[torch.dtype, tuple[torch.Tensor, torch.Tensor | None]] = {}

    def __len__(self) -> int:
        return self.points.shape[0]

    def tensors(self, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(points, normals) as tensors of ``dtype``, padded with one sentinel row at index M
        (used for 'no neighbour'); cached per dtype."""
        if dtype not in self._torch:
            p = torch.as_tensor(np.vstack([self.points, np.zeros((1, 3))]), dtype=dtype)
            n = None
            if self.normals is not None:
                n = torch.as_tensor(np.vstack([self.normals, np.zeros((1, 3))]), dtype=dtype)
            self._torch[dtype] = (p, n)
        return self._torch[dtype]

    def query(self, q: np.ndarray, max_dist: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Nearest map point of each query (K, 3).

        Returns (dist (K,), idx (K,)); queries with no map point within ``max_dist`` or with
        non-finite coordinates get ``dist = inf`` and ``idx = M`` (the sentinel row).
        """
        q = np.asarray(q, dtype=np.float64)
        finite = np.isfinite(q).all(axis=1)
        dist = np.full(q.shape[0], np.inf)
        idx = np.full(q.shape[0], len(self), dtype=np.int64)
        if finite.any():
            d, i = self.tree.query(q[finite], k=1, distance_upper_bound=max_dist,
                                   workers=self.workers)
            dist[finite] = d
            idx[finite] = i
        return dist, idx
