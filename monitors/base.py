"""Monitor base class: a check a localisation stack runs on each registration before trusting it.

A real stack does not take every ICP pose: it checks the registration (how well the scan fits the
map at the estimated pose, how many points found the map, whether the geometry constrains every
direction, whether the pose agrees with odometry) and falls back (odometry only, a wider search, a
stop) when a check fires. This is integrity monitoring in the sense of GNSS receiver autonomous
integrity monitoring (RAIM: a test statistic computed from the solution's own residuals, compared
with a threshold set for a chosen false-alarm rate; Parkinson and Axelrad, "Autonomous GPS
integrity monitoring using the pseudorange residual", Navigation 35(2), 1988). The harness asks
what the *worst undetected* error is: the largest pose error an attack reaches while no monitor
fires (:class:`~icpbench.monitors.oracle.MonitoredOracle`).

The contract: a subclass sets ``name``, ``description``, ``param_ranges`` and implements
:meth:`Monitor._score` (larger = more suspicious); :meth:`Monitor.score` and :meth:`Monitor.check`,
which subclasses cannot override, handle a non-finite pose (always flagged) and a monitor that
returns NaN. A monitor whose score can be written in torch sets ``differentiable`` and implements
:meth:`Monitor._differentiable_score` (same value, with a gradient): the gradient member of the
``ensemble`` then penalises it under ``--monitor-aware`` (:mod:`icpbench.monitors.penalty`); the
others are seen by the query members only. A monitor that uses a motion prior overrides
:meth:`Monitor.motion_prior`, which the harness calls with the true pose to simulate the prior it
is given.

Construction: ``cls(**settings)``; the settings are the named keyword parameters of ``__init__``
(:meth:`Monitor.param_types`), among them ``threshold``, checked against ``param_ranges`` by the
registry (:func:`icpbench.core.registry.check_params`) and again when the monitor is built.
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, final

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.registry import Range, check_ranges, keyword_params
from icpbench.monitors.differentiable import DiffInput
from icpbench.monitors.inputs import MonitorInput, MotionPrior

__all__ = ["Monitor", "MonitorInput", "MonitorResult", "MotionPrior"]


@dataclass(frozen=True)
class MonitorResult:
    """One monitor's verdict on one registration.

    Attributes:
        name: the monitor's registry name.
        score: its score (larger = more suspicious; inf for a non-finite pose).
        threshold: the threshold it was compared with.
        alarm: ``score > threshold``.
    """

    name: str
    score: float
    threshold: float
    alarm: bool


class Monitor(ABC):
    """Base class of every integrity monitor, and the whole contract of a monitor plugin.

    Args:
        threshold: the monitor fires when its score is larger than this (units of the score).
            Each monitor's default is a stated, uncalibrated value;
            :func:`icpbench.harness.monitoring.calibrate` sets it from clean registrations for a
            chosen false-alarm rate.
        **params: a subclass's own settings, recorded by :meth:`settings`.
    """

    #: Registry key; must equal the entry-point name the plugin is registered under.
    name: ClassVar[str] = ""
    #: One line for ``icpbench list``.
    description: ClassVar[str] = ""
    #: Valid values of the numeric settings (``threshold`` among them), checked by the registry
    #: before a monitor is built and by the constructor; NaN and Inf are refused for every setting.
    param_ranges: ClassVar[dict[str, Range]] = {}
    #: The score's unit (for tables and manifests), e.g. ``"m"`` or ``"1"`` (dimensionless).
    unit: ClassVar[str] = "1"
    #: Whether :meth:`differentiable_score` exists (the subclass implements
    #: :meth:`_differentiable_score`).
    differentiable: ClassVar[bool] = False

    def __init__(self, *, threshold: float, **params: Any) -> None:
        values = {"threshold": threshold, **params}
        for k, v in values.items():
            if isinstance(v, float | int) and not isinstance(v, bool) and not math.isfinite(v):
                raise InputError(f"setting {k!r} of monitor {self.name!r} must be a finite number, "
                                 f"got {v!r}")
        check_ranges(f"monitor {self.name!r}", values, self.param_ranges)
        self.threshold = float(threshold)
        self.params = params

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        for final_name in ("score", "check", "differentiable_score"):
            if final_name in cls.__dict__:
                raise TypeError(f"{cls.__name__} overrides Monitor.{final_name}, which is final (it "
                                "flags a non-finite pose and refuses a NaN score); implement _score")

    @classmethod
    def param_types(cls) -> dict[str, Any]:
        """Settings the monitor accepts (name -> type hint): the named keyword parameters of its
        ``__init__``. Unknown settings are refused and values are coerced to these types."""
        return keyword_params(cls.__init__)

    @abstractmethod
    def _score(self, inp: MonitorInput) -> float:
        """The score of a registration whose pose is finite (larger = more suspicious)."""

    @final
    def score(self, inp: MonitorInput) -> float:
        """The monitor's score of one registration (larger = more suspicious).

        A non-finite ``T_hat`` scores inf (a diverged registration is always flagged).

        Raises:
            InputError: ``inp`` is not a :class:`MonitorInput`, or lacks what the monitor needs.
            RuntimeError: the monitor returned NaN (a bug of the monitor).
        """
        if not isinstance(inp, MonitorInput):
            raise InputError(f"monitor {self.name!r} takes a MonitorInput, got {type(inp).__name__}")
        if not inp.pose_finite:
            return math.inf
        s = float(self._score(inp))
        if math.isnan(s):
            raise RuntimeError(f"monitor {self.name!r} returned NaN for sample {inp.sample_id!r}")
        return s

    @final
    def check(self, inp: MonitorInput) -> MonitorResult:
        """Score one registration and compare it with the threshold."""
        s = self.score(inp)
        return MonitorResult(self.name, s, self.threshold, bool(s > self.threshold))

    def _differentiable_score(self, x: DiffInput) -> torch.Tensor:
        """The score of a registration with a finite pose as a scalar tensor: the value of
        :meth:`_score` for the same registration, with a gradient with respect to ``x.scan`` and
        ``x.T_hat``. Implemented by the monitors that set ``differentiable``."""
        raise NotImplementedError(f"monitor {self.name!r} has no differentiable score")

    @final
    def differentiable_score(self, x: DiffInput) -> torch.Tensor:
        """The monitor's score of one registration as a scalar float64 tensor with a gradient
        (a non-finite pose scores inf, without one).

        Raises:
            InputError: the monitor has no differentiable score, or ``x`` is not a
                :class:`~icpbench.monitors.differentiable.DiffInput`.
            RuntimeError: the monitor returned NaN.
        """
        if not self.differentiable:
            raise InputError(f"monitor {self.name!r} has no differentiable score")
        if not isinstance(x, DiffInput):
            raise InputError(f"monitor {self.name!r} takes a DiffInput, got {type(x).__name__}")
        if not bool(torch.isfinite(x.T_hat.detach()).all()):
            return torch.tensor(math.inf, dtype=torch.float64)
        s = self._differentiable_score(x).to(torch.float64).reshape(())
        if bool(torch.isnan(s.detach())):
            raise RuntimeError(f"monitor {self.name!r} returned NaN for sample {x.sample_id!r}")
        return s

    def alarm(self, inp: MonitorInput) -> bool:
        """Whether the monitor fires on this registration (``score > threshold``)."""
        return self.check(inp).alarm

    def motion_prior(self, T_gt: np.ndarray, sample_id: str) -> MotionPrior | None:
        """The motion prior this monitor is given for a sample, simulated by the harness from the
        true pose ``T_gt`` (4, 4) (scan->map). Default: None (the monitor uses no prior)."""
        return None

    def with_threshold(self, threshold: float) -> Monitor:
        """A copy of this monitor with another threshold (the settings are otherwise the same)."""
        check_ranges(f"monitor {self.name!r}", {"threshold": threshold}, self.param_ranges)
        out = copy.copy(self)
        out.threshold = float(threshold)
        return out

    def settings(self) -> dict[str, Any]:
        """Settings recorded in a manifest (the threshold included)."""
        return {"threshold": self.threshold, **self.params}
