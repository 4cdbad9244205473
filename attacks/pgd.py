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

Cost control (docs/performance.md): ``schedule="cosine"`` decays the step from ``step_size`` to
``final_step_size`` (fractions of lambda) over the steps, so large steps come first; ``patience=P``
stops a scan once its best objective has not grown by more than 0.1% of lambda for P steps (a
stopped scan leaves the batch: the surrogate runs on the others only). ``schedule="constant"``,
``patience=None`` is the original oracle (30 steps of 0.1 lambda).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch

from icpbench.attacks.base import Attack, project_to_ball, reuse_radius
from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch
from icpbench.learning.losses import weighted_pose_error
from icpbench.learning.losses import weights as weight_vector
from icpbench.targets.base import Target


class PGDAttack(Attack):
    """Projected gradient ascent per scan through the differentiable surrogate (the oracle).

    Args:
        steps: ascent steps.
        step_size: step length as a fraction of the budget (per point, per step).
        weights: weight preset (``xy``, ``x-only``, ``theta-only``) or 6 numbers.
        icp_iterations: iteration cap of the surrogate ICP inside the attack (the paper trains
            with 25); the tolerance is kept, so converged samples stop early.
        random_start: start from a uniform random point of each ball (else from the clean scan);
            ignored when ``init`` is given.
        init: ``"random"``, ``"clean"``, ``"sector"`` (the sector attack's output, which moves
            every associated point by the budget along its map normal; the ascent then starts
            from the one-step worst case) or ``"sector-iter"`` (the iterated analytic attack's
            output, :mod:`icpbench.attacks.sector_iter`, with its default settings or
            ``init_params``). None: ``"random"`` if ``random_start`` else ``"clean"``.
        init_params: settings of the ``"sector-iter"`` start (e.g. ``{"iterations": 4,
            "icp_iterations": 100, "icp_nn_reuse": 0.05}``, the names of
            :class:`~icpbench.attacks.sector_iter.SectorIterAttack`); None: its defaults. Refused
            with any other ``init``.
        restarts: independent random starts; the best result per scan is kept.
        schedule: ``"constant"`` (every step ``step_size``) or ``"cosine"`` (from ``step_size``
            down to ``final_step_size`` on a half cosine over ``steps``).
        final_step_size: last step of the cosine schedule, as a fraction of the budget.
        patience: stop a scan after this many steps without improving its best objective by
            more than 0.1% of the budget (None: always run ``steps``).
        backprop: gradient of the surrogate ICP: ``"unrolled"`` (through its iterations) or
            ``"implicit"`` (implicit-function derivative of its final pose, no graph through the
            iterations: cheaper per step); None keeps the surrogate's own setting.
        icp_nn_reuse: the surrogate's approximate correspondence search (``ICPConfig.nn_reuse_m``,
            metres; the choice of neighbour carries no gradient either way); 0: exact.
    """

    name: ClassVar[str] = "pgd"
    description: ClassVar[str] = (
        "Per-scan projected gradient ascent through the differentiable surrogate (oracle)"
    )
    needs_surrogate: ClassVar[bool] = True

    def __init__(self, *, strict: bool = False, steps: int = 30, step_size: float = 0.1,
                 weights: str | list[float] = "xy", icp_iterations: int = 25,
                 random_start: bool = True, restarts: int = 1, schedule: str = "constant",
                 final_step_size: float = 0.02, patience: int | None = None,
                 backprop: str | None = None, init: str | None = None, icp_nn_reuse: float = 0.0,
                 init_params: dict[str, Any] | None = None, **params: Any) -> None:
        if init is None:
            init = "random" if random_start else "clean"
        if init not in ("random", "clean", "sector", "sector-iter"):
            raise InputError(f"pgd init must be 'random', 'clean', 'sector' or 'sector-iter', got "
                             f"{init!r}")
        random_start = init == "random"
        super().__init__(strict=strict, steps=steps, step_size=step_size, weights=weights,
                         icp_iterations=icp_iterations, random_start=random_start,
                         restarts=restarts, schedule=schedule, final_step_size=final_step_size,
                         patience=patience, backprop=backprop, init=init, **params)
        self.init = init
        self._init_attack = self._make_init_attack(init, init_params)
        if init_params:  # recorded only when set, so that older runs stay comparable
            self.params["init_params"] = dict(init_params)
        if steps < 1 or restarts < 1:
            raise InputError("pgd needs steps >= 1 and restarts >= 1")
        if not step_size > 0:
            raise InputError(f"pgd step_size must be > 0, got {step_size}")
        self.steps, self.step_size, self.restarts = int(steps), float(step_size), int(restarts)
        self.random_start, self.icp_iterations = bool(random_start), int(icp_iterations)
        self.w = weight_vector(weights)
        if schedule not in ("constant", "cosine"):
            raise InputError(f"pgd schedule must be 'constant' or 'cosine', got {schedule!r}")
        if not final_step_size > 0:
            raise InputError(f"pgd final_step_size must be > 0, got {final_step_size}")
        if patience is not None and int(patience) < 1:
            raise InputError(f"pgd patience must be >= 1 or None, got {patience}")
        self.schedule, self.final_step_size = schedule, float(final_step_size)
        self.patience = None if patience is None else int(patience)
        if backprop not in (None, "unrolled", "implicit"):
            raise InputError(f"pgd backprop must be 'unrolled', 'implicit' or None, got {backprop!r}")
        self.backprop = backprop
        self.icp_nn_reuse = reuse_radius("pgd", "icp_nn_reuse", icp_nn_reuse)
        if self.icp_nn_reuse > 0:  # recorded only when set, so that older runs stay comparable
            self.params["icp_nn_reuse"] = self.icp_nn_reuse

    def step_sizes(self, budget_m: float) -> list[float]:
        """Step length (metres) of each of the ``steps`` ascent steps."""
        a0, a1, n = self.step_size * budget_m, self.final_step_size * budget_m, self.steps
        if self.schedule == "constant" or n == 1:
            return [a0] * n
        return [a1 + 0.5 * (a0 - a1) * (1.0 + math.cos(math.pi * k / (n - 1))) for k in range(n)]

    def _surrogate(self, surrogate: Target) -> Target:
        icp = surrogate.with_max_iterations(self.icp_iterations)
        cfg = getattr(icp, "config", None)
        changes: dict[str, Any] = {}
        if self.backprop is not None and cfg is not None and cfg.backprop != self.backprop:
            changes["backprop"] = self.backprop
        if self.icp_nn_reuse > 0:
            changes["nn_reuse_m"] = self.icp_nn_reuse
        return icp.with_settings(**changes) if changes else icp

    def _objective(self, icp: Target, batch: Batch, adv: torch.Tensor,
                   idx: torch.Tensor | None = None) -> torch.Tensor:
        """Surrogate objective (len(idx),) of adversarial scans adv (len(idx), N, 3) of the
        batch's samples ``idx`` (default: all)."""
        if idx is None:
            reg = icp.register(adv, batch.maps, batch.T_init)
            return weighted_pose_error(pose_error(reg.T, batch.T_gt.to(adv.dtype)), self.w)
        maps = [batch.maps[int(i)] for i in idx]
        reg = icp.register(adv, maps, batch.T_init[idx])
        return weighted_pose_error(pose_error(reg.T, batch.T_gt[idx].to(adv.dtype)), self.w)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        icp = self._surrogate(surrogate)
        clean = batch.scans.to(torch.float64)
        best = clean.clone()
        with torch.no_grad():
            best_val = self._objective(icp, batch, clean)
        for _ in range(self.restarts):
            if self.init == "sector":
                adv = self.sector_start(batch, budget_m, icp).to(torch.float64)
            elif self._init_attack is not None:
                adv = self._init_attack._perturb(batch, budget_m, surrogate=surrogate,
                                                 generator=generator)[0].to(torch.float64)
            elif self.random_start:
                d = generator.randn(*clean.shape[1:], dtype=torch.float64)  # per-sample streams
                d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
                r = generator.rand(clean.shape[1], 1, dtype=torch.float64)
                adv = clean + d * budget_m * r ** (1.0 / 3.0)
            else:
                adv = clean.clone()
            best, best_val = self._ascend(icp, batch, clean, adv, budget_m, best, best_val)
        return best.to(batch.scans.dtype)

    @staticmethod
    def _make_init_attack(init: str, init_params: dict[str, Any] | None) -> Attack | None:
        """The iterated analytic attack of ``init="sector-iter"`` (None for the other starts),
        its settings checked now so that a bad one fails before any scan is attacked."""
        if init != "sector-iter":
            if init_params:
                raise InputError(f"pgd init_params apply to init='sector-iter' only, got init={init!r}")
            return None
        from icpbench.attacks.sector_iter import SectorIterAttack
        from icpbench.core.registry import check_params

        settings = check_params("pgd init_params (sector-iter)", SectorIterAttack.param_types(),
                                init_params or {})
        return SectorIterAttack(**settings)

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
                budget_m: float, best: torch.Tensor, best_val: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """``self.steps`` projected normalised-gradient steps from ``adv`` (B, N, 3) inside the
        budget balls around ``clean`` (step lengths :meth:`step_sizes`; a scan stops early after
        ``patience`` steps without progress); returns the best iterate per scan seen so far
        (including ``best``/``best_val`` given, and the final iterate of scans that ran every
        step) and its objective (B,)."""
        B = adv.shape[0]
        adv, best, best_val = adv.detach().clone(), best.clone(), best_val.clone()
        live = torch.ones(B, dtype=torch.bool)
        stale = torch.zeros(B, dtype=torch.long)
        min_gain = 1e-3 * budget_m
        for alpha in self.step_sizes(budget_m):
            idx = torch.nonzero(live)[:, 0]
            if idx.numel() == 0:
                break
            x = adv[idx].requires_grad_(True)
            val = self._objective(icp, batch, x, None if idx.numel() == B else idx)
            (g,) = torch.autograd.grad(val.sum(), x)
            with torch.no_grad():
                prev = best_val[idx]
                better = val > prev
                best[idx] = torch.where(better[:, None, None], x, best[idx])
                best_val[idx] = torch.where(better, val, prev)
                stale[idx] = torch.where(val > prev + min_gain, 0, stale[idx] + 1)
                g = torch.nan_to_num(g)
                gn = torch.linalg.norm(g, dim=-1, keepdim=True)
                step = x + alpha * g / torch.clamp(gn, min=1e-12)
                adv[idx] = project_to_ball(clean[idx], step, budget_m)
                if self.patience is not None:
                    live[idx] = stale[idx] < self.patience
        idx = torch.nonzero(live)[:, 0]
        if idx.numel():
            with torch.no_grad():
                val = self._objective(icp, batch, adv[idx], None if idx.numel() == B else idx)
                better = val > best_val[idx]
                best[idx] = torch.where(better[:, None, None], adv[idx], best[idx])
                best_val[idx] = torch.where(better, val, best_val[idx])
        return best, best_val

    def refine(self, batch: Batch, start: torch.Tensor, budget_m: float, *,
               surrogate: Target) -> torch.Tensor:
        """``self.steps`` steps of projected ascent from another attack's output (test-time
        refinement, e.g. of the generator's): ``start`` (B, N, 3) adversarial scans within the
        budget of ``batch.scans``; returns the best of ``start`` and the iterates (B, N, 3) in the
        batch's dtype, never worse than ``start`` on the surrogate's objective."""
        icp = self._surrogate(surrogate)
        clean = batch.scans.to(torch.float64)
        start = project_to_ball(clean, start.detach().to(torch.float64), budget_m)
        with torch.no_grad():
            start_val = self._objective(icp, batch, start)
        best, _ = self._ascend(icp, batch, clean, start, budget_m, start.clone(), start_val)
        return best.to(batch.scans.dtype)
