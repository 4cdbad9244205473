"""Attack base class: perturb a batch of scans within a per-point budget, and audit what it did.

The base class (not each attack) measures the displacement of every point, per sample: maximum,
mean, 95th percentile and the fraction of points moved by more than the budget. In *strict* mode it
projects each point's displacement onto the ball of radius ``budget_m`` before returning. The
paper's generator is only softly bounded (its reconstruction loss penalises displacement beyond
lambda), so both numbers are reported and never hidden.
"""

from __future__ import annotations

import functools
import hashlib
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, final

import torch

from icpbench.core.errors import InputError
from icpbench.core.projection import project_to_ball
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

__all__ = ["Attack", "AttackOutput", "project_to_ball", "reuse_radius", "validate_budget"]

STAT_COLUMNS = ("disp_max", "disp_mean", "disp_p95", "frac_over_budget")

#: Largest budget accepted (metres, or normalised units): far beyond any scene, small enough that
#: moving a float32 scan by it stays finite.
MAX_BUDGET = 1e6


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
    """Return the budget as float; raise InputError for negative, zero, NaN, Inf or absurdly large
    (> :data:`MAX_BUDGET`) budgets."""
    try:
        b = float(budget_m)
    except (TypeError, ValueError) as exc:
        raise InputError(f"budget must be a number, got {budget_m!r}") from exc
    if not (b > 0 and b < float("inf")):
        raise InputError(f"budget must be a positive finite number of metres, got {budget_m!r}")
    if b > MAX_BUDGET:
        raise InputError(f"budget must be a positive finite number of metres <= {MAX_BUDGET:g}, "
                         f"got {budget_m!r}")
    return b


def reuse_radius(attack: str, key: str, value: float) -> float:
    """The approximate-correspondence radius ``value`` (metres, ``ICPConfig.nn_reuse_m``) of
    ``attack``'s setting ``key``, checked: a finite number >= 0 (0: exact nearest neighbours).

    Raises:
        InputError: negative or not finite.
    """
    r = float(value)
    if not (math.isfinite(r) and r >= 0):
        raise InputError(f"{attack} {key} must be a finite number >= 0 (metres), got {value}")
    return r


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


def sample_seed(seed: int, attack: str, budget_m: float, sample_id: str) -> int:
    """The seed of one sample's random stream: a stable 63-bit hash of (attack seed, attack name,
    budget, sample id). It does not depend on the batch the sample is in, on the batch size or on
    the executor, so neither do a random attack's rows."""
    text = f"{int(seed)}|{attack}|{float(budget_m)!r}|{sample_id}"
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "big") >> 1


class SampleGenerators:
    """One ``torch.Generator`` per sample of a batch: the only source of an attack's randomness.

    An attack draws each sample's random numbers from that sample's generator
    (:meth:`rand`/:meth:`randn` do it for the whole batch), so a sample's draws are the same
    whichever batch it is in.

    Args:
        generators: B generators, in batch order.
    """

    def __init__(self, generators: Sequence[torch.Generator], seed: int | None = None) -> None:
        self.generators = list(generators)
        #: the attack seed the streams were derived from (None when built from raw generators);
        #: an attack that runs other attacks gives them this seed, so their streams are theirs
        self.seed = seed

    @classmethod
    def for_batch(cls, batch: Batch, seed: int, attack: str, budget_m: float) -> SampleGenerators:
        """Generators seeded with :func:`sample_seed` of each sample of ``batch``."""
        return cls([torch.Generator().manual_seed(sample_seed(seed, attack, budget_m, s.id))
                    for s in batch.samples], seed=int(seed))

    def __len__(self) -> int:
        return len(self.generators)

    def __getitem__(self, b: int) -> torch.Generator:
        return self.generators[b]

    def rand(self, *shape: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """(B, *shape) uniform numbers in [0, 1); row b drawn from sample b's generator."""
        return torch.stack([torch.rand(shape, generator=g, dtype=dtype) for g in self.generators])

    def randn(self, *shape: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """(B, *shape) standard normal numbers; row b drawn from sample b's generator."""
        return torch.stack([torch.randn(shape, generator=g, dtype=dtype) for g in self.generators])


class Attack(ABC):
    """Base class of every attack, and the whole contract between an attack plugin and the runner.

    A subclass sets the class attributes below and implements :meth:`_perturb`; everything else
    (budget checks, the surrogate check, per-sample random streams, the displacement audit, strict
    projection) is done here, once, by :meth:`run`, which subclasses cannot override. Callers use
    :meth:`run` (scans + audit) or :meth:`perturb` (scans only).

    Construction: the runner calls ``cls(strict=..., **settings)``, where the settings are the user's
    ``--attack-param NAME.KEY=VALUE`` values, checked against :meth:`param_types` (the named keyword
    parameters of ``__init__``) before the attack is built, plus ``dataset=`` and ``icp_preset=``
    when the class sets :attr:`wants_context`.

    Args:
        strict: project every point's displacement onto its budget ball after the attack.
    """

    #: Registry key; must equal the entry-point name the plugin is registered under.
    name: ClassVar[str] = ""
    #: One line for ``icpbench list``.
    description: ClassVar[str] = ""
    #: The attack needs gradients: :meth:`run` then requires a differentiable ``surrogate`` target
    #: (one with ``differentiable = True``; the runner passes ``--surrogate``, default ``p2plane``).
    #: A surrogate's iteration cap can be changed with :meth:`Target.with_max_iterations`.
    needs_surrogate: ClassVar[bool] = False
    #: The constructor also receives ``dataset`` (the dataset's registry name) and ``icp_preset``
    #: (the run's ICP preset), e.g. so that the generator picks the checkpoint shipped for the data.
    wants_context: ClassVar[bool] = False
    #: The attack's output depends neither on the budget nor on its random streams (the clean scan
    #: of ``none``): the runner then registers a batch once and reuses it for every budget.
    budget_invariant: ClassVar[bool] = False
    #: The attack queries the *evaluated* target (:class:`~icpbench.targets.oracle.QueryOracle`):
    #: :meth:`_perturb` then receives ``oracle=`` and the runner attacks each target separately.
    needs_oracle: ClassVar[bool] = False
    #: The attack also uses a gradient surrogate when it is given one (and runs without it), e.g.
    #: the ensemble's PGD member; with ``--surrogate self`` it is then attacked per target.
    uses_surrogate: ClassVar[bool] = False
    #: A *preset* of the base attack: the defaults this subclass changes. A subclass that sets it
    #: and defines no ``__init__`` is its base attack with these defaults (same settings, same
    #: code); e.g. ``pgd-warm`` is ``pgd`` with the cheaper oracle's defaults.
    preset: ClassVar[Mapping[str, Any]] = {}
    #: Rough cost class per scan, the order in which ``--attacks all`` runs the attacks (cheapest
    #: first, ties by name) so that an interrupted run keeps the cheap rows: 0 a few passes of
    #: the scan (``none``, ``uniform``); 1 a network or a handful of ICP runs; 2 a budget of
    #: gradient steps or target queries; 3 queries each planned at some cost (``valley``); 4 an
    #: ensemble that re-runs other attacks.
    cost_class: ClassVar[int] = 1

    def __init__(self, *, strict: bool = False, **params: Any) -> None:
        self.strict = bool(strict)
        self.params = params  # a subclass passes its own settings here to record them

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "run" in cls.__dict__:
            raise TypeError(f"{cls.__name__} overrides Attack.run, which is final (it enforces the "
                            "budget, the surrogate and the displacement audit); implement _perturb")
        if "preset" in cls.__dict__ and "__init__" not in cls.__dict__:
            base_init, defaults = cls.__init__, dict(cls.preset)

            @functools.wraps(base_init)  # the base's signature: param_types stays the base's
            def __init__(self: Attack, **settings: Any) -> None:
                base_init(self, **{**defaults, **settings})

            cls.__init__ = __init__  # type: ignore[method-assign]

    @classmethod
    def param_types(cls) -> dict[str, Any]:
        """Settings the attack accepts (name -> type hint): the named keyword parameters of its
        ``__init__`` (``**params`` is not a setting: it only carries a subclass's settings to this
        base class) except ``strict``, which is the run's ``--strict``. Unknown settings are
        refused and values are coerced to these types."""
        from icpbench.core.registry import keyword_params

        return keyword_params(cls.__init__, skip=("strict",))

    @abstractmethod
    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: SampleGenerators) -> torch.Tensor | tuple[torch.Tensor, dict]:
        """Return adversarial scans (B, N, 3), or (scans, extra) with per-sample (B,) extras.

        Args:
            batch: the clean scans (B, N, 3), sensor frame, and their samples and maps.
            budget_m: the per-point budget lambda (already validated).
            surrogate: the differentiable target (when :attr:`needs_surrogate`), else maybe None.
            generator: one random stream per sample; draw sample b's numbers from
                ``generator[b]`` (or use ``generator.rand``/``randn``) and nothing else.
        """

    @classmethod
    def adaptive(cls, self_surrogate: bool) -> bool:
        """Whether the attack's output depends on the evaluated target: it queries it, or it
        follows gradients and the run's surrogate is each target itself (``--surrogate self``)."""
        return cls.needs_oracle or (self_surrogate and (cls.needs_surrogate or cls.uses_surrogate))

    @final
    def run(self, batch: Batch, budget_m: float, *, surrogate: Target | None = None,
            generator: SampleGenerators | torch.Generator | int | None = None,
            oracle: QueryOracle | None = None) -> AttackOutput:
        """Attack a batch and audit the displacement.

        Args:
            batch: clean scans (B, N, 3) and their samples/maps.
            budget_m: per-point perturbation budget lambda (metres, or normalised units for objects).
            surrogate: differentiable target used for gradients (required if ``needs_surrogate``).
            generator: the attack seed (an int; a ``torch.Generator`` stands for its initial seed;
                None = 0), from which each sample gets its own stream (:func:`sample_seed` of seed,
                attack name, budget and sample id), or ready :class:`SampleGenerators`.
            oracle: query access to the evaluated target (required if ``needs_oracle``); its
                per-sample query counts are added to the output's ``extra["queries"]``.
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
        if self.needs_oracle and oracle is None:
            raise InputError(f"attack {self.name!r} queries the evaluated target: it needs an oracle")
        if not isinstance(generator, SampleGenerators):
            seed = (generator.initial_seed() if isinstance(generator, torch.Generator)
                    else 0 if generator is None else int(generator))
            generator = SampleGenerators.for_batch(batch, seed, self.name, budget_m)
        before = None if oracle is None else oracle.queries.copy()
        if self.needs_oracle:
            out = self._perturb(batch, budget_m, surrogate=surrogate, generator=generator,
                                oracle=oracle)
        else:
            out = self._perturb(batch, budget_m, surrogate=surrogate, generator=generator)
        adv, extra = out if isinstance(out, tuple) else (out, {})
        if oracle is not None and before is not None:
            extra = {**extra, "queries": oracle.queries - before}
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
                generator: SampleGenerators | torch.Generator | int | None = None) -> torch.Tensor:
        """Adversarial scans (B, N, 3); see :meth:`run` for the audit."""
        return self.run(batch, budget_m, surrogate=surrogate, generator=generator).scans

    def settings(self) -> dict[str, Any]:
        """Settings recorded in the manifest."""
        return {"strict": self.strict, **self.params}

    @classmethod
    def settings_on(cls, settings: Mapping[str, Any], target: Any) -> dict[str, Any]:
        """Recorded ``settings`` (as :meth:`settings` gives them) as they act on ``target``: a
        setting that makes no difference against this target takes its neutral value, so that
        a run resumed under a changed default keeps the rows it would compute again (the runner
        compares settings this way). Default: ``settings`` unchanged."""
        return dict(settings)

    def fingerprint(self, budgets: Sequence[float]) -> dict[str, str]:
        """Identities of the files this attack reads for these budgets (metres), e.g. checkpoint
        hashes: a resumed run refuses to mix results made from different files. Default: none."""
        return {}
