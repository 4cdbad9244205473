"""Core data types shared by datasets, attacks, targets and the runner.

Frames and units (docs/architecture.md, "Frames, units and pose error"): the *scan* P (N, 3) lives
in the sensor frame and is registered to
the *map* Q (M, 3) in the map frame. ``T_gt`` maps scan-frame points into the map frame (the paper's
T_QP). Metres and radians throughout.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from icpbench.core.errors import InputError


@dataclass(frozen=True)
class Sample:
    """One localisation problem: register ``scan`` to ``map`` starting from ``T_init``.

    Attributes:
        id: stable identifier, e.g. ``"lidar-sim/pass2/000417"``.
        scan: (N, 3) float32, sensor frame, metres; already moved by the random init offset.
        map: (M, 3) float32, map frame, metres.
        map_normals: (M, 3) float32 unit normals of the map points (no gradient).
        T_gt: (4, 4) float64, true scan->map transform.
        T_init: (4, 4) float64, initial guess handed to ICP (identity in the paper).
        meta: free-form metadata (route position, stretch type, pass, frame, category, ...).
    """

    id: str
    scan: np.ndarray
    map: np.ndarray
    map_normals: np.ndarray
    T_gt: np.ndarray
    T_init: np.ndarray = field(default_factory=lambda: np.eye(4))
    meta: Mapping[str, Any] = field(default_factory=dict)

    def validate(self) -> Sample:
        """Check shapes, finiteness and normals; raise :class:`InputError` naming the problem."""
        validate_cloud(self.scan, f"sample {self.id!r}: scan", min_points=6)
        validate_cloud(self.map, f"sample {self.id!r}: map", min_points=6)
        if self.map_normals is None:
            raise InputError(
                f"sample {self.id!r}: map has no normals; estimate them, e.g. "
                "icpbench.datasets.submaps.estimate_normals(map)"
            )
        n = np.asarray(self.map_normals)
        if n.shape != np.asarray(self.map).shape:
            raise InputError(
                f"sample {self.id!r}: map_normals has shape {n.shape}, expected {self.map.shape} "
                "(one unit normal per map point)"
            )
        norms = np.linalg.norm(n, axis=1)
        if not np.all(np.isfinite(norms)) or np.mean(np.abs(norms - 1.0) < 1e-3) < 0.5:
            raise InputError(
                f"sample {self.id!r}: map has no usable normals (expected unit vectors); "
                "estimate them, e.g. icpbench.datasets.submaps.estimate_normals(map)"
            )
        for name in ("T_gt", "T_init"):
            T = np.asarray(getattr(self, name))
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise InputError(f"sample {self.id!r}: {name} must be a finite 4x4 matrix")
        return self


def validate_cloud(points: Any, name: str, *, min_points: int = 6) -> np.ndarray:
    """Validate a point cloud array of shape (K, 3); return it as a numpy array.

    Raises:
        InputError: wrong type/shape, fewer than ``min_points`` points, or NaN/Inf coordinates.
    """
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (K, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"{name} must be a floating-point array, got dtype {arr.dtype}")
    if arr.shape[0] == 0:
        raise InputError(f"{name} is empty (0 points)")
    if arr.shape[0] < min_points:
        raise InputError(
            f"{name} has {arr.shape[0]} points; at least {min_points} are needed to constrain a "
            "6-DoF pose"
        )
    if not np.all(np.isfinite(arr)):
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise InputError(f"{name} has {bad} point(s) with NaN or Inf coordinates")
    # Duplicates are fine, but fewer than min_points *distinct* points cannot constrain a pose.
    # The first 1,000 points usually settle it; only a mostly duplicated cloud pays the full count.
    if len(np.unique(arr[:1000], axis=0)) < min_points:
        distinct = len(np.unique(arr, axis=0))
        if distinct < min_points:
            raise InputError(
                f"{name} has only {distinct} distinct point(s) among {arr.shape[0]} (the rest are "
                f"duplicates); at least {min_points} distinct points are needed to constrain a "
                "6-DoF pose"
            )
    return arr


@dataclass
class Batch:
    """A batch of samples with equal scan size N.

    Attributes:
        samples: the B samples.
        scans: (B, N, 3) tensor of the (clean) scans in the sensor frame.
        T_gt: (B, 4, 4) float64 tensor.
        T_init: (B, 4, 4) float64 tensor.
        memo: results of deterministic computations on this batch that several attacks share
            (e.g. the iterated sector attack, which is also the generator's prior), keyed by the
            computation and its settings; see :func:`icpbench.core.iterated_sector.iterated_sector`.
    """

    samples: Sequence[Sample]
    scans: torch.Tensor
    T_gt: torch.Tensor
    T_init: torch.Tensor
    _maps: list[Any] | None = field(default=None, repr=False)
    memo: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def maps(self) -> list[Any]:
        """B :class:`~icpbench.core.mapindex.MapIndex` (KD-tree + normals), built once and cached.

        Pass ``maps=`` to :meth:`from_samples` to share them across batches (the runner does)."""
        if self._maps is None:
            from icpbench.core.mapindex import MapIndex

            self._maps = [MapIndex(s.map, s.map_normals) for s in self.samples]
        return self._maps

    @classmethod
    def from_samples(cls, samples: Sequence[Sample], dtype: torch.dtype = torch.float64,
                     maps: list[Any] | None = None) -> Batch:
        """Stack samples (all with the same N) into a batch (optionally with prepared maps)."""
        if len(samples) == 0:
            raise InputError("cannot build a batch from zero samples")
        sizes = {s.scan.shape[0] for s in samples}
        if len(sizes) != 1:
            raise InputError(f"samples in one batch must share the scan size N, got {sorted(sizes)}")
        scans = torch.as_tensor(np.stack([s.scan for s in samples]), dtype=dtype)
        T_gt = torch.as_tensor(np.stack([s.T_gt for s in samples]), dtype=torch.float64)
        T_init = torch.as_tensor(np.stack([s.T_init for s in samples]), dtype=torch.float64)
        return cls(samples=list(samples), scans=scans, T_gt=T_gt, T_init=T_init, _maps=maps)

    def __len__(self) -> int:
        return len(self.samples)


@dataclass
class Registration:
    """Result of registering a batch of scans.

    Attributes:
        T: (B, 4, 4) estimated scan->map transforms (differentiable for differentiable targets).
        converged: (B,) bool; pose increment fell below the tolerance before ``max_iterations``.
        iterations: (B,) int; iterations used.
        inlier_fraction: (B,) float; share of scan points with a correspondence at the end.
        status: per sample "ok" or a short reason ("not_converged", "singular",
            "too_few_correspondences", "nonfinite").
    """

    T: torch.Tensor
    converged: torch.Tensor
    iterations: torch.Tensor
    inlier_fraction: torch.Tensor
    status: list[str]
