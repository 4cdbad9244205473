"""Attack ``sector-adaptive``: the iterated one-step worst case of the *evaluated* target's cost,
re-linearised where that target lands (queries only).

Beyond the paper. ``sector-iter`` (:mod:`icpbench.core.iterated_sector`) re-linearises the
point-to-plane sector step at the pose a *surrogate* ICP reaches, so against a point-to-point or
GICP target it aims at the wrong cost and the wrong pose. This attack needs nothing but the
evaluated target's output pose (a :class:`~icpbench.targets.oracle.QueryOracle`), so it runs
against any target, black boxes included:

1. start from the one-step worst case of the target's cost at the true pose
   (:mod:`icpbench.core.cost_sensitivity`: point-to-plane, point-to-point or GICP, read from the
   target's settings by :func:`~icpbench.core.cost_sensitivity.cost_of`): every associated point
   moved by lambda in the direction that shifts the estimate most along the worst horizontal
   direction;
2. query the target (one query per scan) for the pose ``T_k`` it reaches on the current
   adversarial scan, and its horizontal error direction ``e_k``;
3. linearise the target's cost for the adversarial scan at ``T_k`` and move every associated point
   by ``step_size * lambda`` in the direction that pushes the estimate further along ``e_k``;
   project each point's total displacement back onto its lambda-ball;
4. repeat; return per scan the iterate with the largest error *on the target* (the start included).

Each scan costs ``iterations + 1`` queries (recorded per row as ``extra.queries``).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack
from icpbench.core import cost_sensitivity as cs
from icpbench.core.errors import InputError
from icpbench.core.projection import clip_displacements
from icpbench.core.registry import Range
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

#: Errors below this (metres) have no direction; the start's worst direction is used instead.
_MIN_ERR_M = 1e-6


def score(err: np.ndarray) -> np.ndarray:
    """Errors (K,) as scores to maximise: a NaN (a diverged estimate) never wins."""
    return np.where(np.isnan(err), -np.inf, err)


class SectorAdaptiveAttack(Attack):
    """Iterated one-step worst case of the evaluated target's own cost (module docstring).

    Args:
        iterations: re-linearisation steps after the start (queries per scan: iterations + 1).
        step_size: each step's length as a fraction of lambda, in (0, 2].
        d_max: association gate of the model (metres); None: the target's own gate.
    """

    name: ClassVar[str] = "sector-adaptive"
    description: ClassVar[str] = (
        "One-step worst case of the evaluated target's cost (plane/point/GICP), re-linearised where "
        "that target lands; queries only, any target (beyond the paper)"
    )
    needs_oracle: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        "iterations": Range(0, 100_000), "step_size": Range(0.0, 2.0, lo_open=True),
        "d_max": Range(0.0, lo_open=True)}

    def __init__(self, *, strict: bool = False, iterations: int = 4, step_size: float = 0.5,
                 d_max: float | None = None, **params: Any) -> None:
        if isinstance(iterations, bool) or int(iterations) != iterations or int(iterations) < 0:
            raise InputError(f"{self.name} iterations must be an integer >= 0, got {iterations!r}")
        if not 0 < float(step_size) <= 2:
            raise InputError(f"{self.name} step_size must be in (0, 2] (fraction of lambda), got "
                             f"{step_size}")
        if d_max is not None and not (math.isfinite(float(d_max)) and float(d_max) > 0):
            raise InputError(f"{self.name} d_max must be > 0 metres, got {d_max}")
        self.iterations, self.step_size = int(iterations), float(step_size)
        self.d_max = None if d_max is None else float(d_max)
        super().__init__(strict=strict, iterations=self.iterations, step_size=self.step_size,
                         d_max=self.d_max, **params)

    def cost(self, target: Target) -> cs.CostSpec:
        """The cost model of ``target`` with this attack's gate, if it sets one."""
        spec = cs.cost_of(target)
        return spec if self.d_max is None else cs.CostSpec(spec.kind, self.d_max, spec.cauchy_c)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None, generator: Any,
                 oracle: QueryOracle) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        adv, best_k = self.attack(batch, budget_m, oracle)
        return torch.as_tensor(adv, dtype=batch.scans.dtype), {"sector_adaptive_best": best_k}

    def attack(self, batch: Batch, budget_m: float, oracle: QueryOracle
               ) -> tuple[np.ndarray, np.ndarray]:
        """Adversarial scans (B, N, 3) float64 within lambda per point, and the index of the
        returned iterate per scan (B,) (NaN: left clean, fewer than 6 correspondences)."""
        cost = self.cost(oracle.target)
        clean = batch.scans.detach().to(torch.float64).numpy()
        T_gt = batch.T_gt.to(torch.float64).numpy()
        B = clean.shape[0]
        adv, u0 = clean.copy(), np.zeros((B, 6))
        live = np.zeros(B, dtype=bool)
        for b in range(B):  # the start: the one-step worst case at the true pose
            try:
                lin = cs.linearise(clean[b], T_gt[b], batch.maps[b], cost)
            except InputError:
                continue  # too few correspondences: left clean
            u0[b], _ = lin.worst_xy()
            adv[b, lin.index] += lin.displacement(u0[b], budget_m)
            live[b] = True
        best, best_val, best_k = adv.copy(), np.full(B, -np.inf), np.full(B, np.nan)
        for k in range(self.iterations + 1):
            idx = np.flatnonzero(live)
            if idx.size == 0:
                break
            T_hat, err, _ = oracle.register(adv[idx], idx)
            xi = pose_error(torch.as_tensor(T_hat), torch.as_tensor(T_gt[idx])).numpy()
            s = score(err)
            for j, b in enumerate(idx):
                if s[j] > best_val[b]:
                    best_val[b], best[b], best_k[b] = s[j], adv[b], k
                if k == self.iterations:
                    continue
                if not np.all(np.isfinite(T_hat[j])):
                    live[b] = False  # the estimate diverged: keep the best so far
                    continue
                try:
                    lin = cs.linearise(adv[b], T_hat[j], batch.maps[b], cost)
                except InputError:
                    live[b] = False  # the estimate left the map: keep the best so far
                    continue
                u = u0[b].copy()
                if err[j] > _MIN_ERR_M:
                    u[:] = 0.0
                    u[:2] = xi[j, :2] / err[j]
                d = adv[b] - clean[b]
                d[lin.index] += lin.displacement(u, self.step_size * budget_m)
                adv[b] = clean[b] + clip_displacements(d, budget_m)
        return best, best_k
