"""What an integrity monitor sees of one registration: the problem, the result and its health.

A monitor depends on this input only, never on a target's internals, so the same monitor checks
every ICP variant (black boxes included) from what any localisation stack has at hand: the scan
it registered, its map, the pose it estimated and the few health numbers every registration
reports (:class:`~icpbench.core.types.Registration`), and optionally a motion prior.

Frames and units: the scan (N, 3) is in the sensor frame, the map (M, 3) and its unit normals in
the map frame, metres; ``T_hat`` maps scan-frame points into the map frame (the paper's T_QP, as
``T_gt`` does: ``q = R p + t``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex

__all__ = ["MonitorInput", "MotionPrior", "NearestMap"]


@dataclass(frozen=True, eq=False)
class MotionPrior:
    """A prediction of the pose from another source (odometry), with its stated uncertainty.

    Attributes:
        T_pred: (4, 4) float64 predicted scan->map transform (map frame, metres).
        sigma_m: standard deviation (metres) of each of the three map-frame components of the
            predicted translation's error (isotropic Gaussian).
        distance_m: the distance travelled (metres) since the last trusted pose, from which the
            noise model derived ``sigma_m``.
        seed: the seed of the draw that made ``T_pred`` (0 where it was not drawn).
    """

    T_pred: np.ndarray
    sigma_m: float
    distance_m: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        T = np.asarray(self.T_pred, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(f"motion prior: T_pred must be a finite 4x4 matrix, got shape {T.shape}")
        if not (np.isfinite(self.sigma_m) and self.sigma_m > 0):
            raise InputError(f"motion prior: sigma_m must be a positive number of metres, "
                             f"got {self.sigma_m!r}")
        object.__setattr__(self, "T_pred", T)

    def as_dict(self) -> dict[str, Any]:
        """Plain values for a manifest (the predicted translation, metres, map frame)."""
        return {"t_pred": [float(x) for x in self.T_pred[:3, 3]], "sigma_m": float(self.sigma_m),
                "distance_m": float(self.distance_m), "seed": int(self.seed)}


@dataclass(frozen=True, eq=False)
class NearestMap:
    """The nearest map point of every scan point at ``T_hat`` (no distance bound).

    Attributes:
        points: (N, 3) scan points moved into the map frame by ``T_hat`` (metres).
        dist: (N,) distance to the nearest map point (metres; inf where there is none).
        index: (N,) int64 index of that map point (M, the sentinel, where there is none).
    """

    points: np.ndarray
    dist: np.ndarray
    index: np.ndarray

    def within(self, gate_m: float) -> np.ndarray:
        """(N,) bool: the scan points with a map point closer than ``gate_m`` metres."""
        return self.dist < gate_m


@dataclass(frozen=True, eq=False)
class MonitorInput:
    """One registration problem and its result, as a localisation stack's checks see it.

    Attributes:
        scan: (N, 3) float64 registered scan, sensor frame, metres (the scan ICP was given,
            adversarial or not).
        map: the map (M points, map frame, metres) with unit normals (``map.normals`` (M, 3));
            the monitors that use planes refuse a map without normals.
        T_hat: (4, 4) float64 estimated scan->map transform. A non-finite pose is always flagged
            (:meth:`~icpbench.monitors.base.Monitor.score` returns inf without calling the monitor).
        iterations: iterations the registration used.
        converged: whether the registration reported convergence.
        inlier_fraction: share (0..1) of scan points the registration had a correspondence for
            at the end (the target's own gate, e.g. ``d_max``).
        prior: an optional motion prior (odometry prediction); monitors that need one refuse
            an input without it.
        sample_id: the sample's identifier (for messages and records).
    """

    scan: np.ndarray
    map: MapIndex
    T_hat: np.ndarray
    iterations: int = 0
    converged: bool = True
    inlier_fraction: float = 1.0
    prior: MotionPrior | None = None
    sample_id: str = ""

    def __post_init__(self) -> None:
        scan = np.asarray(self.scan, dtype=np.float64)
        if scan.ndim != 2 or scan.shape[1] != 3 or scan.shape[0] == 0:
            raise InputError(f"monitor input {self.sample_id!r}: scan must be a non-empty (N, 3) "
                             f"array, got shape {scan.shape}")
        if not isinstance(self.map, MapIndex):
            raise InputError(f"monitor input {self.sample_id!r}: map must be a MapIndex, got "
                             f"{type(self.map).__name__}")
        T = np.asarray(self.T_hat, dtype=np.float64)
        if T.shape != (4, 4):
            raise InputError(f"monitor input {self.sample_id!r}: T_hat must be 4x4, got {T.shape}")
        if self.prior is not None and not isinstance(self.prior, MotionPrior):
            raise InputError(f"monitor input {self.sample_id!r}: prior must be a MotionPrior, got "
                             f"{type(self.prior).__name__}")
        object.__setattr__(self, "scan", scan)
        object.__setattr__(self, "T_hat", T)
        object.__setattr__(self, "iterations", int(self.iterations))
        object.__setattr__(self, "converged", bool(self.converged))
        object.__setattr__(self, "inlier_fraction", float(self.inlier_fraction))

    @property
    def pose_finite(self) -> bool:
        """Whether ``T_hat`` is finite."""
        return bool(np.all(np.isfinite(self.T_hat)))

    @cached_property
    def nearest(self) -> NearestMap:
        """The scan at ``T_hat`` and its nearest map points, computed once per input and shared
        by the monitors that look at correspondences."""
        q = self.scan @ self.T_hat[:3, :3].T + self.T_hat[:3, 3]
        dist, idx = self.map.query(q)
        return NearestMap(points=q, dist=dist, index=idx)

    def normals(self) -> np.ndarray:
        """(M, 3) unit normals of the map.

        Raises:
            InputError: the map has none.
        """
        if self.map.normals is None:
            raise InputError(f"monitor input {self.sample_id!r}: the map has no normals; build the "
                             "MapIndex with the sample's map_normals")
        return self.map.normals
