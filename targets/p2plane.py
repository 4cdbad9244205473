"""Target ``p2plane``: differentiable point-to-plane ICP (the paper's attack target)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.core.mapindex import MapIndex
from icpbench.core.types import Registration
from icpbench.targets.base import Target
from icpbench.targets.icp import ICPConfig, Mode, config_dict, icp, icp_config


class PointToPlaneICP(Target):
    """Differentiable point-to-plane ICP (KD-tree correspondences, Cauchy weights, d_max gate)."""

    name: ClassVar[str] = "p2plane"
    description: ClassVar[str] = (
        "Differentiable point-to-plane ICP in PyTorch (dICP-style, KD-tree NN, Cauchy, d_max)"
    )
    differentiable: ClassVar[bool] = True
    mode: ClassVar[Mode] = "plane"

    def __init__(self, config: ICPConfig | str | None = "lidar", **overrides: Any) -> None:
        self.config = icp_config(config, **overrides)

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray | None) -> MapIndex:
        return MapIndex(map_points, map_normals, workers=self.config.kdtree_workers)

    def register(self, scans: torch.Tensor, maps: Sequence[MapIndex],
                 T_init: torch.Tensor) -> Registration:
        return icp(scans, maps, T_init, self.config, mode=self.mode)

    def settings(self) -> dict[str, Any]:
        return {"mode": self.mode, **config_dict(self.config)}

    def exact_replica(self) -> Target | None:
        """Point-to-point ICP with the hard gate and exact correspondences: its compiled forward
        pass (:class:`~icpbench.targets.point_forward.CompiledPointICP`, the same registrations
        to about 1e-15 m and the same iteration counts, measured 3x faster per query), which
        answers the query attacks' registrations. Other modes and settings: None."""
        if self.mode != "point" or self.config.soft_dmax or self.config.nn_reuse_m != 0:
            return None
        from icpbench.targets.point_forward import CompiledPointICP

        return CompiledPointICP(self, self.config)
