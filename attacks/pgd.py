"""Attack ``pgd``: per-scan projected gradient ascent on the weighted ICP pose error.

Beyond the paper: a white-box oracle in the spirit of Madry et al. (ICLR 2018). For each scan the
displacement of every point is optimised directly, through the unrolled differentiable surrogate
ICP, to maximise ``||w_1:3 * rho|| + ||w_4:6 * phi||`` (the negative of the generator's adversarial
loss, eq. 3, same weight presets); after every step each point's displacement is projected onto its
Euclidean lambda-ball, so the budget holds exactly (no soft bound). Random start inside the ball
(default), the clean scan, or the analytic sector attack's output (``init="sector"``, a warm start:
the one-step worst case of Laconte et al., RA-L 2024, with the surrogate's association gate); the
per-point ascent direction is the normalised gradient of that point; the best iterate per scan is
returned. Slow and strong: it shows how close the generator gets and at what cost.

Against integrity monitors (the ``ensemble``'s gradient member under ``--monitor-aware``),
:meth:`PGDAttack.refine` takes a ``penalty`` (:class:`~icpbench.monitors.penalty.MonitorPenalty`):
the ascent climbs the error minus the monitors' differentiable scores past their thresholds, and
the best iterate is the best one every such monitor passes.

``init="sector-iter"`` starts from the iterated analytic attack
(:mod:`icpbench.core.iterated_sector`, settings ``sector_iter``); the ``pgd-warm`` preset
(:mod:`icpbench.attacks.pgd_warm`) is that start plus two steps, the cheaper oracle.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, project_to_ball, reuse_radius
from icpbench.core.errors import InputError
from icpbench.core.iterated_sector import SectorIterSettings, iterated_sector
from icpbench.core.pose_loss import weighted_pose_error
from icpbench.core.pose_loss import weights as weight_vector
from icpbench.core.registry import Range
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.targets.base import Target

#: A penalty on B candidates: (scans (B, N, 3), poses (B, 4, 4)) -> (penalty (B,) tensor in
#: metres of objective, feasible (B,) bool); :class:`~icpbench.monitors.penalty.MonitorPenalty`.
Penalty = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, np.ndarray]]

INITS = ("random", "clean", "sector", "sector-iter")


class PGDAttack(Attack):
    """Projected gradient ascent per scan through the differentiable surrogate (the oracle).

    Args:
        steps: ascent steps (each of ``step_size`` times lambda).
        step_size: step length as a fraction of the budget (per point, per step).
        weights: weight preset (``xy``, ``x-only``, ``theta-only``) or 6 numbers.
        icp_iterations: iteration cap of the surrogate ICP inside the attack (the paper trains
            with 25); the tolerance is kept, so converged samples stop early.
        init: the start: ``"random"`` (a uniform random point of each ball), ``"clean"``,
            ``"sector"`` (the sector attack's output with the surrogate's association gate) or
            ``"sector-iter"`` (the iterated analytic attack with settings ``sector_iter``).
        sector_iter: settings of the ``"sector-iter"`` start
            (:class:`~icpbench.core.iterated_sector.SectorIterSettings` field names; missing ones
            keep their defaults, which are the ``sector-iter`` attack's). Refused with another
            ``init``.
        backprop: gradient of the surrogate ICP: ``"unrolled"`` (through its iterations) or
            ``"implicit"`` (implicit-function derivative of its final pose, no graph through the
            iterations: cheaper per step); None keeps the surrogate's own setting.
        icp_nn_reuse: the surrogate's approximate correspondence search (``ICPConfig.nn_reuse_m``,
            metres; the choice of neighbour carries no gradient either way); 0: exact.
    """

    name: ClassVar[str] = "pgd"
    cost_class: ClassVar[int] = 2
    description: ClassVar[str] = (
        "Per-scan projected gradient ascent through the differentiable surrogate (oracle)"
    )
    needs_surrogate: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        "steps": Range(1, 100_000), "step_size": Range(0.0, 2.0, lo_open=True),
        "icp_iterations": Range(1, 1_000_000), "icp_nn_reuse": Range(0.0)}

    def __init__(self, *, strict: bool = False, steps: int = 30, step_size: float = 0.1,
                 weights: str | list[float] = "xy", icp_iterations: int = 25,
                 init: str = "random", sector_iter: dict[str, Any] | None = None,
                 backprop: str | None = None, icp_nn_reuse: float = 0.0, **params: Any) -> None:
        if init not in INITS:
            raise InputError(f"{self.name} init must be one of {', '.join(INITS)}, got {init!r}")
        if sector_iter is not None and init != "sector-iter":
            raise InputError(f"{self.name} sector_iter settings apply to init='sector-iter' only, "
                             f"got init={init!r}")
        if int(steps) < 1 or not float(step_size) > 0:
            raise InputError(f"{self.name} needs steps >= 1 and step_size > 0, got {steps} and "
                             f"{step_size}")
        if backprop not in (None, "unrolled", "implicit"):
            raise InputError(f"{self.name} backprop must be 'unrolled', 'implicit' or None, got "
                             f"{backprop!r}")
        self.start_settings = (SectorIterSettings.from_mapping(sector_iter, f"{self.name} sector_iter")
                               if init == "sector-iter" else None)
        self.init, self.steps, self.step_size = init, int(steps), float(step_size)
        self.icp_iterations, self.backprop = int(icp_iterations), backprop
        self.w = weight_vector(weights)
        self.icp_nn_reuse = reuse_radius(self.name, "icp_nn_reuse", icp_nn_reuse)
        super().__init__(strict=strict, steps=self.steps, step_size=self.step_size, weights=weights,
                         icp_iterations=self.icp_iterations, init=init,
                         sector_iter=(None if self.start_settings is None
                                      else self.start_settings.as_dict()),
                         backprop=backprop, icp_nn_reuse=self.icp_nn_reuse, **params)

    def _surrogate(self, surrogate: Target) -> Target:
        icp = surrogate.with_max_iterations(self.icp_iterations)
        cfg = getattr(icp, "config", None)
        changes: dict[str, Any] = {}
        if self.backprop is not None and cfg is not None and cfg.backprop != self.backprop:
            changes["backprop"] = self.backprop
        if self.icp_nn_reuse > 0:
            changes["nn_reuse_m"] = self.icp_nn_reuse
        return icp.with_settings(**changes) if changes else icp

    def _objective(self, icp: Target, batch: Batch, adv: torch.Tensor) -> torch.Tensor:
        """Surrogate objective (B,) of adversarial scans ``adv`` (B, N, 3) of the batch."""
        return self._scored(icp, batch, adv, None)[0]

    def _scored(self, icp: Target, batch: Batch, adv: torch.Tensor, penalty: Penalty | None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """(objective to ascend (B,), score to keep the best by (B,)) of ``adv`` (B, N, 3): the
        weighted pose error for both without a penalty; with one, the error minus the penalty
        to ascend and the error where the candidate is feasible (-inf elsewhere) to keep."""
        reg = icp.register(adv, batch.maps, batch.T_init)
        err = weighted_pose_error(pose_error(reg.T, batch.T_gt.to(adv.dtype)), self.w)
        if penalty is None:
            return err, err.detach()
        pen, feasible = penalty(adv, reg.T)
        keep = torch.where(torch.as_tensor(feasible), err.detach(),
                           torch.full_like(err.detach(), -torch.inf))
        return err - pen, keep

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        icp = self._surrogate(surrogate)
        clean = batch.scans.to(torch.float64)
        with torch.no_grad():
            best_val = self._objective(icp, batch, clean)
        if self.init == "sector":
            adv = self.sector_start(batch, budget_m, icp).to(torch.float64)
        elif self.init == "sector-iter":
            adv = torch.as_tensor(iterated_sector(batch, budget_m, surrogate,
                                                  self.start_settings).scans)
        elif self.init == "random":
            d = generator.randn(*clean.shape[1:], dtype=torch.float64)  # per-sample streams
            d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
            r = generator.rand(clean.shape[1], 1, dtype=torch.float64)
            adv = clean + d * budget_m * r ** (1.0 / 3.0)
        else:
            adv = clean.clone()
        best, _ = self._ascend(icp, batch, clean, adv, budget_m, clean.clone(), best_val)
        return best.to(batch.scans.dtype)

    @staticmethod
    def sector_start(batch: Batch, budget_m: float, icp: Target) -> torch.Tensor:
        """The sector attack's adversarial scans (B, N, 3) with the surrogate's association gate
        ``d_max`` (metres; the lidar preset's when the surrogate has none)."""
        from icpbench.attacks.sector import SectorAttack

        cfg = getattr(icp, "config", None)
        d_max = getattr(cfg, "d_max", None)
        attack = SectorAttack(d_max=d_max) if d_max is not None else SectorAttack()
        adv, _ = attack._perturb(batch, budget_m, surrogate=None, generator=None)
        return adv

    def _ascend(self, icp: Target, batch: Batch, clean: torch.Tensor, adv: torch.Tensor,
                budget_m: float, best: torch.Tensor, best_val: torch.Tensor,
                penalty: Penalty | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``self.steps`` projected normalised-gradient steps of ``step_size * budget_m`` from
        ``adv`` (B, N, 3) inside the budget balls around ``clean``; returns the best iterate per
        scan seen (``best``/``best_val`` given included, and the final iterate) and its
        objective (B,) (with a ``penalty``: its error, -inf where no iterate was feasible)."""
        adv, best, best_val = adv.detach().clone(), best.clone(), best_val.clone()
        alpha = self.step_size * budget_m
        for _ in range(self.steps):
            x = adv.clone().requires_grad_(True)
            val, keep = self._scored(icp, batch, x, penalty)
            (g,) = torch.autograd.grad(val.sum(), x)
            with torch.no_grad():
                better = keep > best_val
                best = torch.where(better[:, None, None], x, best)
                best_val = torch.where(better, keep, best_val)
                g = torch.nan_to_num(g)
                gn = torch.linalg.norm(g, dim=-1, keepdim=True)
                adv = project_to_ball(clean, x + alpha * g / torch.clamp(gn, min=1e-12), budget_m)
        with torch.no_grad():
            _, val = self._scored(icp, batch, adv, penalty)
            better = val > best_val
            best = torch.where(better[:, None, None], adv, best)
            best_val = torch.where(better, val, best_val)
        return best, best_val

    def refine(self, batch: Batch, start: torch.Tensor, budget_m: float, *,
               surrogate: Target, penalty: Penalty | None = None) -> torch.Tensor:
        """``self.steps`` steps of projected ascent from another attack's output (test-time
        refinement, e.g. of the generator's): ``start`` (B, N, 3) adversarial scans within the
        budget of ``batch.scans``; returns the best of ``start`` and the iterates (B, N, 3) in the
        batch's dtype, never worse than ``start`` on the surrogate's objective. With a
        ``penalty`` (B candidates of this batch; :mod:`icpbench.monitors.penalty`) the ascent
        climbs the error minus the penalty and returns the feasible iterate with the largest
        error (``start`` where none is feasible)."""
        icp = self._surrogate(surrogate)
        clean = batch.scans.to(torch.float64)
        start = project_to_ball(clean, start.detach().to(torch.float64), budget_m)
        # the first step evaluates the start itself (with its gradient): no separate evaluation
        unseen = torch.full((start.shape[0],), -torch.inf, dtype=torch.float64)
        best, _ = self._ascend(icp, batch, clean, start, budget_m, start.clone(), unseen,
                               penalty)
        return best.to(batch.scans.dtype)
