"""The surrogate of ``--surrogate self``: the evaluated target itself, or its differentiable replica,
at the target's own converged pose.

A gradient attack crafted through a 25-iteration unrolled point-to-plane ICP and evaluated on
another ICP measures transfer, not the target's worst case (Croce and Hein, ICML 2020, on
non-adaptive evaluations). With ``--surrogate self`` every gradient attack runs through the target
it is evaluated on (a differentiable target) or through the target's differentiable replica
(``target.replica()``, for a black box that has one), with

* the target's own iteration cap: :meth:`SelfSurrogate.with_max_iterations` keeps it, so an attack
  cannot truncate the surrogate short of the pose the evaluation reaches;
* the implicit gradient at that pose (``backprop="implicit"``): exact at a converged pose, and no
  graph through hundreds of iterations.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import torch

from icpbench.core.types import Registration
from icpbench.targets.base import Target


class SelfSurrogate(Target):
    """A differentiable target used as its own surrogate (module docstring).

    Args:
        inner: the differentiable target (the evaluated one, or the replica of a black box).
        of: the registry name of the evaluated target (for the manifest).
    """

    name: ClassVar[str] = "self"
    description: ClassVar[str] = "the evaluated target (or its replica) as its own surrogate"
    differentiable: ClassVar[bool] = True

    def __init__(self, inner: Target, of: str) -> None:
        cfg = getattr(inner, "config", None)
        if cfg is not None and getattr(cfg, "backprop", "implicit") != "implicit":
            inner = inner.with_settings(backprop="implicit")
        self.inner = inner
        self.of = of
        self.config = getattr(inner, "config", None)

    def with_max_iterations(self, n: int) -> Target:
        """Itself: the target's own cap is kept (module docstring)."""
        return self

    def with_settings(self, **changes: Any) -> Target:
        """Settings changed on the inner target, except its iteration cap and gradient mode."""
        changes = {k: v for k, v in changes.items() if k not in ("max_iterations", "backprop")}
        return SelfSurrogate(self.inner.with_settings(**changes), self.of) if changes else self

    def prepare(self, map_points: Any, map_normals: Any) -> Any:
        return self.inner.prepare(map_points, map_normals)

    def register(self, scans: torch.Tensor, maps: Sequence[Any],
                 T_init: torch.Tensor) -> Registration:
        return self.inner.register(scans, maps, T_init)

    def settings(self) -> dict[str, Any]:
        return {"of": self.of, "surrogate": self.inner.name, **self.inner.settings()}


def self_surrogate(target: Target) -> SelfSurrogate | None:
    """The surrogate of ``--surrogate self`` for ``target``: itself when differentiable, else its
    replica (``target.replica()``), else None (no gradient attack can reach it)."""
    if target.differentiable:
        return SelfSurrogate(target, target.name)
    replica = getattr(target, "replica", None)
    inner = replica() if callable(replica) else None
    if inner is None or not inner.differentiable:
        return None
    return SelfSurrogate(inner, target.name)
