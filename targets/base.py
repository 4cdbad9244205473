"""Target base class: an ICP variant that registers batches of scans to prepared maps.

Frames: scans (B, N, 3) are in the sensor frame; each map is in its own map frame; every transform
maps scan-frame points into the map frame (T_map_scan, the paper's T_QP).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.types import Registration


class Target(ABC):
    """An ICP variant under attack.

    Subclasses set ``name``, ``description`` and ``differentiable`` and implement :meth:`prepare`
    (built once per map, then cached by the caller) and :meth:`register`.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    differentiable: ClassVar[bool] = False

    @abstractmethod
    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray) -> Any:
        """Build the per-map structures (KD-tree, normals, voxel map, ...).

        Args:
            map_points: (M, 3) map points, map frame, metres.
            map_normals: (M, 3) unit normals of the map points.
        """

    @abstractmethod
    def register(
        self, scans: torch.Tensor, maps: Sequence[Any], T_init: torch.Tensor
    ) -> Registration:
        """Register a batch.

        Args:
            scans: (B, N, 3) scans, sensor frame (may require grad for differentiable targets).
            maps: B prepared maps from :meth:`prepare`.
            T_init: (B, 4, 4) initial scan->map transforms.

        Returns:
            :class:`~icpbench.types.Registration` with T (B, 4, 4) and per-sample health.
        """

    def settings(self) -> dict[str, Any]:
        """Settings recorded in the results manifest."""
        return {}
