"""Attack ``pgd``: per-scan projected gradient ascent on the weighted ICP pose error.

Beyond the paper: a white-box oracle in the spirit of Madry et al. (ICLR 2018). For each scan the
displacement of every point is optimised directly, through the unrolled differentiable surrogate
ICP, to maximise ``||w_1:3 * rho|| + ||w_4:6 * phi||`` (the negative of the generator's adversarial
loss, eq. 3, same weight presets); after every step each point's displacement is projected onto its
Euclidean lambda-ball, so the budget holds exactly (no soft bound). Random start inside the ball; the
per-point ascent direction is the normalised gradient of that point; the best iterate per scan is
returned. Slow and strong: it shows how close the generator gets and at what cost.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch

from icpbench.attacks.base import Attack, project_to_ball
from icpbench.errors import InputError
from icpbench.losses import weighted_pose_error
from icpbench.losses import weights as weight_vector
from icpbench.se3 import pose_error
from icpbench.targets.base import Target
from icpbench.types import Batch


class PGDAttack(Attack):
    """Projected gradient ascent per scan through the differentiable surrogate (the oracle).

    Args:
        steps: ascent steps.
        step_size: step length as a fraction of the budget (per point, per step).
        weights: weight preset (``xy``, ``x-only``, ``theta-only``) or 6 numbers.
        icp_iterations: iteration cap of the surrogate ICP inside the attack (the paper trains
            with 25); the tolerance is kept, so converged samples stop early.
        random_start: start from a uniform random point of each ball (else from the clean scan).
        restarts: independent random starts; the best result per scan is kept.
    """

    name: ClassVar[str] = "pgd"
    description: ClassVar[str] = (
        "Per-scan projected gradient ascent through the differentiable surrogate (oracle)"
    )
    needs_surrogate: ClassVar[bool] = True

    def __init__(self, *, strict: bool = False, steps: int = 30, step_size: float = 0.1,
                 weights: str | list[float] = "xy", icp_iterations: int = 25,
                 random_start: bool = True, restarts: int = 1, **params: Any) -> None:
        super().__init__(strict=strict, steps=steps, step_size=step_size, weights=weights,
                         icp_iterations=icp_iterations, random_start=random_start,
                         restarts=restarts, **params)
        if steps < 1 or restarts < 1:
            raise InputError("pgd needs steps >= 1 and restarts >= 1")
        if not step_size > 0:
            raise InputError(f"pgd step_size must be > 0, got {step_size}")
        self.steps, self.step_size, self.restarts = int(steps), float(step_size), int(restarts)
        self.random_start, self.icp_iterations = bool(random_start), int(icp_iterations)
        self.w = weight_vector(weights)

    def _surrogate(self, surrogate: Target) -> Target:
        return surrogate.with_max_iterations(self.icp_iterations)

    def _objective(self, icp: Target, batch: Batch, adv: torch.Tensor) -> torch.Tensor:
        reg = icp.register(adv, batch.maps, batch.T_init)
        return weighted_pose_error(pose_error(reg.T, batch.T_gt.to(adv.dtype)), self.w)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        icp = self._surrogate(surrogate)
        clean = batch.scans.to(torch.float64)
        best = clean.clone()
        with torch.no_grad():
            best_val = self._objective(icp, batch, clean)
        for _ in range(self.restarts):
            if self.random_start:
                d = generator.randn(*clean.shape[1:], dtype=torch.float64)  # per-sample streams
                d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
                r = generator.rand(clean.shape[1], 1, dtype=torch.float64)
                adv = clean + d * budget_m * r ** (1.0 / 3.0)
            else:
                adv = clean.clone()
            best, best_val = self._ascend(icp, batch, clean, adv, budget_m, best, best_val)
        return best.to(batch.scans.dtype)

    def _ascend(self, icp: Target, batch: Batch, clean: torch.Tensor, adv: torch.Tensor,
                budget_m: float, best: torch.Tensor, best_val: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """``self.steps`` projected normalised-gradient steps from ``adv`` (B, N, 3) inside the
        budget balls around ``clean``; returns the best iterate per scan seen so far (including
        ``best``/``best_val`` given, and the final iterate) and its objective (B,)."""
        alpha = self.step_size * budget_m
        for _ in range(self.steps):
            adv = adv.detach().requires_grad_(True)
            val = self._objective(icp, batch, adv)
            (g,) = torch.autograd.grad(val.sum(), adv)
            with torch.no_grad():
                better = val > best_val
                best = torch.where(better[:, None, None], adv, best)
                best_val = torch.where(better, val, best_val)
                g = torch.nan_to_num(g)
                gn = torch.linalg.norm(g, dim=-1, keepdim=True)
                adv = adv + alpha * g / torch.clamp(gn, min=1e-12)
                adv = project_to_ball(clean, adv, budget_m)
        with torch.no_grad():
            val = self._objective(icp, batch, adv)
            better = val > best_val
            best = torch.where(better[:, None, None], adv, best)
            best_val = torch.where(better, val, best_val)
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
