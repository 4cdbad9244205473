"""Target ``p2point``: differentiable point-to-point ICP."""

from __future__ import annotations

from typing import ClassVar

from icpbench.targets.icp import Mode
from icpbench.targets.p2plane import PointToPlaneICP


class PointToPointICP(PointToPlaneICP):
    """Differentiable point-to-point ICP (KD-tree NN, Cauchy on ||q - m||, d_max gate)."""

    name: ClassVar[str] = "p2point"
    description: ClassVar[str] = "Differentiable point-to-point ICP in PyTorch (KD-tree NN, Cauchy)"
    mode: ClassVar[Mode] = "point"
