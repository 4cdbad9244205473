"""Integrity monitors in ``icpbench run``: thresholds calibrated on clean scans of the training
split, and the alarms of every registration the run makes.

With ``--monitors`` (:attr:`RunConfig.monitors <icpbench.harness.runner.RunConfig.monitors>`),
before the grid each monitor's threshold is set per target for the false-alarm rate
``false_alarm_rate`` (:func:`~icpbench.harness.monitoring.calibrate`) from the target's clean
registrations of the first ``calibration_samples`` scans of the dataset's ``train`` split (the
test split is never used to set a threshold). The thresholds are recorded in the manifest under
``monitors``. Every row of the run then carries, in its ``extra`` column, each monitor's score
(``monitor_score.<name>``) and alarm (``monitor_alarm.<name>``, 1 or 0) on the registration the
row measured, and ``monitor_alarm.any``; ``icpbench table`` turns them into the detection rate of
each attack and the error that reaches the planner undetected (:mod:`icpbench.harness.monitor_report`).

With ``monitor_aware``, the query attacks see a
:class:`~icpbench.monitors.oracle.MonitoredOracle` (errors of flagged candidates hidden), so they
maximise the undetected error (attacks that know the monitors); otherwise they ignore them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.types import Batch, Registration
from icpbench.harness.monitoring import MonitorCalibration, calibrate, calibrated
from icpbench.monitors.base import Monitor
from icpbench.monitors.oracle import MonitoredOracle, registration_inputs, score_inputs

if TYPE_CHECKING:
    from icpbench.attacks.base import AttackOutput
    from icpbench.harness.runner import RunConfig
    from icpbench.targets.base import Target

__all__ = ["ALARM", "SCORE", "build_monitors", "calibrate_run", "monitor_extra", "thresholds_of"]

#: Prefixes of the ``extra`` keys of a row (``monitor_alarm.<name>``, ``monitor_score.<name>``).
ALARM, SCORE = "monitor_alarm.", "monitor_score."


def build_monitors(cfg: RunConfig) -> list[Monitor]:
    """The run's monitors with their settings (thresholds not yet calibrated)."""
    return [registry.monitors.get(n)(**cfg.monitor_params.get(n, {})) for n in cfg.monitors]


def batch_scores(monitors: list[Monitor], batch: Batch, scans: torch.Tensor,
                 reg: Registration) -> dict[str, np.ndarray]:
    """Every monitor's scores ``{name: (B,)}`` of the registration ``reg`` of ``scans``
    (B, N, 3, sensor frame) of ``batch``'s samples, each monitor with its simulated motion prior."""
    T = reg.T.detach().to(torch.float64).numpy()
    inputs = registration_inputs(batch, scans.detach().to(torch.float64).numpy(), T, reg,
                                 range(len(batch)))
    T_gt = batch.T_gt.detach().to(torch.float64).numpy()
    priors = {m.name: [m.motion_prior(T_gt[b], s.id) for b, s in enumerate(batch.samples)]
              for m in monitors}
    return score_inputs(monitors, inputs, priors)


def _clean_scores(target: Target, monitors: list[Monitor], batch: Batch,
                  prepare: Callable[[Target, Batch], list]) -> dict[str, np.ndarray]:
    """Every monitor's scores of ``target``'s clean registrations of ``batch``."""
    with torch.no_grad():
        reg = target.register(batch.scans, prepare(target, batch), batch.T_init)
    return batch_scores(monitors, batch, batch.scans, reg)


def calibrate_run(cfg: RunConfig, targets: Mapping[str, Target],
                  prepare: Callable[[Target, Batch], list],
                  progress: Callable[[str], None] | None = None
                  ) -> dict[str, dict[str, MonitorCalibration]]:
    """``{target: {monitor: calibration}}`` from clean registrations of the calibration scans
    (``cfg.calibration_split``: the train split, or the evaluated split's held-out scans).

    Args:
        cfg: the run (monitors, their settings, ``false_alarm_rate``, ``calibration_samples``,
            the dataset and its settings, ``batch_size``).
        targets: the run's targets by name.
        prepare: ``(target, batch) -> maps`` in the form the target's ``register`` takes.
        progress: called with a line per target (None: quiet).

    Raises:
        InputError: the calibration scans are fewer usable ones than the rate needs
            (``ceil(1 / rate)``), or a calibration fails (see :func:`calibrate`).
    """
    from icpbench.harness.runner import load_dataset

    need = math.ceil(1.0 / cfg.false_alarm_rate - 1e-9)
    source, first, where = _calibration_scans(cfg)
    data = load_dataset(source)
    samples = []
    for i in range(first, min(first + cfg.calibration_samples, len(data))):
        try:
            samples.append(data[i].validate())
        except InputError:
            continue  # a bad file: calibrate on the others
    if len(samples) < need:
        raise InputError(
            f"monitor calibration at a false-alarm rate of {cfg.false_alarm_rate:g} needs at least "
            f"{need} clean scans of {where}, got {len(samples)} (of "
            f"calibration_samples={cfg.calibration_samples}); raise --calibration-samples or "
            "--false-alarm-rate" + (", or lower --samples" if first else ""))
    monitors = build_monitors(cfg)
    out: dict[str, dict[str, MonitorCalibration]] = {}
    for tname, target in targets.items():
        if progress is not None:
            progress(f"calibrating {', '.join(cfg.monitors)} on {len(samples)} clean scans of "
                     f"{where} registered by {tname}")
        scores: dict[str, list[float]] = {m.name: [] for m in monitors}
        for lo in range(0, len(samples), cfg.batch_size):
            batch = Batch.from_samples(samples[lo:lo + cfg.batch_size])
            for name, s in _clean_scores(target, monitors, batch, prepare).items():
                scores[name] += s.tolist()
        out[tname] = {m.name: calibrate(m, scores[m.name], cfg.false_alarm_rate)
                      for m in monitors}
    return out


def _calibration_scans(cfg: RunConfig) -> tuple[RunConfig, int, str]:
    """Where the calibration scans come from: the configuration of their dataset, the index of
    the first, and its name in messages. ``train``: the train split from its start; ``heldout``:
    the evaluated split after the first ``samples`` (the scans the run evaluates are never among
    them)."""
    from dataclasses import replace

    if cfg.calibration_split == "heldout":
        return cfg, int(cfg.samples or 0), (f"the {cfg.dataset!r} {cfg.split} split after its "
                                            f"first {cfg.samples} (held out)")
    return replace(cfg, split="train"), 0, f"the {cfg.dataset!r} train split"


def thresholds_of(cal: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """``{target: {monitor: threshold}}`` of calibrations (records or their manifest dicts)."""
    return {t: {m: float(c["threshold"] if isinstance(c, Mapping) else c.threshold)
                for m, c in per.items()} for t, per in cal.items()}


def calibrated_monitors(cfg: RunConfig, thresholds: Mapping[str, float]) -> list[Monitor]:
    """The run's monitors with one target's calibrated thresholds."""
    return [calibrated(m, thresholds[m.name]) for m in build_monitors(cfg)]


def undetected_output(oracle: MonitoredOracle, out: AttackOutput, batch: Batch,
                      budget_m: float) -> AttackOutput:
    """A monitor-aware attack's output with each sample's scan replaced by the best candidate no
    monitor flagged, where the attack's own is flagged or scored less
    (:meth:`MonitoredOracle.keep_undetected`); the displacement audit and the query counts are
    those of the scans returned."""
    from icpbench.attacks import base

    before = oracle.queries.copy()
    scans = oracle.keep_undetected(out.scans)
    stats = base.displacement_stats(batch.scans.to(scans.dtype), scans, budget_m)
    stats["disp_max_raw"] = stats["disp_max"].clone()
    extra = dict(out.extra)
    extra["queries"] = torch.as_tensor(np.asarray(extra.get("queries", 0)) + oracle.queries - before)
    return base.AttackOutput(scans=scans, stats=stats, extra=extra)


def monitor_extra(monitors: list[Monitor], batch: Batch, scans: torch.Tensor, reg: Registration
                  ) -> list[dict[str, float]]:
    """Per sample of ``batch``, the ``extra`` entries of its row: each monitor's score and alarm
    on the registration ``reg`` of ``scans`` (B, N, 3), and whether any monitor fired."""
    scores = batch_scores(monitors, batch, scans, reg)
    rows = []
    for b in range(len(batch)):
        d: dict[str, float] = {}
        for m in monitors:
            s = float(scores[m.name][b])
            d[SCORE + m.name] = s
            d[ALARM + m.name] = float(s > m.threshold)
        d[ALARM + "any"] = float(any(d[ALARM + m.name] for m in monitors))
        rows.append(d)
    return rows
