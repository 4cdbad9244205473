"""Query access to the evaluated target: what a query-only (score-based) attack may ask.

A :class:`QueryOracle` wraps one target and one batch: an attack hands it adversarial scans of
(some of) the batch's samples and gets back the pose the target estimates and its horizontal error
``trans_err_xy`` against the true pose, the quantity Table 1 reports. Nothing else of the target is
exposed (no gradient, no correspondences), so an attack that uses only the oracle runs against any
target, black boxes included, as the score-based attacks of image classification do (Andriushchenko
et al., "Square Attack: a query-efficient black-box adversarial attack via random search",
ECCV 2020). Every registration of a sample counts as one query of that sample; the runner records
the counts per row.

Where the target has an *exact replica* (:meth:`~icpbench.targets.base.Target.exact_replica`: a
faster implementation measured to register every scan as the target does, to rounding), the oracle
may let it answer (``answer_with``): the attack sees the same poses sooner, and nothing it reports
changes, since the runner registers every attack's output with the target itself.

Frames: scans (B, N, 3) in the sensor frame; poses ``T_map_scan`` (4, 4); errors in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.targets.base import Target


class QueryOracle:
    """The evaluated target, for one batch, as a counted query interface.

    Args:
        target: the target the rows are evaluated on.
        batch: the batch under attack (true poses and initial guesses).
        maps: B maps in the form ``target.register`` takes (prepared handles for a black box, the
            batch's ``MapIndex`` for a differentiable target).
        answer_with: a target that registers the queries in ``target``'s place (its
            :meth:`~icpbench.targets.base.Target.exact_replica`), on the batch's ``MapIndex`` maps
            (a differentiable target, or one with ``takes_map_index``); None:
            the target itself. ``target`` stays the evaluated one: its name, settings and cost
            model are what attacks read.
    """

    #: The oracle reports NaN for candidates that integrity monitors flag (a
    #: :class:`~icpbench.monitors.oracle.MonitoredOracle`): an attack then maximises the
    #: *undetected* error, and the ``ensemble`` adds its monitor-aware members.
    hides_detected: ClassVar[bool] = False

    def __init__(self, target: Target, batch: Batch, maps: Sequence[Any],
                 answer_with: Target | None = None) -> None:
        if len(maps) != len(batch):
            raise InputError(f"oracle: got {len(maps)} maps for a batch of {len(batch)} scans")
        if answer_with is not None and not (answer_with.differentiable
                                            or answer_with.takes_map_index):
            raise InputError(f"oracle: {answer_with.name!r} cannot answer for {target.name!r}: "
                             "an answering replica registers on the batch's maps, so it must be "
                             "a differentiable target or take MapIndex maps")
        self.target = target
        self.answer_with = answer_with
        self.batch = batch
        self.maps = list(maps)
        self.queries = np.zeros(len(batch), dtype=np.int64)

    @classmethod
    def prepared(cls, target: Target, batch: Batch, **settings: Any) -> QueryOracle:
        """The oracle of ``target`` on ``batch`` with its maps prepared here: the batch's
        ``MapIndex`` for a differentiable target, ``target.prepare`` of each map otherwise (the
        runner shares prepared maps across batches instead); ``settings`` go to the constructor
        of a subclass."""
        maps = batch.maps if target.differentiable else [
            target.prepare(s.map, s.map_normals) for s in batch.samples]
        return cls(target, batch, maps, **settings)

    @property
    def name(self) -> str:
        """The evaluated target's registry name."""
        return self.target.name

    def penalty(self) -> Any:
        """What a gradient attack subtracts from its objective so its candidates pass what this
        oracle checks: None here (nothing is checked); a
        :class:`~icpbench.monitors.penalty.MonitorPenalty` for a monitored oracle."""
        return None

    def register(self, scans: torch.Tensor | np.ndarray, index: Sequence[int] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Register adversarial scans with the target (one query per sample).

        Args:
            scans: (K, N, 3) scans, sensor frame, of the samples ``index`` (default: all B, K = B).
            index: which samples of the batch the K scans belong to.

        Returns:
            ``(T, err_xy, status)``: estimated poses (K, 4, 4) float64, horizontal errors
            ``||rho_xy||`` (K,) in metres (NaN where the pose is not finite: an attack should not
            count a diverged estimate as a large error, since Table 1 cannot average it) and the
            target's per-sample status.
        """
        idx = np.arange(len(self.batch)) if index is None else np.asarray(index, dtype=np.int64)
        x = torch.as_tensor(np.asarray(scans) if isinstance(scans, np.ndarray) else scans.detach())
        if x.ndim != 3 or x.shape[0] != idx.size or x.shape[-1] != 3:
            raise InputError(f"oracle: scans must have shape ({idx.size}, N, 3), got "
                             f"{tuple(x.shape)}")
        sel = torch.as_tensor(idx)
        who, maps = ((self.target, self.maps) if self.answer_with is None
                     else (self.answer_with, self.batch.maps))
        with torch.no_grad():
            reg = who.register(x.to(self.batch.scans.dtype), [maps[i] for i in idx],
                               self.batch.T_init[sel])
        np.add.at(self.queries, idx, 1)
        T = reg.T.detach().to(torch.float64)
        xi = pose_error(T, self.batch.T_gt[sel].to(torch.float64))
        err = torch.linalg.norm(xi[:, :2], dim=-1).numpy()
        err = np.where(np.isfinite(err), err, np.nan)
        T_np = T.numpy()
        return T_np, self._judge(x, T_np, reg, idx, err), list(reg.status)

    def _judge(self, scans: torch.Tensor, T: np.ndarray, reg: Any, idx: np.ndarray,
               err: np.ndarray) -> np.ndarray:
        """The errors (K,) an attack is told for K registrations of ``scans`` (K, N, 3) at poses
        ``T`` (K, 4, 4) of the samples ``idx``: here ``err`` itself; a subclass may hide some
        (e.g. those an integrity monitor flags)."""
        return err

    def errors(self, scans: torch.Tensor | np.ndarray, index: Sequence[int] | None = None
               ) -> np.ndarray:
        """Horizontal errors (K,) in metres of the target on ``scans`` (see :meth:`register`)."""
        return self.register(scans, index)[1]
