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

from icpbench.core.types import Registration
from icpbench.targets.icp import ICP_RANGES


class Target(ABC):
    """An ICP variant under attack, and the whole contract between a target plugin and the runner.

    Subclasses set ``name``, ``description`` and ``differentiable`` and implement :meth:`prepare`
    (built once per map, then cached by the caller) and :meth:`register`.

    Construction: the runner calls ``cls(preset, **settings)``. ``preset`` is the run's ICP preset
    (a name such as ``"lidar"`` or ``"objects"``, see :mod:`icpbench.targets.icp`, or an
    ``ICPConfig``); ``settings`` are the user's ``--target-param NAME.KEY=VALUE`` values, checked
    against :meth:`param_types` before the target is built. A target built on the shared ICP
    settings keeps them in :attr:`config`.
    """

    #: Registry key; must equal the entry-point name the plugin is registered under.
    name: ClassVar[str] = ""
    #: One line for ``icpbench list``.
    description: ClassVar[str] = ""
    #: :meth:`register` is differentiable with respect to the scans (usable as a surrogate of
    #: gradient attacks); it then receives the batch's ``MapIndex`` maps instead of prepared ones.
    differentiable: ClassVar[bool] = False
    #: :meth:`register` takes the batch's ``MapIndex`` maps (every differentiable target does;
    #: so does a compiled forward pass that answers queries, without gradients).
    takes_map_index: ClassVar[bool] = False
    #: The target's ICP settings (an ``icpbench.targets.icp.ICPConfig``), or None for a target
    #: that does not use them.
    config: Any = None

    #: Valid values of the numeric settings (checked with the types before a target is built;
    #: NaN and Inf are refused for every setting). Targets with settings of their own extend it.
    param_ranges: ClassVar[dict[str, Any]] = ICP_RANGES

    @classmethod
    def param_types(cls) -> dict[str, Any]:
        """Settings the target accepts (name -> type hint): the named keyword parameters of its
        ``__init__`` after the preset and, if ``__init__`` takes ``**overrides``, the fields of
        ``ICPConfig`` (the overrides of the preset). Unknown settings are refused and values are
        coerced to these types before the target is built."""
        from icpbench.core.registry import accepts_extra, keyword_params

        params = keyword_params(cls.__init__)
        params.pop(next(iter(params), ""), None)  # the preset (first parameter)
        if accepts_extra(cls.__init__):
            from dataclasses import fields

            from icpbench.targets.icp import ICPConfig

            hints = keyword_params(ICPConfig.__init__)
            params = {**{f.name: hints.get(f.name, Any) for f in fields(ICPConfig)}, **params}
        return params

    def with_max_iterations(self, n: int) -> Target:
        """A target like this one whose ICP stops after at most ``n`` iterations (the ``pgd``
        attack runs its surrogate with a smaller cap inside the ascent loop).

        Default: ``type(self)(self.config.with_(max_iterations=n))`` by the constructor contract,
        or ``self`` for a target without :attr:`config`. Targets with other constructor settings
        that must survive override this."""
        if self.config is None:
            return self
        return self.with_settings(max_iterations=int(n))

    def with_settings(self, **changes: Any) -> Target:
        """A target like this one with some ``ICPConfig`` fields replaced (e.g. an attack's
        surrogate with its own iteration cap, gradient mode or correspondence search).

        Default: ``type(self)(self.config.with_(**changes))`` by the constructor contract; targets
        with other constructor settings that must survive override this.

        Raises:
            InputError: the target has no ``config`` to change.
        """
        if self.config is None:
            from icpbench.core.errors import InputError

            raise InputError(f"target {self.name!r} has no ICP settings to change "
                             f"({', '.join(sorted(changes))})")
        return type(self)(self.config.with_(**changes))

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
            :class:`~icpbench.core.types.Registration` with T (B, 4, 4) and per-sample health.
        """

    def settings(self) -> dict[str, Any]:
        """Settings recorded in the results manifest."""
        return {}

    def replica(self) -> Target | None:
        """The differentiable target that reproduces this one with the same settings (a gradient
        attack on a black box runs through it), or None where there is none.

        Default: the target itself when it is differentiable, else None. Black boxes with a
        replica override this (docs/methods.md, "Differentiable replicas of the black boxes")."""
        return self if self.differentiable else None

    def exact_replica(self) -> Target | None:
        """A target whose registrations equal this one's to rounding (measured, not assumed), so
        that it may answer an attack's queries in this target's place, or None.

        Only the *queries* of a query attack go to it (:class:`~icpbench.targets.oracle.
        QueryOracle`, ``answer_with``); every row of a run is still this target's own registration
        of the attack's output, so a replica that drifted could only make an attack weaker, never
        a reported error larger. Worth it where the replica is faster than the target (KISS-ICP:
        docs/performance.md, "Queries answered by an exact replica"). Default None."""
        return None
