"""The evaluated target behind integrity monitors: query access that hides detected errors.

A :class:`MonitoredOracle` is a :class:`~icpbench.targets.oracle.QueryOracle` (same interface:
``register``, ``errors``, ``queries``, ``target``, ``batch``, ``name``) whose errors are NaN for
every candidate scan that any of its monitors flags. The query-only attacks of the harness already
treat NaN as "never the largest error" (a diverged pose scores NaN), so each of them, run on this
oracle without change, maximises the *undetected* error: the largest error a localisation stack
that checks its registrations would accept. The oracle counts the flagged queries per sample
(:attr:`MonitoredOracle.flagged`) and per monitor (:attr:`MonitoredOracle.alarms`).

Frames and units as in the query oracle: scans (K, N, 3) in the sensor frame, poses ``T_map_scan``
(4, 4), errors in metres; the monitors see each candidate scan, the sample's map (the batch's
``MapIndex`` with normals) and the pose and health the target returned
(:class:`~icpbench.monitors.inputs.MonitorInput`), and a monitor that uses a motion prior the one
it simulates once per sample from the true pose (:meth:`~icpbench.monitors.base.Monitor.motion_prior`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.types import Batch, Registration
from icpbench.monitors.base import Monitor
from icpbench.monitors.inputs import MonitorInput, MotionPrior
from icpbench.monitors.penalty import MonitorPenalty
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

__all__ = ["MonitoredOracle", "registration_inputs", "score_inputs"]


def registration_inputs(batch: Batch, scans: np.ndarray, T: np.ndarray, reg: Registration,
                        index: Sequence[int]) -> list[MonitorInput]:
    """The monitor inputs of K registrations of samples ``index`` of ``batch``.

    Args:
        batch: the batch (its ``maps``, ``MapIndex`` with normals, are the monitors' maps).
        scans: (K, N, 3) registered scans, sensor frame.
        T: (K, 4, 4) float64 estimated scan->map transforms.
        reg: the target's :class:`~icpbench.core.types.Registration` of these K scans (health).
        index: the K sample indices into ``batch``.
    """
    maps = batch.maps
    it, conv, inl = (torch.as_tensor(v).detach().cpu().reshape(-1).numpy()
                     for v in (reg.iterations, reg.converged, reg.inlier_fraction))
    return [MonitorInput(scan=scans[k], map=maps[i], T_hat=T[k], iterations=int(it[k]),
                         converged=bool(conv[k]), inlier_fraction=float(inl[k]),
                         sample_id=batch.samples[i].id)
            for k, i in enumerate(int(i) for i in index)]


def score_inputs(monitors: Sequence[Monitor], inputs: Sequence[MonitorInput],
                 priors: dict[str, Sequence[MotionPrior | None]] | None = None
                 ) -> dict[str, np.ndarray]:
    """Every monitor's scores of K inputs: ``{name: (K,) float64}``.

    Args:
        monitors: the monitors.
        inputs: K monitor inputs (without priors).
        priors: ``{monitor name: K priors}`` for the monitors that use one; a monitor whose prior
            is None scores the input as it is.
    """
    out = {}
    for m in monitors:
        pri = (priors or {}).get(m.name) or [None] * len(inputs)
        out[m.name] = np.array([m.score(x if p is None else dataclasses.replace(x, prior=p))
                                for x, p in zip(inputs, pri, strict=True)], dtype=np.float64)
    return out


class MonitoredOracle(QueryOracle):
    """A query oracle whose error is NaN for every candidate a monitor flags.

    Args:
        target: the target the rows are evaluated on.
        batch: the batch under attack (true poses, initial guesses and the maps the monitors use).
        maps: B maps in the form ``target.register`` takes (as for :class:`QueryOracle`).
        monitors: the monitors, each with its threshold (calibrated or not); their names must
            differ (the counts are kept per name).

    Attributes:
        flagged: (B,) int64 number of queries of each sample that at least one monitor flagged
            (a non-finite pose is always flagged).
        alarms: ``{monitor name: (B,) int64}`` the queries each monitor flagged.
        priors: ``{monitor name: B priors}``, the motion prior each monitor was given per sample
            (None for monitors without one), drawn once when the oracle is built.
        last_scores: ``{monitor name: (K,) float64}`` scores of the latest query.
        last_flagged: (K,) bool, the candidates of the latest query that were flagged.
        best_error: (B,) the largest finite error of an unflagged candidate seen so far per
            sample (-inf: none yet); ``best_scan`` holds that candidate (None: none yet).
    """

    hides_detected: ClassVar[bool] = True

    def __init__(self, target: Target, batch: Batch, maps: Sequence[Any],
                 monitors: Sequence[Monitor]) -> None:
        super().__init__(target, batch, maps)
        monitors = list(monitors)
        if not monitors:
            raise InputError("monitored oracle: give at least one monitor")
        for m in monitors:
            if not isinstance(m, Monitor):
                raise InputError(f"monitored oracle: {type(m).__name__} is not a Monitor")
        names = [m.name for m in monitors]
        if len(set(names)) != len(names):
            raise InputError(f"monitored oracle: monitor names must differ, got {', '.join(names)}")
        self.monitors = monitors
        B = len(batch)
        self.flagged = np.zeros(B, dtype=np.int64)
        self.alarms = {n: np.zeros(B, dtype=np.int64) for n in names}
        T_gt = batch.T_gt.detach().to(torch.float64).numpy()
        self.priors: dict[str, list[MotionPrior | None]] = {
            m.name: [m.motion_prior(T_gt[b], s.id) for b, s in enumerate(batch.samples)]
            for m in monitors}
        self.last_scores: dict[str, np.ndarray] = {}
        self.last_flagged = np.zeros(0, dtype=bool)
        self.best_error = np.full(B, -np.inf)
        self.best_scan: list[torch.Tensor | None] = [None] * B

    @classmethod
    def wrap(cls, oracle: QueryOracle, monitors: Sequence[Monitor]) -> MonitoredOracle:
        """The monitored oracle of an existing oracle's target, batch and maps (fresh counts)."""
        return cls(oracle.target, oracle.batch, oracle.maps, monitors)

    def _judge(self, scans: torch.Tensor, T: np.ndarray, reg: Registration, idx: np.ndarray,
               err: np.ndarray) -> np.ndarray:
        """As :meth:`QueryOracle.register` (the same registration, pose and error), except that
        the error is NaN where a monitor fires (the target's status is returned unchanged)."""
        flags = self._check(scans.detach().to(torch.float64).numpy(), T, reg, idx)
        for k in np.flatnonzero(~flags & np.isfinite(err)):
            b = int(idx[k])
            if err[k] > self.best_error[b]:
                self.best_error[b], self.best_scan[b] = float(err[k]), scans[k].detach().clone()
        return np.where(flags, np.nan, err)

    def penalty(self) -> MonitorPenalty:
        """The monitors as a penalty on the batch's scans (their priors as drawn here), for the
        gradient member of the ``ensemble`` (:mod:`icpbench.monitors.penalty`)."""
        return MonitorPenalty(self.monitors, self.batch.maps, self.priors,
                              [s.id for s in self.batch.samples])

    def keep_undetected(self, adv: torch.Tensor) -> torch.Tensor:
        """The scans (B, N, 3) to report for an attack that returned ``adv``: per sample, ``adv``
        if no monitor flags it and no unflagged candidate seen scored a larger error, else the
        best unflagged candidate seen; where none was seen, the clean scan if it passes (else
        ``adv``). Costs one query per sample (two where the clean scan is tried)."""
        out = adv.detach().clone()
        seen = self.best_error.copy()  # before this check adds adv itself
        err = self.errors(out)
        for b in range(len(self.batch)):
            if np.isfinite(seen[b]) and not (np.isfinite(err[b]) and err[b] >= seen[b]):
                out[b] = self.best_scan[b].to(out.dtype)
        missing = np.flatnonzero(~np.isfinite(self.best_error))
        if missing.size:
            clean = self.batch.scans[torch.as_tensor(missing)].to(out.dtype)
            passed = np.isfinite(self.errors(clean, missing))
            for j, b in enumerate(missing):
                if passed[j]:
                    out[b] = clean[j]
        return out

    def _check(self, scans: np.ndarray, T: np.ndarray, reg: Registration, idx: np.ndarray
               ) -> np.ndarray:
        """Score K registrations with every monitor, count the alarms; (K,) bool flagged."""
        inputs = registration_inputs(self.batch, scans, T, reg, idx)
        priors = {n: [p[i] for i in idx] for n, p in self.priors.items()}
        self.last_scores = score_inputs(self.monitors, inputs, priors)
        flags = np.zeros(idx.size, dtype=bool)
        for m in self.monitors:
            hit = self.last_scores[m.name] > m.threshold
            np.add.at(self.alarms[m.name], idx[hit], 1)
            flags |= hit
        np.add.at(self.flagged, idx[flags], 1)
        self.last_flagged = flags
        return flags

    def record(self) -> dict[str, Any]:
        """Plain values for a manifest: each monitor's settings and alarm counts, the flagged and
        total query counts per sample, and the motion priors drawn."""
        ids = [s.id for s in self.batch.samples]
        return {
            "monitors": {m.name: m.settings() for m in self.monitors},
            "samples": ids,
            "queries": self.queries.tolist(),
            "flagged": self.flagged.tolist(),
            "alarms": {n: a.tolist() for n, a in self.alarms.items()},
            "priors": {n: [None if p is None else p.as_dict() for p in ps]
                       for n, ps in self.priors.items() if any(p is not None for p in ps)},
        }
