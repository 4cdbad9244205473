"""Index precompute for the PointNet++ generator: everything the network gathers, from the clean scan.

The generator (Zhang et al., ICRA 2025, §III-B; PointNet++ by Qi et al., NeurIPS 2017) only needs
*indices* and *interpolation weights* that depend on the clean scan X, never on the perturbed one.
They are computed here once per sample, outside autograd, with Open3D's farthest-point sampler
(C++) and small_gicp KD-trees (the same neighbours as SciPy's ``cKDTree``, 1.7x faster for the
seven kNN queries of a 10,000-point scan: 42 vs 72 ms, docs/performance.md), so the training loop
only gathers and runs shared MLPs.

Levels and index spaces (``n1 = N``, ``n_k = floor(N / a_k)`` with ``(a_2, a_3, a_4) = (a, b, c)``):

* level 1: all N points in their original order (identity centroids);
* levels 2-4: the first ``n_2``, ``n_3``, ``n_4`` points of ONE farthest-point sampling (FPS)
  sequence, so level 4 is a subset of level 3 and level 3 of level 2. ``fps_idx`` lists the
  level-2 points so that every level is a prefix: the FPS start, the rest of level 4, then the
  points of level 3 not in level 4, then those of level 2 not in level 3, each part in increasing
  scan index. Level-k points are ``X[fps_idx[:n_k]]`` and level-k features are stored in that
  order, so an index into level k is a position in ``fps_idx``. The order inside a part is not
  the order in which FPS picked the points: the network is invariant to it (kNN groups, max
  pooling and interpolation do not see it), so it changes outputs only by float rounding;
* ``groups[0]`` (B, N, K): K nearest level-1 points of every point (itself included);
  ``groups[k-1]`` (B, n_k, K): K nearest level-(k-1) points of every level-k point, as indices
  into level k-1 (level 1: into the N scan points);
* ``interp_idx[j]``/``interp_w[j]`` (B, N, k_interp), j = 0, 1, 2 for levels 2, 3, 4: the k_interp
  nearest level-k points of every scan point and normalised inverse-distance weights
  ``w_i = d_i^-p / sum_j d_j^-p`` with ``p = idw_power``. Default ``p = 2``: PointNet++ eq. (2)
  and the implementation the paper cites (yanx27/Pointnet_Pointnet2_pytorch) weight by inverse
  *squared* distance; the paper's wording "inversely proportional to their distances" is also
  available as ``p = 1``.

FPS is vanilla FPS (Eldar et al., ICPR 1994) from Open3D's
``farthest_point_down_sample`` in double precision: once on the scan for level 2, then on level 2
for level 3 and on level 3 for level 4 (FPS restricted to a set that contains the first m picks
makes the same first m picks, because each pick is the farthest point of the whole scan and so of
any subset holding it). It returns the level *sets* of fpsample's float32 vanilla FPS
(:func:`farthest_point_indices`, used before; the shipped models were trained with it): identical
sets on all 50 lidar-sim scans compared (25 test, 25 train), at 40 instead of 80 ms for a
10,000-point scan (docs/performance.md). The two can differ only where two candidates' distances
tie within float32 rounding.

Determinism and permutation equivariance: nothing is random. The FPS start is the point farthest
from the centroid (ties, within 1e-12 relative, broken by the lexicographically largest
coordinates), so permuting the input points permutes level 1 and leaves the level 2-4 point sets
unchanged (their order inside a part follows the scan index). Exact ties inside FPS or kNN
(duplicate points, symmetric layouts) are broken by index order by the libraries, so equivariance
holds for clouds in general position.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import fpsample
import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.types import validate_cloud


@dataclass(frozen=True)
class GeometryConfig:
    """Parameters of the index precompute.

    Attributes:
        a, b, c: level-2/3/4 point counts are ``floor(N / a)``, ``floor(N / b)``, ``floor(N / c)``
            (paper: 2, 4, 8 for objects with N = 2,048; 3, 12, 48 for lidar with N = 10,000);
            ``1 <= a <= b <= c``.
        k: neighbours per set-abstraction group (K = 32).
        k_interp: neighbours of the inverse-distance interpolation (3).
        idw_power: exponent p of the interpolation weights ``d^-p`` (2: PointNet++; 1: 1/d).
    """

    a: float = 2.0
    b: float = 4.0
    c: float = 8.0
    k: int = 32
    k_interp: int = 3
    idw_power: float = 2.0

    def __post_init__(self) -> None:
        for name in ("a", "b", "c", "idw_power"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise InputError(f"{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))  # 2 and 2.0 serialise alike
        if not 1.0 <= self.a <= self.b <= self.c:
            raise InputError(f"need 1 <= a <= b <= c for nested levels, got a, b, c = "
                             f"{self.a}, {self.b}, {self.c}")
        for name in ("k", "k_interp"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InputError(f"{name} must be a positive integer, got {v!r}")
        if self.idw_power <= 0:
            raise InputError(f"idw_power must be > 0, got {self.idw_power}")

    def level_sizes(self, n_points: int) -> tuple[int, int, int, int]:
        """Point counts (N, n2, n3, n4) of the four levels for a scan of ``n_points``."""
        return (n_points, int(n_points // self.a), int(n_points // self.b),
                int(n_points // self.c))

    def min_points(self) -> int:
        """Smallest N for which every level is large enough (K <= n3, k_interp <= n4)."""
        n = max(self.k, math.ceil(self.k * self.b), math.ceil(self.k_interp * self.c))
        while True:  # floor() can make the bound above one or two points short
            N, n2, n3, n4 = self.level_sizes(n)
            if min(N, n2, n3) >= self.k and n4 >= self.k_interp:
                return n
            n += 1


@dataclass(frozen=True)
class Geometry:
    """Precomputed indices and weights for a batch of B scans of N points (see module docstring).

    Attributes:
        config: the parameters used.
        fps_idx: (B, n2) int64 indices into the N scan points; levels 3 and 4 are its prefixes.
        groups: 4 int64 tensors (B, N, K), (B, n2, K), (B, n3, K), (B, n4, K); level k indexes
            level k-1 (level 1 and level 2 index the N scan points).
        interp_idx: 3 int64 tensors (B, N, k_interp) into levels 2, 3, 4.
        interp_w: 3 float32 tensors (B, N, k_interp), rows sum to 1.
    """

    config: GeometryConfig
    fps_idx: torch.Tensor
    groups: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]
    interp_idx: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
    interp_w: tuple[torch.Tensor, torch.Tensor, torch.Tensor]

    @property
    def batch_size(self) -> int:
        return int(self.fps_idx.shape[0])

    @property
    def sizes(self) -> tuple[int, int, int, int]:
        """(N, n2, n3, n4)."""
        return (int(self.groups[0].shape[1]), int(self.groups[1].shape[1]),
                int(self.groups[2].shape[1]), int(self.groups[3].shape[1]))

    def to(self, device: torch.device | str) -> Geometry:
        """A copy with every tensor on ``device``."""
        return Geometry(self.config, self.fps_idx.to(device),
                        tuple(g.to(device) for g in self.groups),  # type: ignore[arg-type]
                        tuple(i.to(device) for i in self.interp_idx),  # type: ignore[arg-type]
                        tuple(w.to(device) for w in self.interp_w))  # type: ignore[arg-type]

    def select(self, index: Sequence[int] | torch.Tensor) -> Geometry:
        """The geometry of a sub-batch (``index`` into the batch dimension)."""
        ix = torch.as_tensor(index, dtype=torch.long)
        return Geometry(self.config, self.fps_idx[ix],
                        tuple(g[ix] for g in self.groups),  # type: ignore[arg-type]
                        tuple(i[ix] for i in self.interp_idx),  # type: ignore[arg-type]
                        tuple(w[ix] for w in self.interp_w))  # type: ignore[arg-type]

    @staticmethod
    def stack(items: Sequence[Geometry]) -> Geometry:
        """Concatenate geometries (same config and N) along the batch dimension."""
        if len(items) == 0:
            raise InputError("cannot stack zero geometries")
        cfg, sizes = items[0].config, items[0].sizes
        for g in items[1:]:
            if g.config != cfg:
                raise InputError(f"cannot stack geometries with different configs: {cfg} vs {g.config}")
            if g.sizes != sizes:
                raise InputError(f"cannot stack geometries of different scan sizes: {sizes} vs {g.sizes}")
        return Geometry(
            cfg, torch.cat([g.fps_idx for g in items]),
            tuple(torch.cat([g.groups[j] for g in items]) for j in range(4)),  # type: ignore[arg-type]
            tuple(torch.cat([g.interp_idx[j] for g in items]) for j in range(3)),  # type: ignore[arg-type]
            tuple(torch.cat([g.interp_w[j] for g in items]) for j in range(3)),  # type: ignore[arg-type]
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat numpy arrays (for an ``np.savez`` cache); inverse of :meth:`from_arrays`."""
        out: dict[str, np.ndarray] = {"fps_idx": self.fps_idx.cpu().numpy()}
        for j in range(4):
            out[f"group{j + 1}"] = self.groups[j].cpu().numpy()
        for j in range(3):
            out[f"interp_idx{j + 2}"] = self.interp_idx[j].cpu().numpy()
            out[f"interp_w{j + 2}"] = self.interp_w[j].cpu().numpy()
        out["config_json"] = np.array(json.dumps(asdict(self.config), sort_keys=True))
        return out

    @staticmethod
    def from_arrays(arrays: dict[str, Any], config: GeometryConfig) -> Geometry:
        """Rebuild from :meth:`to_arrays`; ``config`` must be the one they were computed with."""
        stored = str(np.asarray(arrays["config_json"]))
        if stored != json.dumps(asdict(config), sort_keys=True):
            raise InputError(f"cached geometry was computed with {stored}, not {config}; recompute it")
        t = {k: torch.as_tensor(np.asarray(v)) for k, v in arrays.items() if k != "config_json"}
        return Geometry(config, t["fps_idx"],
                        (t["group1"], t["group2"], t["group3"], t["group4"]),
                        (t["interp_idx2"], t["interp_idx3"], t["interp_idx4"]),
                        (t["interp_w2"], t["interp_w3"], t["interp_w4"]))


def fps_start_index(points: np.ndarray) -> int:
    """Permutation-invariant FPS start: the point farthest from the centroid; near-ties (1e-12
    relative) go to the lexicographically largest (x, y, z)."""
    d2 = ((points - points.mean(axis=0)) ** 2).sum(axis=1)
    cand = np.flatnonzero(d2 >= d2.max() * (1.0 - 1e-12))
    if cand.size == 1:
        return int(cand[0])
    p = points[cand]
    return int(cand[np.lexsort((p[:, 2], p[:, 1], p[:, 0]))[-1]])


def farthest_point_indices(points: np.ndarray, n_samples: int) -> np.ndarray:
    """``n_samples`` vanilla FPS indices (int64) into ``points`` (N, 3), in selection order,
    starting from :func:`fps_start_index` (``fpsample``, float32): the reference that
    :func:`nested_fps_levels` reproduces."""
    idx = fpsample.fps_sampling(points, n_samples, start_idx=fps_start_index(points))
    return np.asarray(idx, dtype=np.int64)


def _open3d_fps(points: np.ndarray, n_samples: int, start: int) -> np.ndarray:
    """The set of ``n_samples`` vanilla-FPS picks from ``points`` (N, 3) starting at ``start``, as
    increasing indices (Open3D returns the picked points in scan order; each point carries its
    index in the normal channel, so duplicates map back exactly)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    tag = np.zeros((points.shape[0], 3))
    tag[:, 0] = np.arange(points.shape[0])
    pc.normals = o3d.utility.Vector3dVector(tag)
    picked = pc.farthest_point_down_sample(n_samples, start_index=start)
    return np.asarray(picked.normals)[:, 0].astype(np.int64)


def nested_fps_levels(points: np.ndarray, sizes: tuple[int, int, int]) -> np.ndarray:
    """Level-2 indices (int64, (n2,)) into ``points`` (N, 3) for level sizes (n2, n3, n4): the first
    n2 / n3 / n4 vanilla-FPS picks from :func:`fps_start_index` are ``[:n2]`` / ``[:n3]`` /
    ``[:n4]`` (module docstring: the start first, then each level's own points in index order)."""
    n2, n3, n4 = sizes
    start = fps_start_index(points)
    s2 = _open3d_fps(points, n2, start)
    s3 = s2[_open3d_fps(points[s2], n3, int(np.searchsorted(s2, start)))]
    s4 = s3[_open3d_fps(points[s3], n4, int(np.searchsorted(s3, start)))]
    parts = [np.array([start]), s4[s4 != start], np.setdiff1d(s3, s4, assume_unique=True),
             np.setdiff1d(s2, s3, assume_unique=True)]
    return np.concatenate(parts).astype(np.int64)


def _knn(tree: Any, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices (Q, k) of the k nearest tree points of each query (a small_gicp
    ``KdTree``; neighbours in order of distance)."""
    i, d2 = tree.batch_knn_search(np.ascontiguousarray(queries, dtype=np.float64), k)
    return np.sqrt(np.asarray(d2, dtype=np.float64)), np.asarray(i).astype(np.int64)


def _idw(dist: np.ndarray, power: float) -> np.ndarray:
    """Normalised inverse-distance weights (rows sum to 1) from neighbour distances (n, k)."""
    w = 1.0 / (dist**power + 1e-12)
    return w / w.sum(axis=1, keepdims=True)


def compute_geometry(points: np.ndarray | torch.Tensor, config: GeometryConfig | None = None) -> Geometry:
    """Precompute the indices and weights of one clean scan.

    Args:
        points: (N, 3) clean scan (any frame; float32/float64, finite). Unit-free: kNN and FPS are
            scale-invariant, only the interpolation weights' epsilon (1e-12) assumes distances well
            above 1e-6.
        config: level sizes, K, interpolation; default :class:`GeometryConfig()`.

    Returns:
        A :class:`Geometry` with batch size 1.

    Raises:
        InputError: bad array, or N too small for the levels (the message gives the minimum).
    """
    cfg = config or GeometryConfig()
    x = validate_cloud(points, "scan").astype(np.float64, copy=False)
    N, n2, n3, n4 = cfg.level_sizes(x.shape[0])
    if min(N, n2, n3) < cfg.k or n4 < cfg.k_interp:
        raise InputError(
            f"a scan of {N} points gives levels of ({N}, {n2}, {n3}, {n4}) points with a, b, c = "
            f"{cfg.a}, {cfg.b}, {cfg.c}; K = {cfg.k} needs n3 >= K and k_interp = {cfg.k_interp} "
            f"needs n4 >= k_interp: use at least {cfg.min_points()} points or smaller a, b, c, K")
    fps = nested_fps_levels(x, (n2, n3, n4))
    lvl = [x, x[fps], x[fps[:n3]], x[fps[:n4]]]
    import small_gicp  # on first use, as in icpbench.core.mapindex

    trees = [small_gicp.KdTree(np.ascontiguousarray(p)) for p in lvl]
    groups = [_knn(trees[0], lvl[0], cfg.k)[1]]
    # level-2 centroids are scan points grouped over the scan points: the same queries against
    # the same tree as their rows of groups[0]
    groups.append(groups[0][fps])
    for k in (2, 3):  # level k+1 centroids grouped over level k
        groups.append(_knn(trees[k - 1], lvl[k], cfg.k)[1])
    interp_idx, interp_w = [], []
    for k in (1, 2, 3):
        d, i = _knn(trees[k], x, cfg.k_interp)
        interp_idx.append(torch.from_numpy(i.astype(np.int64))[None])
        interp_w.append(torch.from_numpy(_idw(d, cfg.idw_power).astype(np.float32))[None])
    return Geometry(
        cfg, torch.from_numpy(fps)[None],
        tuple(torch.from_numpy(g.astype(np.int64))[None] for g in groups),  # type: ignore[arg-type]
        tuple(interp_idx),  # type: ignore[arg-type]
        tuple(interp_w),  # type: ignore[arg-type]
    )


def compute_geometry_batch(scans: np.ndarray | torch.Tensor | Sequence[np.ndarray],
                           config: GeometryConfig | None = None) -> Geometry:
    """:func:`compute_geometry` for each of B clean scans (B, N, 3), stacked."""
    if isinstance(scans, torch.Tensor):
        scans = scans.detach().cpu().numpy()
    if len(scans) == 0:
        raise InputError("scans is empty (0 samples)")
    return Geometry.stack([compute_geometry(s, config) for s in scans])
