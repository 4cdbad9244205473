"""Attack base class: perturb a batch of scans within a per-point budget, and audit what it did.

The base class (not each attack) measures the displacement of every point, per sample: maximum,
mean, 95th percentile and the fraction of points moved by more than the budget. In *strict* mode it
projects each point's displacement onto the ball of radius ``budget_m`` before returning. The
paper's generator is only softly bounded (its reconstruction loss penalises displacement beyond
lambda), so both numbers are reported and never hidden.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch

from icpbench.errors import InputError
from icpbench.targets.base import Target
from icpbench.types import Batch

STAT_COLUMNS = ("disp_max", "disp_mean", "disp_p95", "frac_over_budget")


@dataclass
class AttackOutput:
    """Adversarial scans and the audit of the displacement.

    Attributes:
        scans: (B, N, 3) adversarial scans, sensor frame, metres.
        stats: per-sample (B,) tensors ``disp_max``, ``disp_mean``, ``disp_p95`` (metres) and
            ``frac_over_budget`` (share of points moved by more than the budget, before strict
            projection if any), plus ``disp_max_raw`` (before projection).
        extra: attack-specific per-sample (B,) values, e.g. the sector attack's analytic estimate.
    """

    scans: torch.Tensor
    stats: dict[str, torch.Tensor]
    extra: dict[str, torch.Tensor] = field(default_factory=dict)


def validate_budget(budget_m: float) -> float:
    """Return the budget as float; raise InputError for negative, zero, NaN or Inf budgets."""
    try:
        b = float(budget_m)
    except (TypeError, ValueError) as exc:
        raise InputError(f"budget must be a number, got {budget_m!r}") from exc
    if not (b > 0 and b < float("inf")):
        raise InputError(f"budget must be a positive finite number of metres, got {budget_m!r}")
    return b


def project_to_ball(clean: torch.Tensor, adv: torch.Tensor,
                    budget_m: float | torch.Tensor) -> torch.Tensor:
    """Project each point's displacement ``adv - clean`` (B, N, 3) onto the Euclidean ball of radius
    ``budget_m`` (metres): one float for every sample, or a (B,) tensor with one budget per sample.

    Differentiable in ``adv`` (and in a tensor budget); the gradient is finite at zero displacement."""
    d = adv - clean
    norm = torch.linalg.vector_norm(d, dim=-1, keepdim=True)  # (B, N, 1)
    if isinstance(budget_m, torch.Tensor):
        if budget_m.dim() != 1 or budget_m.shape[0] != d.shape[0]:
            raise InputError(f"per-sample budget must have shape ({d.shape[0]},), "
                             f"got {tuple(budget_m.shape)}")
        budget_m = budget_m.to(device=d.device, dtype=d.dtype)[:, None, None]
    scale = torch.clamp(budget_m / torch.clamp(norm, min=1e-12), max=1.0)
    return clean + d * scale


def displacement_stats(clean: torch.Tensor, adv: torch.Tensor, budget_m: float,
                       tol: float = 1e-6) -> dict[str, torch.Tensor]:
    """Per-sample displacement statistics of (B, N, 3) clouds (metres); see :class:`AttackOutput`.

    A point counts as over budget when it moved more than ``budget_m * (1 + tol)``."""
    with torch.no_grad():
        d = torch.linalg.norm((adv - clean).to(torch.float64), dim=-1)  # (B, N)
        return {
            "disp_max": d.max(1).values,
            "disp_mean": d.mean(1),
            "disp_p95": torch.quantile(d, 0.95, dim=1),
            "frac_over_budget": (d > budget_m * (1 + tol)).to(torch.float64).mean(1),
        }


class Attack(ABC):
    """Base class of every attack.

    Subclasses set ``name``/``description`` (and ``needs_surrogate=True`` if they need a
    differentiable target's gradients) and implement :meth:`_perturb`. Callers use :meth:`run`
    (scans + audit) or :meth:`perturb` (scans only).

    Args:
        strict: project every point's displacement onto its budget ball after the attack.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    needs_surrogate: ClassVar[bool] = False

    def __init__(self, *, strict: bool = False, **params: Any) -> None:
        self.strict = bool(strict)
        self.params = params

    @abstractmethod
    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: torch.Generator) -> torch.Tensor | tuple[torch.Tensor, dict]:
        """Return adversarial scans (B, N, 3), or (scans, extra) with per-sample extras."""

    def run(self, batch: Batch, budget_m: float, *, surrogate: Target | None = None,
            generator: torch.Generator | int | None = None) -> AttackOutput:
        """Attack a batch and audit the displacement.

        Args:
            batch: clean scans (B, N, 3) and their samples/maps.
            budget_m: per-point perturbation budget lambda (metres, or normalised units for objects).
            surrogate: differentiable target used for gradients (required if ``needs_surrogate``).
            generator: the only source of randomness: a ``torch.Generator`` or an int seed.
        """
        budget_m = validate_budget(budget_m)
        if self.needs_surrogate:
            if surrogate is None:
                raise InputError(f"attack {self.name!r} needs a differentiable surrogate target")
            if not surrogate.differentiable:
                raise InputError(
                    f"attack {self.name!r} needs a differentiable surrogate; "
                    f"{surrogate.name!r} is a black box (use p2plane or p2point as surrogate)"
                )
        if not isinstance(generator, torch.Generator):
            seed = 0 if generator is None else int(generator)
            generator = torch.Generator().manual_seed(seed)
        out = self._perturb(batch, budget_m, surrogate=surrogate, generator=generator)
        adv, extra = out if isinstance(out, tuple) else (out, {})
        if adv.shape != batch.scans.shape:
            raise RuntimeError(
                f"attack {self.name!r} returned shape {tuple(adv.shape)}, "
                f"expected {tuple(batch.scans.shape)}"
            )
        if not bool(torch.isfinite(adv).all()):
            bad = int((~torch.isfinite(adv)).any(-1).sum())
            raise RuntimeError(f"attack {self.name!r} returned {bad} point(s) with NaN or Inf "
                               "coordinates")
        clean = batch.scans.to(adv.dtype)
        stats = displacement_stats(clean, adv, budget_m)
        stats["disp_max_raw"] = stats["disp_max"].clone()
        if self.strict:
            adv = project_to_ball(clean, adv, budget_m)
            projected = displacement_stats(clean, adv, budget_m)
            projected["frac_over_budget"] = stats["frac_over_budget"]  # what the attack wanted
            projected["disp_max_raw"] = stats["disp_max_raw"]
            stats = projected
        return AttackOutput(scans=adv.detach(), stats=stats,
                            extra={k: torch.as_tensor(v) for k, v in extra.items()})

    def perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None = None,
                generator: torch.Generator | int | None = None) -> torch.Tensor:
        """Adversarial scans (B, N, 3); see :meth:`run` for the audit."""
        return self.run(batch, budget_m, surrogate=surrogate, generator=generator).scans

    def settings(self) -> dict[str, Any]:
        """Settings recorded in the manifest."""
        return {"strict": self.strict, **self.params}

    def fingerprint(self, budgets: Sequence[float]) -> dict[str, str]:
        """Identities of the files this attack reads for these budgets (metres), e.g. checkpoint
        hashes: a resumed run refuses to mix results made from different files. Default: none."""
        return {}
