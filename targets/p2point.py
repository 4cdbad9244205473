"""Target ``p2point``: differentiable point-to-point ICP.

Per-target default: from the evaluation presets (``"lidar"``, ``"objects"``, given by name) the
iteration cap is :data:`POINT_MAX_ITERATIONS` (500, KISS-ICP's cap for the same cost) instead of
the preset's 100 / 150, unless ``max_iterations`` is given. Point-to-point ICP creeps along weakly
constrained directions (a highway's road axis): on the 48 clean ``lidar-sim`` test scans a
quarter of the scans stopped at the 100-iteration cap, none at 500 (the slowest took ~330;
docs/methods.md, "Per-target settings"). The shared preset, and so ``p2plane``, is unchanged.
"""

from __future__ import annotations

from typing import Any, ClassVar

from icpbench.targets.icp import ICPConfig, Mode, icp_config
from icpbench.targets.p2plane import PointToPlaneICP

#: Iteration cap of ``p2point`` built from an evaluation preset name (module docstring).
POINT_MAX_ITERATIONS = 500
#: Presets whose cap ``p2point`` replaces (the ``*-train`` presets keep their short caps).
EVALUATION_PRESETS = ("lidar", "objects")


class PointToPointICP(PointToPlaneICP):
    """Differentiable point-to-point ICP (KD-tree NN, robust weight on ||q - m||, d_max gate).

    Args:
        config: preset name or ``ICPConfig`` (an ``ICPConfig`` is used as given).
        **overrides: ``ICPConfig`` fields; without ``max_iterations`` an evaluation preset name
            gets :data:`POINT_MAX_ITERATIONS`.
    """

    name: ClassVar[str] = "p2point"
    description: ClassVar[str] = ("Differentiable point-to-point ICP in PyTorch (KD-tree NN, Cauchy; "
                                  "500 iterations)")
    mode: ClassVar[Mode] = "point"

    def __init__(self, config: ICPConfig | str | None = "lidar", **overrides: Any) -> None:
        if isinstance(config, str) and config in EVALUATION_PRESETS:
            overrides.setdefault("max_iterations", POINT_MAX_ITERATIONS)
        self.config = icp_config(config, **overrides)
