"""The iterated analytic worst case: the sector step, re-linearised where the attacked ICP lands.

Beyond the paper. The sector baseline (Laconte, Lisus and Barfoot, RA-L 2024, arXiv 2309.04251;
:mod:`icpbench.core.sector_math`) linearises one point-to-plane step at the *true* pose. Once its
corruption is applied, ICP settles elsewhere, with other correspondences, where the one-step model
no longer describes what moves the estimate. This computation repeats the analytic step at the pose
the surrogate ICP actually reaches, as the basic iterative method repeats a one-step attack
(Kurakin, Goodfellow and Bengio, "Adversarial examples in the physical world", ICLR workshop 2017):

1. start from the sector attack (every associated point moved by lambda along its map normal);
2. run the surrogate ICP (forward only, no gradient) on the current adversarial scan from the
   initial guess, giving ``T_k`` and the horizontal error direction ``e_k`` (map frame, unit);
3. associate the *adversarial* points at ``T_k``, build the one-step sensitivity ``G`` there and
   move every associated point by ``step_size * lambda`` along its new normal, with the sign that
   pushes the estimate further along ``e_k`` (``sign(e_k . G_xy,i)``); project each point's total
   displacement back onto its lambda-ball;
4. repeat ``iterations`` times; return, per scan, the iterate with the largest surrogate error
   ``||rho_xy||`` (the start included, so it is never below the sector attack on the surrogate).

One settings type, :class:`SectorIterSettings`, serves every user of this computation: the
``sector-iter`` attack, the prior channels of the shipped generator, and the warm start of ``pgd``
and ``pgd-warm``. The result is kept in the batch's memo, so that in one run the generator's prior
and the ``sector-iter`` row cost the computation once when their settings agree (they do by
default).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from icpbench.core import sector_math as sector
from icpbench.core.errors import InputError
from icpbench.core.projection import clip_displacements
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch

if TYPE_CHECKING:
    from icpbench.targets.base import Target

#: Errors below this (metres) have no direction; the sector start's predicted one is used.
_MIN_ERR_M = 1e-6
#: Association gate (metres) when neither the settings nor the surrogate give one: the lidar preset's.
DEFAULT_DMAX_M = 5.0


@dataclass(frozen=True)
class SectorIterSettings:
    """Settings of the iterated analytic attack (module docstring).

    Attributes:
        iterations: re-linearisation steps after the sector start (0: the sector attack with the
            surrogate's association gate). 2 by default, so that Table 1 stays within its time
            budget; more steps find more at about one surrogate ICP per step and scan
            (the trade on 48 lidar-sim test scans: docs/findings.md).
        step_size: length of each step along the normals, as a fraction of lambda, in (0, 2].
        icp_iterations: iteration cap of the surrogate ICP that locates the attacked pose (100: the
            lidar evaluation ICP's cap, so the attack aims at the pose the evaluation reaches).
        icp_nn_reuse: the surrogate ICP's approximate correspondences (``ICPConfig.nn_reuse_m``,
            metres): a point keeps its map row while it moves less than this since its last
            KD-tree query; 0 (default): exact nearest neighbours, whose forward passes the
            evaluation ICP of the same settings takes from its cache
            (:mod:`icpbench.targets.forward_cache`) instead of running them again.
        d_max: association gate of the analytic steps (metres); None: the surrogate's own gate
            (:data:`DEFAULT_DMAX_M` when it has none).
    """

    iterations: int = 2
    step_size: float = 0.5
    icp_iterations: int = 100
    icp_nn_reuse: float = 0.0
    d_max: float | None = None

    def __post_init__(self) -> None:
        for name in ("iterations", "icp_iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v:
                raise InputError(f"sector-iter {name} must be an integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.iterations < 0 or self.icp_iterations < 1:
            raise InputError(f"sector-iter needs iterations >= 0 and icp_iterations >= 1, got "
                             f"{self.iterations} and {self.icp_iterations}")
        step = float(self.step_size)
        if not 0 < step <= 2:
            raise InputError(f"sector-iter step_size must be in (0, 2] (fraction of lambda), got "
                             f"{self.step_size}")
        reuse = float(self.icp_nn_reuse)
        if not (math.isfinite(reuse) and reuse >= 0):
            raise InputError(f"sector-iter icp_nn_reuse must be a finite number >= 0 (metres), got "
                             f"{self.icp_nn_reuse}")
        object.__setattr__(self, "step_size", step)
        object.__setattr__(self, "icp_nn_reuse", reuse)
        if self.d_max is not None:
            d = float(self.d_max)
            if not (math.isfinite(d) and d > 0):
                raise InputError(f"sector-iter d_max must be > 0 metres, got {self.d_max}")
            object.__setattr__(self, "d_max", d)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any] | SectorIterSettings | None,
                     owner: str = "sector-iter settings") -> SectorIterSettings:
        """Settings from a mapping of field names (missing ones keep their defaults).

        Raises:
            InputError: an unknown name (the message lists the valid ones) or a bad value.
        """
        if isinstance(values, SectorIterSettings):
            return values
        values = dict(values or {})
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise InputError(f"unknown setting(s) {', '.join(map(repr, unknown))} for {owner}; "
                             f"valid: {', '.join(names)}")
        try:
            return cls(**values)
        except (TypeError, ValueError) as exc:
            raise InputError(f"bad {owner} {values}: {exc}") from exc

    def with_(self, **changes: Any) -> SectorIterSettings:
        """A copy with some fields changed (checked)."""
        return replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """The settings as a JSON-serialisable dict."""
        return asdict(self)

    def surrogate(self, target: Target) -> Target:
        """``target`` with this iteration cap and correspondence reuse (a copy; forward use)."""
        icp = target.with_max_iterations(self.icp_iterations)
        return icp.with_settings(nn_reuse_m=self.icp_nn_reuse) if self.icp_nn_reuse > 0 else icp

    def gate(self, target: Target) -> float:
        """The association gate (metres) of the analytic steps on ``target``."""
        if self.d_max is not None:
            return self.d_max
        d = getattr(getattr(target, "config", None), "d_max", None)
        return float(d) if d is not None else DEFAULT_DMAX_M


@dataclass
class IteratedSectorResult:
    """Output of :func:`iterated_sector` for a batch of B scans.

    Attributes:
        scans: (B, N, 3) float64 adversarial scans, sensor frame, metres (within lambda per point).
        best_iterate: (B,) index of the returned iterate (0: the sector start; NaN: left clean).
        surrogate_xy: (B,) horizontal surrogate error of the returned iterate (metres; NaN: left clean).
        seconds: wall time the computation took (seconds, whole batch).
    """

    scans: np.ndarray
    best_iterate: np.ndarray
    surrogate_xy: np.ndarray
    seconds: float


def surrogate_key(target: Target | None) -> tuple[str, str]:
    """What identifies a surrogate in a batch memo key: its class and its settings."""
    return type(target).__name__, repr(getattr(target, "config", None))


def _memo_key(settings: SectorIterSettings, budget_m: float, target: Target) -> tuple:
    return ("sector-iter", float(budget_m), settings, *surrogate_key(target))


def is_memoised(batch: Batch, budget_m: float, surrogate: Target,
                settings: SectorIterSettings | None = None) -> bool:
    """Whether :func:`iterated_sector` with these arguments would take its result from the memo."""
    return _memo_key(settings or SectorIterSettings(), budget_m, surrogate) in batch.memo


def iterated_sector(batch: Batch, budget_m: float, surrogate: Target,
                    settings: SectorIterSettings | None = None) -> IteratedSectorResult:
    """The iterated analytic attack on ``batch`` at budget ``budget_m`` (metres) through
    ``surrogate`` (module docstring), memoised in ``batch.memo``.

    Samples with fewer than 6 associated points at the true pose are left clean (as the sector
    attack leaves them); the budget holds exactly (projection after every step).

    Raises:
        InputError: the sector model fails on a sample that has enough correspondences.
    """
    settings = settings or SectorIterSettings()
    key = _memo_key(settings, budget_m, surrogate)
    if key not in batch.memo:
        batch.memo[key] = _compute(batch, float(budget_m), surrogate, settings)
    return batch.memo[key]


def _compute(batch: Batch, budget_m: float, surrogate: Target,
             settings: SectorIterSettings) -> IteratedSectorResult:
    t0 = time.perf_counter()
    icp = settings.surrogate(surrogate)
    d_max = settings.gate(icp)
    clean = batch.scans.detach().to(torch.float64).cpu().numpy()
    T_gt = batch.T_gt.detach().to(torch.float64).cpu().numpy()
    B = clean.shape[0]
    adv = clean.copy()
    ehat0 = np.zeros((B, 2))
    live = np.zeros(B, dtype=bool)
    for b in range(B):  # the sector start
        try:
            model = sector.analyse(clean[b], T_gt[b], batch.maps[b], d_max=d_max)
        except InputError:
            if sector.associate(clean[b], T_gt[b], batch.maps[b], d_max).n_valid >= 6:
                raise
            continue  # too few correspondences: left clean, as the sector attack does
        adv[b], _, xi = model.attack(budget_m, ("x", "y"), 1)
        ehat0[b] = xi[:2] / max(float(np.hypot(xi[0], xi[1])), 1e-12)
        live[b] = True
    best, best_val = adv.copy(), np.full(B, -np.inf)
    best_k = np.zeros(B)
    step = settings.step_size * budget_m
    for k in range(settings.iterations + 1):
        idx = np.flatnonzero(live)
        if idx.size == 0:
            break
        with torch.no_grad():
            sel = torch.as_tensor(idx)
            reg = icp.register(torch.as_tensor(adv[idx]), [batch.maps[i] for i in idx],
                               batch.T_init[sel].to(torch.float64))
            T_hat = reg.T.to(torch.float64)
            xi = pose_error(T_hat, batch.T_gt[sel].to(torch.float64)).cpu().numpy()
            T_hat = T_hat.cpu().numpy()
        for j, b in enumerate(idx):
            err = float(np.hypot(xi[j, 0], xi[j, 1]))
            if err > best_val[b]:
                best_val[b], best[b], best_k[b] = err, adv[b], k
            if k == settings.iterations:
                continue
            try:  # linearise the attacked scan where the surrogate put it
                m = sector.analyse(adv[b], T_hat[j], batch.maps[b], d_max=d_max)
            except InputError:
                live[b] = False  # the estimate left the map: keep the best so far
                continue
            e = xi[j, :2] / err if err > _MIN_ERR_M else ehat0[b]
            v = m.assoc.valid
            sign = np.where(e @ m.G[:2] < 0, -1.0, 1.0)
            n_s = m.assoc.normals_map[v] @ T_hat[j][:3, :3]  # R^T n per row: sensor frame
            d = adv[b] - clean[b]
            d[v] += step * sign[:, None] * n_s
            adv[b] = clean[b] + clip_displacements(d, budget_m)
    found = np.isfinite(best_val)
    return IteratedSectorResult(scans=best, best_iterate=np.where(found, best_k, np.nan),
                                surrogate_xy=np.where(found, best_val, np.nan),
                                seconds=time.perf_counter() - t0)
