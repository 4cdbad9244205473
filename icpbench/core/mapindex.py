"""A map prepared once for nearest-neighbour queries: points, normals and a KD-tree.

Nearest neighbours come from small_gicp's ``KdTree`` (nanoflann-style, exact). Measured on the
2-core CPU, 1 thread, CPU-time medians (docs/performance.md): 10,000 queries into a
100,000-point map took 5.4 ms with small_gicp against 8.2 ms with pykdtree and 12.8 ms with
SciPy's ``cKDTree`` (2,048 into 10,000: 0.76 / 1.14 / 1.69 ms); Open3D's tensor
``NearestNeighborSearch`` took 12 ms.
Results are identical (exact search). A dense ``torch.cdist`` was ~500x slower than any tree.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from icpbench.core.errors import InputError


class MapIndex:
    """Map points (M, 3), unit normals (M, 3) and a KD-tree over the points (map frame, metres)."""

    #: :meth:`nearest2`'s row is the exact nearest map point (the KD-tree's) for every query
    #: closer than this to it (metres); a subclass with a neighbour rule of its own lowers it
    #: (KISS-ICP's replica map: one voxel), so that the compiled forward pass
    #: (``targets/point_forward.py``) may answer such queries from its candidate lists.
    exact_within: float = float("inf")
    #: A voxel neighbour rule of KISS-ICP's kind (:class:`~icpbench.targets.kiss.VoxelNeighbours`)
    #: that :meth:`nearest2` answers by beyond ``exact_within``, for the compiled forward pass to
    #: run itself; None: :meth:`nearest2` only.
    voxel_search: Any = None

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
        self.workers = max(1, int(workers))
        self._tree: Any = None
        self._torch: dict[torch.dtype, tuple[torch.Tensor, torch.Tensor | None]] = {}
        self._table: dict[torch.dtype, torch.Tensor] = {}

    def __len__(self) -> int:
        return self.points.shape[0]

    def __getstate__(self) -> dict[str, Any]:
        # the native tree does not pickle: it is rebuilt on first use after unpickling
        return {**self.__dict__, "_tree": None}

    @property
    def tree(self) -> Any:
        """The small_gicp ``KdTree`` over the points (built on first use)."""
        if self._tree is None:
            import small_gicp  # imported on first use: modules that only name MapIndex stay light

            self._tree = small_gicp.KdTree(self.points, num_threads=self.workers)
        return self._tree

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

    def table(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """(M + 1, 6) tensor ``[points | normals]`` (zero normals if the map has none) with the
        sentinel row of zeros at index M: one gather fetches a correspondence's point and normal.
        Cached per dtype."""
        if dtype not in self._table:
            nrm = self.normals if self.normals is not None else np.zeros_like(self.points)
            self._table[dtype] = torch.as_tensor(
                np.vstack([np.hstack([self.points, nrm]), np.zeros((1, 6))]), dtype=dtype)
        return self._table[dtype]

    def nearest2(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest and second-nearest map distance and the nearest index of queries (K, 3).

        Returns (d1 (K,), d2 (K,), idx (K,) int64), no distance bound; ``d2 = inf`` when the map
        has a single point. Queries the tree cannot answer (non-finite, or so far away that the
        squared distance overflows) get ``d1 = d2 = inf`` and ``idx = M`` (the sentinel row).
        Used by the ICP to know how far a query may move before its nearest neighbour can change
        (by less than ``(d2 - d1) / 2`` it cannot: triangle inequality).
        """
        q = np.asarray(q, dtype=np.float64)
        K, M = q.shape[0], len(self)
        d1, d2 = np.full(K, np.inf), np.full(K, np.inf)
        idx = np.full(K, M, dtype=np.int64)
        finite = np.isfinite(q).all(axis=1)
        if not finite.any():
            return d1, d2, idx
        k = 1 if M < 2 else 2
        i, d = self.tree.batch_knn_search(np.ascontiguousarray(q[finite]), k,
                                          num_threads=self.workers)
        i = np.asarray(i).astype(np.int64)  # "no neighbour" comes back as 2**64 - 1 -> -1
        d = np.sqrt(np.asarray(d, dtype=np.float64))
        good = (i[:, 0] >= 0) & (i[:, 0] < M) & np.isfinite(d[:, 0])
        sel = np.flatnonzero(finite)[good]
        d1[sel], idx[sel] = d[good, 0], i[good, 0]
        if k == 2:
            d2[sel] = np.where((i[good, 1] >= 0) & (i[good, 1] < M), d[good, 1], np.inf)
        return d1, d2, idx

    def query(self, q: np.ndarray, max_dist: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Nearest map point of each query (K, 3).

        Returns (dist (K,), idx (K,)); queries with no map point closer than ``max_dist`` or with
        non-finite coordinates get ``dist = inf`` and ``idx = M`` (the sentinel row).
        """
        d1, _, idx = self._nearest1(q)
        far = ~(d1 < max_dist)
        d1[far], idx[far] = np.inf, len(self)
        return d1, idx

    def _nearest1(self, q: np.ndarray) -> tuple[np.ndarray, None, np.ndarray]:
        """Like :meth:`nearest2` without the second neighbour (k = 1 is cheaper)."""
        q = np.asarray(q, dtype=np.float64)
        K, M = q.shape[0], len(self)
        d1, idx = np.full(K, np.inf), np.full(K, M, dtype=np.int64)
        finite = np.isfinite(q).all(axis=1)
        if finite.any():
            i, d = self.tree.batch_knn_search(np.ascontiguousarray(q[finite]), 1,
                                              num_threads=self.workers)
            i = np.asarray(i).astype(np.int64)[:, 0]
            d = np.sqrt(np.asarray(d, dtype=np.float64)[:, 0])
            good = (i >= 0) & (i < M) & np.isfinite(d)
            sel = np.flatnonzero(finite)[good]
            d1[sel], idx[sel] = d[good], i[good]
        return d1, None, idx
