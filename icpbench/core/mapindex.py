"""A map prepared once for nearest-neighbour queries: points, normals and a KD-tree.

Nearest neighbours come from small_gicp's ``KdTree`` (nanoflann-style, exact). Measured on the
2-core CPU, 1 thread, CPU-time medians (docs/performance.md): 10,000 queries into a
100,000-point map took 5.4 ms with small_gicp against 8.2 ms with pykdtree and 12.8 ms with
SciPy's ``cKDTree`` (2,048 into 10,000: 0.76 / 1.14 / 1.69 ms); Open3D's tensor
``NearestNeighborSearch`` took 12 ms.
Results are identical (exact search). A dense ``torch.cdist`` was ~500x slower than any tree.

Single nearest neighbours (:meth:`MapIndex.query`, the attacks' plans) split the queries: one
inside the map's bounding box goes to small_gicp's tree, one outside (metres from every map point:
a long-range scan point beyond a map crop, a plan's candidate moved off it) to SciPy's ``cKDTree``
(built unbalanced, 32 points per leaf, loose node boxes), which backtracks far less for such a
query. Measured on the ``unseen`` town's valley plans (1.26 M queries into a 57,000-62,000-point
map, 1 thread; a scan with half its plan's queries metres away / one with a quarter):
small_gicp alone 1.28 / 0.50 s, ``cKDTree`` alone 0.78 / 0.78 s, split 0.59 / 0.46 s, the box
test included; both trees give the same nearest indices (a map with a duplicated point keeps
small_gicp's tree for every query: either tree may name either copy). The far queries' distances
are formed from the index in small_gicp's order of summation, ``(dx^2 + dz^2) + dy^2``, which
equals its squared distance to the bit (all 1.26 M queries), so the attacks' plans are unchanged.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from icpbench.core.errors import InputError

#: Growth of the map's bounding box, as a share of its longest side, inside which
#: :meth:`MapIndex.near_map` sends a query to small_gicp's tree (the split below was measured
#: with it).
BOX_MARGIN = 0.02


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
        self._far: cKDTree | None = None
        self._box: tuple[np.ndarray, np.ndarray] | None = None
        self._torch: dict[torch.dtype, tuple[torch.Tensor, torch.Tensor | None]] = {}
        self._table: dict[torch.dtype, torch.Tensor] = {}

    def __len__(self) -> int:
        return self.points.shape[0]

    def __getstate__(self) -> dict[str, Any]:
        # the native tree does not pickle: it is rebuilt on first use after unpickling (and the
        # SciPy tree, cheaper to rebuild than to send)
        return {**self.__dict__, "_tree": None, "_far": None, "_box": None}

    @property
    def tree(self) -> Any:
        """The small_gicp ``KdTree`` over the points (built on first use)."""
        if self._tree is None:
            import small_gicp  # imported on first use: modules that only name MapIndex stay light

            self._tree = small_gicp.KdTree(self.points, num_threads=self.workers)
        return self._tree

    @property
    def far_tree(self) -> cKDTree:
        """SciPy's ``cKDTree`` over the points, for queries far from the map (module docstring;
        built on first use: unbalanced, 32 points per leaf, loose node boxes)."""
        if self._far is None:
            self._far = cKDTree(self.points, leafsize=32, balanced_tree=False,
                                compact_nodes=False)
        return self._far

    def near_map(self, q: np.ndarray) -> np.ndarray:
        """(K,) bool: finite query ``q`` (K, 3) lies in the map's bounding box grown by
        :data:`BOX_MARGIN` of its longest side (the queries small_gicp's tree answers fastest;
        one outside is far from every map point). Every query counts as near on a map with a
        duplicated point: there the two trees may name different copies, and small_gicp's choice
        is the one every result before the split was made with. Only decides which tree answers
        a query; both are exact."""
        if self._box is None:
            lo, hi = self.points.min(axis=0), self.points.max(axis=0)
            margin = BOX_MARGIN * float((hi - lo).max())
            if np.unique(self.points, axis=0).shape[0] < self.points.shape[0]:
                lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
            self._box = (lo - margin, hi + margin)
        lo, hi = self._box
        return ((q >= lo) & (q <= hi)).all(axis=1)

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
        non-finite coordinates get ``dist = inf`` and ``idx = M`` (the sentinel row). A finite
        ``max_dist`` also bounds the search (far queries cost less); the result is the same as an
        unbounded search's cut at ``max_dist``.
        """
        d1, _, idx = self._nearest1(q, max_dist)
        far = ~(d1 < max_dist)
        d1[far], idx[far] = np.inf, len(self)
        return d1, idx

    def _nearest1(self, q: np.ndarray, bound: float = np.inf) -> tuple[np.ndarray, None, np.ndarray]:
        """Like :meth:`nearest2` without the second neighbour (module docstring: queries near the
        map from small_gicp's tree, far ones from :attr:`far_tree`); a far query whose nearest map
        point is not within ``bound`` (a little more: the trees' distances round differently)
        may come back as none (``inf``, ``M``)."""
        q = np.asarray(q, dtype=np.float64)
        K, M = q.shape[0], len(self)
        d1, idx = np.full(K, np.inf), np.full(K, M, dtype=np.int64)
        finite = np.isfinite(q).all(axis=1)
        if finite.any():
            qf = q if finite.all() else q[finite]
            rows = np.flatnonzero(finite)
            near = self.near_map(qf)
            if near.any():
                i, d2 = self.tree.batch_knn_search(np.ascontiguousarray(qf[near]), 1,
                                                   num_threads=self.workers)
                i = np.asarray(i).astype(np.int64)[:, 0]  # none: 2**64 - 1 -> -1
                d = np.sqrt(np.asarray(d2, dtype=np.float64)[:, 0])
                good = (i >= 0) & (i < M) & np.isfinite(d)
                sel = rows[near][good]
                d1[sel], idx[sel] = d[good], i[good]
            if not near.all():
                far = qf[~near]
                reach = bound * (1.0 + 1e-9) + 1e-9 if np.isfinite(bound) else np.inf
                i = self.far_tree.query(far, k=1, distance_upper_bound=reach)[1]
                found = np.flatnonzero(i < M)
                x = far[found] - self.points[i[found]]
                # small_gicp's order of summation (module docstring): its distances to the bit
                d = np.sqrt((x[:, 0] * x[:, 0] + x[:, 2] * x[:, 2]) + x[:, 1] * x[:, 1])
                good = np.isfinite(d)
                sel = rows[~near][found[good]]
                d1[sel], idx[sel] = d[good], i[found[good]]
        return d1, None, idx
