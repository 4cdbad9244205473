"""A registration as a gradient attack sees it: the scan and the estimated pose as tensors.

A monitor that offers a differentiable score (:attr:`~icpbench.monitors.base.Monitor.differentiable`)
computes it from a :class:`DiffInput`: the scan (N, 3) in the sensor frame and the pose ``T_hat``
(4, 4) scan->map, both float64 tensors that may carry gradients (the pose through the surrogate
ICP's implicit derivative), the sample's map and, for a monitor that uses one, its motion prior.

As in ICP, which map point a scan point is paired with is chosen without gradient (the nearest one
at ``T_hat``, by the same KD-tree lookup as :attr:`~icpbench.monitors.inputs.MonitorInput.nearest`),
and the pair's geometry then carries the gradient. A count (how many points lie within a gate) is
piecewise constant; :func:`soft_within` gives it a slope (a logistic step of width ``gate / 10``)
and :func:`straight_through` keeps the exact value with that slope, so a differentiable score
*equals* the monitor's score of the same registration and only its gradient is smoothed.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.monitors.inputs import MotionPrior

__all__ = ["DiffInput", "Pairs", "soft_within", "straight_through"]

#: Width of the logistic step of :func:`soft_within`, as a fraction of the gate.
SOFT_WIDTH = 0.1


@dataclass(frozen=True, eq=False)
class Pairs:
    """Every scan point with a map point, at ``T_hat``.

    Attributes:
        index: (K,) int64 index of each one's nearest map point.
        points: (K, 3) the scan points moved into the map frame (differentiable).
        dist: (K,) their distance to that map point (metres, differentiable).
        exact_dist: (K,) float64 numpy distances of the lookup (equal to ``dist``'s values).
    """

    index: np.ndarray
    points: torch.Tensor
    dist: torch.Tensor
    exact_dist: np.ndarray

    def within(self, gate_m: float) -> np.ndarray:
        """(K,) bool: the pairs closer than ``gate_m`` metres (as ``NearestMap.within``)."""
        return self.exact_dist < gate_m


@dataclass(frozen=True, eq=False)
class DiffInput:
    """One registration with gradients (see the module docstring).

    Attributes:
        scan: (N, 3) float64 tensor, sensor frame, metres.
        T_hat: (4, 4) float64 tensor, the estimated scan->map transform (finite).
        map: the sample's map with unit normals (map frame, metres).
        prior: the motion prior of the monitor that uses one (else None).
        sample_id: the sample's identifier (for messages).
    """

    scan: torch.Tensor
    T_hat: torch.Tensor
    map: MapIndex
    prior: MotionPrior | None = None
    sample_id: str = ""

    def __post_init__(self) -> None:
        if self.scan.ndim != 2 or self.scan.shape[-1] != 3 or self.scan.shape[0] == 0:
            raise InputError(f"differentiable monitor input {self.sample_id!r}: scan must be a "
                             f"non-empty (N, 3) tensor, got shape {tuple(self.scan.shape)}")
        if tuple(self.T_hat.shape) != (4, 4):
            raise InputError(f"differentiable monitor input {self.sample_id!r}: T_hat must be 4x4, "
                             f"got {tuple(self.T_hat.shape)}")
        if not isinstance(self.map, MapIndex):
            raise InputError(f"differentiable monitor input {self.sample_id!r}: map must be a "
                             f"MapIndex, got {type(self.map).__name__}")

    @cached_property
    def points(self) -> torch.Tensor:
        """(N, 3) the scan moved into the map frame by ``T_hat`` (differentiable)."""
        T = self.T_hat.to(torch.float64)
        return self.scan.to(torch.float64) @ T[:3, :3].T + T[:3, 3]

    @cached_property
    def pairs(self) -> Pairs:
        """The nearest map point of every scan point that has one (chosen without gradient)."""
        q = self.points
        dist, idx = self.map.query(q.detach().numpy())
        rows = np.flatnonzero(np.isfinite(dist))
        p = q[torch.as_tensor(rows)]
        d = torch.linalg.norm(p - torch.as_tensor(self.map.points[idx[rows]]), dim=-1)
        return Pairs(index=idx[rows], points=p, dist=d, exact_dist=dist[rows])

    def normals(self) -> np.ndarray:
        """(M, 3) unit normals of the map.

        Raises:
            InputError: the map has none.
        """
        if self.map.normals is None:
            raise InputError(f"differentiable monitor input {self.sample_id!r}: the map has no "
                             "normals")
        return self.map.normals


def soft_within(dist: torch.Tensor, gate_m: float) -> torch.Tensor:
    """(K,) a logistic step from 1 (well inside ``gate_m``) to 0 (well outside), width
    ``SOFT_WIDTH * gate_m``: the slope a count of points within the gate lacks."""
    return torch.sigmoid((gate_m - dist) / (SOFT_WIDTH * gate_m))


def straight_through(exact: float, soft: torch.Tensor) -> torch.Tensor:
    """A scalar tensor with the value ``exact`` and the gradient of ``soft``."""
    return soft + (float(exact) - soft.detach())
