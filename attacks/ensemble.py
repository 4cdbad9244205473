"""Attack ``ensemble``: per scan, the largest error on the *evaluated* target over a fixed standard
set of attacks, white-box and query-only; the harness's one definition of the worst case.

Beyond the paper; the ICP version of AutoAttack (Croce and Hein, "Reliable evaluation of adversarial
robustness with an ensemble of diverse parameter-free attacks", ICML 2020): a robustness figure
measured with one non-adaptive attack is an upper bound that is routinely wrong, so the harness
reports the worst over a fixed, diverse, adaptive set. :data:`MEMBERS` names every member in the
order they run; :data:`DEFAULT_MEMBERS` are the ones that run unless ``members`` says otherwise:

=====================  =========================================================================
``uniform``            the whole scan translated by lambda (the paper's baseline; every board's
                       reference, so always worth its one query)
``normal``             every point by lambda along its map normal, projected to x-y (paper);
                       not a default member (it never won a scan of the 48-scan board)
``sector``             the analytic one-step point-to-plane worst case (Laconte et al., RA-L 2024);
                       rarely the worst itself, but the start PGD climbs from on GICP
``sector-adaptive``    the one-step worst case of the target's *own* cost, re-linearised where the
                       target lands (queries only; :mod:`icpbench.attacks.sector_adaptive`)
``pgd``                projected gradient ascent through the run's surrogate, started from the best
                       scan of the members before it: with ``--surrogate self`` the target itself,
                       or its differentiable replica, at its own converged pose (implicit
                       gradient); skipped when there is no differentiable surrogate. Against
                       a monitored oracle it climbs the error minus the monitors'
                       differentiable scores (:mod:`icpbench.monitors.penalty`)
``spoof``              the scan made to agree with the map at a wrong pose, the pose searched with
                       queries (:mod:`icpbench.attacks.spoof`), from the clean scan
``valley``             spoof with each point's move chosen so the target's model cost falls all the
                       way to the wrong pose (:mod:`icpbench.attacks.valley`), from the clean scan
``search``             score-based random search (:mod:`icpbench.attacks.search`) started from the
                       best scan of every member before it
``drift``              the scan translated rigidly, heading and length (<= lambda) searched
                       (:mod:`icpbench.attacks.drift`): only a motion prior sees it. Not a default
                       member; added to the defaults when the oracle hides detected errors
                       (``--monitor-aware``, :data:`MONITOR_AWARE_MEMBERS`), where the other
                       members' candidates overshoot an odometry gate and it finds the gate's edge
``refine``             projected gradient ascent (as ``pgd``, :data:`REFINE_STEPS` steps) from
                       the best scan of every member before it: against a monitored oracle the
                       error minus the monitors' differentiable scores, so it climbs from the best
                       undetected scan along the edge of what the monitors accept. Not a default
                       member; added with ``drift`` under ``--monitor-aware``
=====================  =========================================================================

Every member's output is registered by the target (a query) and the scan with the largest
``trans_err_xy`` is kept, so the ensemble's row is never below any member's on any scan. The
members run with the attack seed they would have alone, so the members that start from the clean
scan give the rows they would give alone. Per row: ``extra.winner`` (index of the winning member in
:data:`MEMBERS`), ``extra.err_<member>`` (each member's error on the target; a member that did not
run has no column, one that was skipped on a scan NaN), ``extra.s_<member>`` (its seconds per scan),
``extra.queries``; with a search budget above 20 queries, ``extra.search_best_at_<q>``: the
ensemble's error had the search stopped after q of its queries (q in
:data:`~icpbench.attacks.search.TRACE_QUERIES`), so one large-budget run shows how the worst case
grows with the budget.

When the query search, started from the gradient member's result (where that was the best so
far), still raises the error on a *differentiable* target by more than :data:`WEAK_GRADIENT_GAIN`,
the gradient stalled where random search climbs: it is weak there (masked, truncated or aimed at the
wrong pose), and the ICP is not as robust as the gradient alone would say. A warning is logged
(logger ``icpbench``) and ``extra.weak_gradient`` is 1 on those scans.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, SampleGenerators
from icpbench.attacks.drift import DriftAttack
from icpbench.attacks.normal import NormalTranslationAttack
from icpbench.attacks.pgd import PGDAttack
from icpbench.attacks.search import QuerySearchAttack
from icpbench.attacks.sector import SectorAttack
from icpbench.attacks.sector_adaptive import SectorAdaptiveAttack, score
from icpbench.attacks.spoof import SpoofAttack
from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.attacks.valley import ValleyAttack
from icpbench.core.cost_sensitivity import KernelModel, acting_kernel_model
from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

#: Query budgets of ``spoof`` and ``valley`` in the ensemble, the headings each queries first and
#: the headings it screens by the map's misfit before (docs/methods.md, "The standard ensemble").
SPOOF_QUERIES, VALLEY_QUERIES, DIRECTIONS, SCREEN = 24, 16, 8, 0
#: Steps of the line to the wrong pose on which ``valley`` models the target's cost in the ensemble
#: (:class:`~icpbench.attacks.valley.ValleyAttack` ``line_steps``; its own default is finer).
VALLEY_LINE_STEPS = 4
#: The search member stops a scan after this many queries in a row without a larger error.
SEARCH_PATIENCE = 8
#: Query budget of the ``drift`` member.
DRIFT_QUERIES = 24
#: Ascent steps of the ``refine`` member (each of ``pgd_step_size`` times lambda).
REFINE_STEPS = 10

#: Every member, in the order they run; ``extra.winner`` indexes this tuple. The one place that
#: names the members: the leaderboard, budget curves and tables read it from here.
MEMBERS: tuple[str, ...] = ("uniform", "normal", "sector", "sector-adaptive", "pgd", "spoof",
                            "valley", "search", "drift", "refine")
#: The members that run by default (``members`` setting): every member that won a scan of the
#: 48-scan board; ``uniform``, the reference of every "x uniform" figure; and ``sector``, from which
#: PGD finds GICP's worst case on a fifth of its scans.
DEFAULT_MEMBERS: tuple[str, ...] = ("uniform", "sector", "sector-adaptive", "pgd", "spoof",
                                    "valley", "search")
#: Members added to the defaults when the oracle hides the errors integrity monitors detect
#: (:attr:`~icpbench.targets.oracle.QueryOracle.hides_detected`; ``--monitor-aware``); a run that
#: names its members gets exactly those.
MONITOR_AWARE_MEMBERS: tuple[str, ...] = ("drift", "refine")
#: Members that use nothing but the target's output pose.
QUERY_ONLY: frozenset[str] = frozenset({"sector-adaptive", "spoof", "valley", "search", "drift"})

#: Relative gain of the search over the gradient member that flags a weak gradient.
WEAK_GRADIENT_GAIN = 0.1

log = logging.getLogger("icpbench")


def column(member: str) -> str:
    """The ``extra`` key of a member's error (``err_sector_adaptive`` for ``sector-adaptive``)."""
    return "err_" + member.replace("-", "_")


def seconds_column(member: str) -> str:
    """The ``extra`` key of a member's attack time per scan, seconds (``s_sector_adaptive``)."""
    return "s_" + member.replace("-", "_")


def parse_members(members: str | list[str] | tuple[str, ...] | None) -> tuple[str, ...]:
    """The members named by ``members`` (comma-separated text or a list; None: the defaults), in
    the order of :data:`MEMBERS`.

    Raises:
        InputError: an unknown or repeated name, or no member at all.
    """
    if members is None:
        return DEFAULT_MEMBERS
    names = [m.strip() for m in (members.split(",") if isinstance(members, str) else members)]
    names = [m for m in names if m]
    unknown = [m for m in names if m not in MEMBERS]
    if unknown:
        raise InputError(f"ensemble members: unknown {', '.join(map(repr, unknown))}; valid: "
                         f"{', '.join(MEMBERS)}")
    if len(set(names)) != len(names):
        raise InputError(f"ensemble members: a member is named twice in {names}")
    if not names:
        raise InputError(f"ensemble members: none given; valid: {', '.join(MEMBERS)}")
    return tuple(m for m in MEMBERS if m in names)


class EnsembleAttack(Attack):
    """Worst case per scan over the standard members (module docstring).

    Args:
        members: the members to run (comma-separated names of :data:`MEMBERS`, run in that order;
            default :data:`DEFAULT_MEMBERS`).
        pgd_steps: ascent steps of the ``pgd`` member (0: skip it).
        pgd_step_size: its step as a fraction of lambda (the ``refine`` member's too).
        sector_iterations: re-linearisations of the ``sector-adaptive`` member.
        queries: query budget of the ``search`` member per scan (0: skip it).
        patience: the search stops a scan after this many queries in a row without a larger
            error (0: it spends every query).
        spoof_queries, valley_queries: query budgets of ``spoof`` and ``valley`` per scan.
        valley_line_steps: steps of the line on which ``valley`` models the target's cost.
        valley_kernel_model: how ``valley`` models the target's robust kernel
            (:class:`~icpbench.attacks.valley.ValleyAttack` ``kernel_model``; ``"geman-mcclure"``
            from the standard protocol v3, ``"cauchy"`` before).
        directions: headings each of them queries in its first sweep.
        screen: headings each of them ranks by the map's misfit before choosing which to query
            (:func:`~icpbench.attacks.spoof.misfit`; 0: an even fan, no screen).
    """

    name: ClassVar[str] = "ensemble"
    cost_class: ClassVar[int] = 4
    description: ClassVar[str] = (
        "Per scan, the worst error on the evaluated target over uniform, sector, sector-adaptive, "
        "PGD (through the target or its replica), spoof, valley and a query search from the best"
    )
    needs_oracle: ClassVar[bool] = True
    uses_surrogate: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        "pgd_steps": Range(0, 100_000), "pgd_step_size": Range(0.0, 2.0, lo_open=True),
        "sector_iterations": Range(0, 100_000), "queries": Range(0, 10_000_000),
        "spoof_queries": Range(1, 10_000_000), "valley_queries": Range(1, 10_000_000),
        "directions": Range(1, 100_000), "screen": Range(0, 100_000),
        "patience": Range(0, 10_000_000), "valley_line_steps": Range(1, 10_000)}

    def __init__(self, *, strict: bool = False, members: str | None = None, pgd_steps: int = 5,
                 pgd_step_size: float = 0.1, sector_iterations: int = 4, queries: int = 20,
                 spoof_queries: int = SPOOF_QUERIES, valley_queries: int = VALLEY_QUERIES,
                 directions: int = DIRECTIONS, screen: int = SCREEN,
                 patience: int = SEARCH_PATIENCE, valley_line_steps: int = VALLEY_LINE_STEPS,
                 valley_kernel_model: KernelModel = "geman-mcclure", **params: Any) -> None:
        for nm, v, lo in (("pgd_steps", pgd_steps, 0), ("sector_iterations", sector_iterations, 0),
                          ("queries", queries, 0), ("spoof_queries", spoof_queries, 1),
                          ("valley_queries", valley_queries, 1), ("directions", directions, 1),
                          ("screen", screen, 0), ("patience", patience, 0),
                          ("valley_line_steps", valley_line_steps, 1)):
            if isinstance(v, bool) or int(v) != v or int(v) < lo:
                raise InputError(f"{self.name} {nm} must be an integer >= {lo}, got {v!r}")
        self.active = parse_members(members)
        self.named = members is not None  # the run chose its members: none is added
        self.pgd_steps, self.queries = int(pgd_steps), int(queries)
        self.pgd_step_size = float(pgd_step_size)
        if self.pgd_steps:
            PGDAttack(steps=self.pgd_steps, step_size=self.pgd_step_size)  # checks the settings
        self.search_attack = QuerySearchAttack(strict=strict, queries=max(self.queries, 1),
                                               patience=int(patience))
        spoofing = dict(directions=int(directions), screen=int(screen))
        self.members: dict[str, Attack] = {
            "uniform": UniformTranslationAttack(strict=strict),
            "normal": NormalTranslationAttack(strict=strict),
            "sector": SectorAttack(strict=strict),
            "sector-adaptive": SectorAdaptiveAttack(strict=strict,
                                                    iterations=int(sector_iterations)),
            "spoof": SpoofAttack(strict=strict, queries=int(spoof_queries), **spoofing),
            "valley": ValleyAttack(strict=strict, queries=int(valley_queries),
                                   line_steps=int(valley_line_steps),
                                   kernel_model=valley_kernel_model, **spoofing),
            "drift": DriftAttack(strict=strict, queries=DRIFT_QUERIES, directions=int(directions)),
        }
        super().__init__(strict=strict, pgd_steps=self.pgd_steps, pgd_step_size=self.pgd_step_size,
                         sector_iterations=int(sector_iterations), queries=self.queries,
                         spoof_queries=int(spoof_queries), valley_queries=int(valley_queries),
                         directions=int(directions), screen=int(screen),
                         patience=int(patience), valley_line_steps=int(valley_line_steps),
                         valley_kernel_model=valley_kernel_model, members=list(self.active),
                         **params)

    @classmethod
    def settings_on(cls, settings: Mapping[str, Any], target: Any) -> dict[str, Any]:
        """``settings`` with ``valley_kernel_model`` as it acts on ``target``
        (:func:`~icpbench.core.cost_sensitivity.acting_kernel_model`)."""
        return {**settings, "valley_kernel_model": acting_kernel_model(
            settings.get("valley_kernel_model"), target)}

    def active_for(self, oracle: QueryOracle | None) -> tuple[str, ...]:
        """The members that run against ``oracle``: the chosen ones, plus
        :data:`MONITOR_AWARE_MEMBERS` when the oracle hides detected errors and the run left the
        members to their defaults; in the order of :data:`MEMBERS`."""
        if self.named or not getattr(oracle, "hides_detected", False):
            return self.active
        return tuple(m for m in MEMBERS if m in self.active or m in MONITOR_AWARE_MEMBERS)

    def _pgd(self, surrogate: Target, steps: int) -> PGDAttack:
        """The gradient member (``pgd`` or ``refine``) for this surrogate: ``steps`` steps, the
        surrogate's own iteration cap, implicit gradient."""
        cap = getattr(getattr(surrogate, "config", None), "max_iterations", 100)
        return PGDAttack(strict=self.strict, steps=steps, step_size=self.pgd_step_size,
                         icp_iterations=int(cap), backprop="implicit")

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: SampleGenerators, oracle: QueryOracle
                 ) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        seed = 0 if generator.seed is None else generator.seed
        clean = batch.scans.detach().to(torch.float64)
        B = len(batch)
        best = clean.clone()
        best_err = np.full(B, np.nan)
        winner = np.full(B, np.nan)
        extra: dict[str, np.ndarray] = {}
        active = self.active_for(oracle)
        for i, name in enumerate(MEMBERS):
            if name not in active:
                continue
            t0 = time.perf_counter()
            if name == "search":
                from_gradient = winner == MEMBERS.index("pgd")  # the search starts there
                if self.queries == 0:
                    err = np.full(B, np.nan)
                else:
                    gens = SampleGenerators.for_batch(batch, seed, name, budget_m)
                    # a scan no member has scored yet (NaN) makes the search measure its start
                    trace: dict[int, np.ndarray] = {}
                    adv_np, err = self.search_attack.search(
                        batch, budget_m, oracle, gens, start=best.numpy(),
                        start_err=None if np.isnan(best_err).any() else best_err, trace=trace)
                    # the ensemble's worst case had it stopped after q search queries
                    extra.update({f"search_best_at_{q}": e for q, e in trace.items()})
                    adv = torch.as_tensor(adv_np)
            elif name in ("pgd", "refine"):
                steps = self.pgd_steps if name == "pgd" else REFINE_STEPS
                if steps == 0 or surrogate is None or not surrogate.differentiable:
                    err = np.full(B, np.nan)
                else:
                    # against a monitored oracle: the monitors' scores as a penalty
                    adv = self._pgd(surrogate, steps).refine(batch, best.to(batch.scans.dtype),
                                                             budget_m, surrogate=surrogate,
                                                             penalty=oracle.penalty())
                    adv = adv.to(torch.float64)
                    err = oracle.errors(adv)
            elif name in ("spoof", "valley"):  # their own best is measured already
                gens = SampleGenerators.for_batch(batch, seed, name, budget_m)
                member = self.members[name]
                adv_np, err, _ = member.spoof(batch, budget_m, oracle, gens)  # type: ignore[attr-defined]
                adv = torch.as_tensor(adv_np)
            elif name == "drift":
                gens = SampleGenerators.for_batch(batch, seed, name, budget_m)
                adv_np, err, _, _ = self.members[name].drift(  # type: ignore[attr-defined]
                    batch, budget_m, oracle, gens)
                adv = torch.as_tensor(adv_np)
            else:
                member = self.members[name]
                adv = member.run(batch, budget_m, surrogate=surrogate, generator=seed,
                                 oracle=oracle if member.needs_oracle else None
                                 ).scans.to(torch.float64)
                err = oracle.errors(adv)
            extra[column(name)] = err
            extra[seconds_column(name)] = np.full(B, (time.perf_counter() - t0) / B)
            better = score(err) > score(best_err)
            if better.any():
                sel = torch.as_tensor(better)
                best[sel] = adv[sel]
                best_err[better], winner[better] = err[better], i
        extra["winner"] = winner
        weak = np.zeros(B)
        g, q = extra.get(column("pgd")), extra.get(column("search"))
        if g is not None and q is not None and getattr(oracle.target, "differentiable", False) \
                and not np.isnan(g).all():
            weak = (from_gradient & (score(q) > (1 + WEAK_GRADIENT_GAIN) * score(g))
                    ).astype(np.float64)
            if weak.any():
                log.warning("ensemble: on %d of %d scans of the differentiable target %r the query "
                            "search raised the gradient member's error by more than %d%%: the "
                            "gradient is weak there, not the ICP robust", int(weak.sum()), B,
                            oracle.name, round(100 * WEAK_GRADIENT_GAIN))
        extra["weak_gradient"] = weak
        return best.to(batch.scans.dtype), extra
