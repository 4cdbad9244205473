"""Calibration of integrity monitors: a threshold for a chosen false-alarm rate on clean data.

A monitor is only as strict as its threshold, and a threshold only means something against the
false alarms it causes: a check that fires on 10% of clean registrations would be switched off in
a real stack. The rule used here is the one of a constant false-alarm-rate detector: on n clean
registrations (no attack), the threshold is the ``k``-th smallest score with
``k = ceil((1 - rate) n)``, so that at most ``rate * n`` of them lie above it (``score > threshold``
fires). For new clean registrations exchangeable with the calibration set, the expected false-alarm
rate is then at most ``rate + 1 / (n + 1)`` (the split-conformal argument: the new score's rank
among the n + 1 is uniform; Angelopoulos and Bates, "A Gentle Introduction to Conformal Prediction
and Distribution-Free Uncertainty Quantification", 2021). The order statistic is used as it is (no
interpolation), so infinite scores (a degenerate scan) are allowed as long as fewer than
``rate * n`` of them exist.

The :class:`MonitorCalibration` record holds what a manifest stores; :func:`calibrated` gives the
monitor with the calibrated threshold.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from icpbench.core.errors import InputError
from icpbench.monitors.base import Monitor
from icpbench.monitors.inputs import MonitorInput
from icpbench.monitors.oracle import score_inputs

__all__ = ["MonitorCalibration", "calibrate", "calibrated", "clean_scores"]


@dataclass(frozen=True)
class MonitorCalibration:
    """A monitor's threshold for a false-alarm rate, and what it was set from.

    Attributes:
        monitor: the monitor's registry name.
        false_alarm_rate: the rate asked for (0..1).
        threshold: the calibrated threshold (units of the monitor's score).
        n: the number of clean scores it was set from.
        observed_rate: the share of those scores above the threshold (<= ``false_alarm_rate``).
        settings: the monitor's other settings (the threshold holds only for them).
    """

    monitor: str
    false_alarm_rate: float
    threshold: float
    n: int
    observed_rate: float
    settings: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Plain values for a manifest."""
        return asdict(self)


def calibrate(monitor: Monitor, clean_scores: Sequence[float] | np.ndarray,
              false_alarm_rate: float = 0.01) -> MonitorCalibration:
    """The threshold of ``monitor`` at which at most ``false_alarm_rate`` of the clean scores
    fire: the ``ceil((1 - rate) n)``-th smallest of the n scores (see the module docstring).

    Args:
        monitor: the monitor the scores come from (its name and settings are recorded).
        clean_scores: (n,) its scores on clean registrations.
        false_alarm_rate: the rate (0 < rate < 1).

    Raises:
        InputError: a rate outside (0, 1); scores that are not a flat list of numbers, any NaN;
            fewer than ``1 / rate`` scores (the rate cannot be told from the largest score); a
            threshold that is infinite (more than ``rate * n`` clean scores are inf) or outside
            the monitor's range of thresholds.
    """
    rate = float(false_alarm_rate)
    if not (0.0 < rate < 1.0):
        raise InputError(f"false_alarm_rate must be between 0 and 1 (exclusive), got {false_alarm_rate!r}")
    s = np.asarray(clean_scores, dtype=np.float64)
    if s.ndim != 1 or s.size == 0:
        raise InputError(f"calibration of {monitor.name!r}: clean scores must be a non-empty flat "
                         f"list, got shape {s.shape}")
    if np.isnan(s).any():
        raise InputError(f"calibration of {monitor.name!r}: {int(np.isnan(s).sum())} clean score(s) "
                         "are NaN")
    n = s.size
    need = math.ceil(1.0 / rate - 1e-9)
    if n < need:
        raise InputError(f"calibration of {monitor.name!r} at a false-alarm rate of {rate:g} needs at "
                         f"least {need} clean scores, got {n}")
    k = math.ceil((1.0 - rate) * n - 1e-9)  # 1-based rank; the tolerance absorbs 0.99 * 1000 = 990.0...1
    threshold = float(np.sort(s)[k - 1])
    if not math.isfinite(threshold):
        raise InputError(f"calibration of {monitor.name!r}: more than {rate:g} of the clean scores are "
                         "infinite; no finite threshold reaches that false-alarm rate")
    calibrated(monitor, threshold)  # the monitor's range of thresholds
    settings = {k_: v for k_, v in monitor.settings().items() if k_ != "threshold"}
    return MonitorCalibration(monitor=monitor.name, false_alarm_rate=rate, threshold=threshold, n=n,
                              observed_rate=float(np.mean(s > threshold)), settings=settings)


def calibrated(monitor: Monitor, calibration: MonitorCalibration | float) -> Monitor:
    """``monitor`` with the calibrated threshold (a record of this monitor, or a number).

    Raises:
        InputError: the record is another monitor's, or the threshold is outside its range.
    """
    if isinstance(calibration, MonitorCalibration):
        if calibration.monitor != monitor.name:
            raise InputError(f"calibration of {calibration.monitor!r} given to monitor {monitor.name!r}")
        return monitor.with_threshold(calibration.threshold)
    return monitor.with_threshold(float(calibration))


def clean_scores(monitor: Monitor, inputs: Sequence[MonitorInput],
                 T_gt: Sequence[np.ndarray] | np.ndarray | None = None) -> np.ndarray:
    """(K,) scores of ``monitor`` on K clean registrations.

    Args:
        monitor: the monitor.
        inputs: K monitor inputs of clean registrations.
        T_gt: (K, 4, 4) true scan->map poses, from which a monitor that uses a motion prior is
            given its simulated prior (:meth:`Monitor.motion_prior`, seeded by each input's
            ``sample_id``); not needed otherwise, and ignored where an input has a prior.
    """
    priors = None
    if T_gt is not None:
        if len(T_gt) != len(inputs):
            raise InputError(f"clean scores: got {len(T_gt)} true poses for {len(inputs)} inputs")
        priors = {monitor.name: [None if x.prior is not None else
                                 monitor.motion_prior(np.asarray(T, dtype=np.float64), x.sample_id)
                                 for x, T in zip(inputs, T_gt, strict=True)]}
    return score_inputs([monitor], inputs, priors)[monitor.name]
