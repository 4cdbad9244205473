"""Target ``kiss-icp-replica``: KISS-ICP's scan-to-map registration as a differentiable ICP.

The black box :class:`~icpbench.targets.kiss.KissICPTarget` (KISS-ICP, Vizzo et al., "KISS-ICP: In
Defense of Point-to-Point ICP", RA-L 2023) runs, per iteration: transform the scan by the current
pose; for each point take the nearest stored map point among the 27 voxels around it
(``VoxelHashMap::GetClosestNeighbor``); keep pairs closer than ``max_corr``; weight them
``kernel^2 / (kernel + r^2)^2`` (Geman-McClure, ``r = ||q - m||``); solve the 6x6 point-to-point
Gauss-Newton system; apply ``T <- exp(dx) T``; stop when ``||dx|| < convergence`` or after
``max_iterations``. This target runs the same iteration in PyTorch
(:func:`icpbench.targets.icp.icp`, ``mode="point"``), so gradients reach the scan points:

==========================  ======================================================================
KISS                        replica
==========================  ======================================================================
voxel-hash map              the points KISS's own ``_VoxelHashMap`` keeps of the batch's map
                            (built once per ``MapIndex`` and cached, :func:`kiss.kept_points`)
27-voxel neighbour search   exact nearest neighbour (KD-tree) of the kept points where it is closer
                            than a voxel (then it lies in the 27 voxels, so KISS finds the same
                            point); between a voxel and ``max_corr`` KISS's search itself
                            (:class:`kiss.VoxelNeighbours`); beyond ``max_corr`` nothing counts
``max_corr``                ``ICPConfig.d_max`` (hard gate ``d < d_max``, as KISS's)
``kernel``                  ``ICPConfig.kernel = "geman_mcclure"``, ``cauchy_c = sqrt(kernel)``:
                            ``1 / (1 + r^2 / c^2)^2 = kernel^2 / (kernel + r^2)^2``
``convergence``             ``ICPConfig.tol`` on ``||delta||`` (the same test)
``max_iterations``          ``ICPConfig.max_iterations`` (500)
LDLT solve                  ``(H + 1e-9 trace(H) / 6 I)^-1`` (``ICPConfig.damping``; relative
                            damping of 1e-9 changes the step by ~1e-9 of itself)
==========================  ======================================================================

The correspondence choice carries no gradient (piecewise constant in the scan), as in every ICP
target here; residuals, weights and the solve do. ``backprop="implicit"`` differentiates the
converged pose (the black box's pose, when the two agree) instead of the iterations.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.map_cache import PerMapCache
from icpbench.core.mapindex import MapIndex
from icpbench.core.registry import check_ranges
from icpbench.core.types import Registration
from icpbench.targets.base import Target
from icpbench.targets.icp import ICPConfig, config_dict, icp
from icpbench.targets.kiss import KissICPTarget, VoxelNeighbours, kept_points, kiss_settings


class KissReplicaMap(MapIndex):
    """The points KISS's voxel map keeps (map frame), with KISS's neighbour search.

    ``nearest2`` answers the ICP's correspondence cache (:class:`icpbench.targets.icp._Correspondences`)
    so that its rows are KISS's neighbours: see the module docstring. The distances it returns
    only steer how far a point may move before it is asked again.
    """

    _REACH = 2.0 * np.sqrt(3.0)  # farthest point of the 27 voxels, in voxels
    _TINY_GAP = 1e-12  # metres: a gap below the cache's 1e-9 m margin, i.e. ask again

    def __init__(self, points: np.ndarray, voxel_size: float, max_corr: float) -> None:
        super().__init__(points)
        self.search = VoxelNeighbours(self.points, voxel_size)
        self.voxel_size = float(voxel_size)
        self.max_corr = float(max_corr)
        self.exact_within = self.voxel_size  # the 27 voxels hold every point within one voxel
        self.voxel_search = self.search

    def nearest2(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """KISS's neighbour row of each query (K, 3), with distances (d1, d2) whose half gap
        ``(d2 - d1) / 2`` is how far the query may move with the same answer from KISS (the
        correspondence cache's slack):

        * exact neighbour within a voxel: KISS's too, while it stays within a voxel and the
          nearest: ``d2`` is shrunk to ``2 voxel - d1``;
        * exact neighbour beyond ``max_corr``: KISS's is farther still, so the pair is gated out,
          and the cache's far rule (move ``d1 - max_corr`` first) holds;
        * in between: if the exact neighbour lies in the 27 voxels it is KISS's (the nearest of
          all, so of those), else KISS's own search over the 27 voxels; the answer holds while
          the query stays in its voxel (the same 27 voxels) and keeps its nearest among the
          candidates: ``d2 = d1 + 2 min(boundary distance, gap / 2)`` (gap: second minus first
          distance, exact or among the 27 voxels), with d1 the exact distance (not above
          ``max_corr``, so the far rule stays off).
        """
        q = np.asarray(q, dtype=np.float64)
        d1, d2, idx = super().nearest2(q)
        near = d1 < self.voxel_size
        d2 = np.where(near, np.minimum(d2, 2.0 * self.voxel_size - d1), d2)
        mid = ~near & (d1 <= self.max_corr) & np.isfinite(d1)
        if mid.any():
            m = np.flatnonzero(mid)
            qm = q[m]
            vq = np.floor(qm / self.voxel_size)
            frac = qm / self.voxel_size - vq
            wall = self.voxel_size * np.minimum(frac, 1.0 - frac).min(axis=1)
            gap = 0.5 * (d2[m] - d1[m])
            # the exact neighbour lies in the 27 voxels: it is KISS's (nearest overall, so nearest
            # of them), while the query keeps its voxel and that neighbour
            inside = (np.abs(np.floor(self.points[idx[m]] / self.voxel_size) - vq) <= 1).all(axis=1)
            # every point of the 27 voxels is within 2 sqrt(3) voxels: beyond, they hold none
            empty = ~inside & (d1[m] > self._REACH * self.voxel_size)
            idx[m[empty]] = len(self)
            gap[empty] = np.inf
            search = ~inside & ~empty
            if search.any():  # otherwise KISS's search, and its own gap
                k1, k2, idx[m[search]] = self.search.query2(q[m[search]])
                with np.errstate(invalid="ignore"):  # nothing found (inf - inf): only the voxel
                    gap[search] = np.where(np.isfinite(k1), 0.5 * (k2 - k1), np.inf)
            d2[m] = d1[m] + 2.0 * np.maximum(np.minimum(wall, gap), self._TINY_GAP)
        far = ~near & ~mid & np.isfinite(d1)
        d2[far] = d1[far] + self._TINY_GAP  # the cache's far rule gives the slack
        return d1, d2, idx


class KissICPReplica(Target):
    """Differentiable replica of :class:`~icpbench.targets.kiss.KissICPTarget` (same settings).

    Args:
        preset: ICP preset name or ``ICPConfig`` (as for ``kiss-icp``).
        voxel_size, max_points_per_voxel, initial_threshold, max_corr, kernel, max_iterations:
            KISS's settings, defaults as ``kiss-icp`` (:func:`icpbench.targets.kiss.kiss_settings`).
        backprop: ``"unrolled"`` or ``"implicit"`` (``ICPConfig.backprop``).
        **overrides: ``ICPConfig`` fields of the preset (``d_max`` sets the default voxel, ``tol``
            KISS's convergence threshold).
    """

    name: ClassVar[str] = "kiss-icp-replica"
    description: ClassVar[str] = "KISS-ICP registration replicated in PyTorch (differentiable)"
    differentiable: ClassVar[bool] = True
    #: the black box's ranges (the replica takes the same settings, less the thread count)
    param_ranges: ClassVar[dict[str, Any]] = {
        k: v for k, v in KissICPTarget.param_ranges.items() if k != "threads"}

    def __init__(self, preset: ICPConfig | str | None = "lidar", *,
                 voxel_size: float | None = None, max_points_per_voxel: int = 20,
                 initial_threshold: float | None = None, max_corr: float | None = None,
                 kernel: float | None = None, max_iterations: int = 500,
                 **overrides: Any) -> None:
        check_ranges("target 'kiss-icp-replica'", locals(), self.param_ranges)
        from icpbench.targets.blackbox import resolve_preset

        base = resolve_preset(preset, overrides, "kiss-icp-replica")
        self.voxel_size, self.sigma, self.max_corr, self.kernel = kiss_settings(
            base, voxel_size, initial_threshold, max_corr, kernel)
        if max_points_per_voxel < 1 or max_iterations < 1:
            raise InputError("max_points_per_voxel and max_iterations must be >= 1")
        self.max_points_per_voxel = int(max_points_per_voxel)
        self.base = base
        self.config = base.with_(max_iterations=int(max_iterations), d_max=self.max_corr,
                                 kernel="geman_mcclure", cauchy_c=float(np.sqrt(self.kernel)),
                                 nn_reuse_m=0.0)
        self._maps: PerMapCache[KissReplicaMap] = PerMapCache()

    def with_settings(self, **changes: Any) -> KissICPReplica:
        """A replica with some ``ICPConfig`` fields of the *resulting* config replaced (e.g.
        ``backprop``, ``max_iterations``), KISS's settings kept."""
        out = KissICPReplica(self.base, voxel_size=self.voxel_size,
                             max_points_per_voxel=self.max_points_per_voxel,
                             initial_threshold=self.sigma, max_corr=self.max_corr,
                             kernel=self.kernel, max_iterations=self.config.max_iterations)
        out.config = self.config.with_(**changes)
        out._maps = self._maps
        return out

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None = None) -> MapIndex:
        return MapIndex(map_points, map_normals, workers=self.config.kdtree_workers)

    def kiss_map(self, m: MapIndex) -> KissReplicaMap:
        """KISS's thinned map of a batch map (built once per ``MapIndex`` object, then cached)."""
        def build(m: MapIndex) -> KissReplicaMap:
            _, kept = kept_points(m.points, self.voxel_size, self.max_points_per_voxel)
            return KissReplicaMap(kept, self.voxel_size, self.max_corr)

        return self._maps.get(m, build)

    def register(self, scans: torch.Tensor, maps: Sequence[MapIndex],
                 T_init: torch.Tensor) -> Registration:
        """Register scans (B, N, 3), sensor frame, to the batch's maps from T_init (B, 4, 4)."""
        return icp(scans, [self.kiss_map(m) for m in maps], T_init, self.config, mode="point")

    def settings(self) -> dict[str, Any]:
        return {"replica_of": "kiss-icp", "voxel_size": self.voxel_size,
                "max_points_per_voxel": self.max_points_per_voxel, "initial_threshold": self.sigma,
                "max_corr": self.max_corr, "kernel": self.kernel, "mode": "point",
                **config_dict(self.config)}
