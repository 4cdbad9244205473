"""Attack ``valley``: spoof a wrong pose, choosing each point's displacement so that the target's
cost falls all the way from the true pose to the wrong one (queries only, any target).

Beyond the paper. The ``spoof`` attack (:mod:`icpbench.attacks.spoof`) puts every point that can
reach it on the map at the pose shifted by D and moves the others lambda towards it. An ICP is a
descent method on its cost, so it stops at the first minimum of the cost on its way: along the line
from the true pose to D, the points that cannot reach (cross walls, poles) pull back once the pose
has passed lambda, and spoofed scans settle near 0.8 D (docs/methods.md, "The valley attack").

Here the cost along that line is modelled and the displacement chosen to make it *fall* along the
whole line. With ``q_i(a) = p_i + d_i + a D`` (scan point i at the true pose plus its displacement,
shifted by the fraction a of D; map frame) and the model cost of the evaluated target
``E(a) = sum_i rho(r_i(a))`` (:func:`~icpbench.core.cost_sensitivity.cost_of`: point or plane
residual to the nearest map point, its gate and its Cauchy kernel), every point contributes its
own term, so for a fixed weighting of the line's steps the choice separates per point. Each point
picks its displacement from a finite set of candidates of norm <= lambda (:func:`candidates`): no
move, the spoof displacement towards the map at 0.5-1.5 D, lambda along +-D, across D, up and down
and along +-its map normal. Which mix of candidates makes the largest climb of the cost along the
line smallest, ``min_d max_k [E(a_k) - E(a_{k-1})]``, is a linear programme over step weights
solved by cutting planes (:func:`choose`).

The schedule over D is the spoof attack's (a sweep of headings, a ladder of ``|D|``, random steps
from the best) with the ladder of this attack (:attr:`ValleyAttack.ladder`); the target's own
answer decides, so a model that misjudges the target costs queries, never the budget.

Frames: scans in the sensor frame; candidates and the line in the map frame at the true pose,
rotated back with ``R_gt^T``. Units: metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from scipy.optimize import linprog

from icpbench.attacks.spoof import SpoofAttack, spoofed_displacement
from icpbench.core.cost_sensitivity import (
    KERNEL_MODELS,
    CostSpec,
    KernelModel,
    acting_kernel_model,
    cost_of,
)
from icpbench.core.errors import InputError
from icpbench.core.projection import clip_displacements
from icpbench.core.registry import Range
from icpbench.targets.oracle import QueryOracle

#: Fractions of D of the spoof candidates.
SPOOF_FRACTIONS = (0.5, 0.75, 1.0, 1.25, 1.5)
#: Steps of the line from the true pose to D.
LINE_STEPS = 8
#: Cutting-plane rounds of the per-point choice.
ROUNDS = 40


def candidates(points_map: np.ndarray, offset: np.ndarray, map_index: Any,
               budget_m: float) -> np.ndarray:
    """Candidate displacements (C, N, 3), map frame, each row of norm <= ``budget_m``.

    Args:
        points_map: (N, 3) finite scan points at the true pose, map frame.
        offset: (3,) horizontal offset D, map frame, metres (non-zero).
        map_index: the map (``query``, ``points``, ``normals`` or None).
        budget_m: lambda.
    """
    n = points_map.shape[0]
    head = offset / np.linalg.norm(offset)
    across = np.array([-head[1], head[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    out = [np.zeros_like(points_map)]
    eye = np.eye(3)  # the spoof move in the map frame
    out += [spoofed_displacement(points_map, eye, s * offset, map_index, budget_m)
            for s in SPOOF_FRACTIONS]
    for e in (head, -head, across, -across, up, -up):
        out.append(np.broadcast_to(budget_m * e, (n, 3)).copy())
    if map_index.normals is not None:
        _, idx = map_index.query(points_map)
        normal = map_index.normals[idx]
        out += [budget_m * normal, -budget_m * normal]
    return clip_displacements(np.stack(out), budget_m)  # exact budget despite rounding


def rho(r: np.ndarray, cost: CostSpec) -> np.ndarray:
    """The model cost of residuals ``r`` (metres): ``cost``'s robust cost
    (:meth:`~icpbench.core.cost_sensitivity.CostSpec.rho`; Cauchy ``c^2/2 log(1 + r^2/c^2)`` or
    ``r^2/2`` by default), constant beyond the gate ``d_max`` (a gated pair pulls nothing)."""
    return cost.rho(np.minimum(np.abs(r), cost.d_max))


def line_climbs(points_map: np.ndarray, cand: np.ndarray, offset: np.ndarray, map_index: Any,
                cost: CostSpec, steps: int = LINE_STEPS) -> np.ndarray:
    """Climbs ``rho(r_i(a_k)) - rho(r_i(a_{k-1}))`` (C, K, N) of each point's model cost between
    the steps ``a_k = k / K`` of the line from the true pose to D, for every candidate.

    With point residuals the steps are looked up in turn, and a step is not looked up where an
    earlier one was so far from the map that this one is beyond the gate ``d_max`` (its
    distance is at least the earlier one's less the way between them, by the triangle
    inequality; the model cost is flat from the gate on): the same climbs, to the bit, with the
    farthest lookups, the dearest, left out (4-step plans of a ``town`` scan, 2026-11-30: 0.57 s
    against 0.68 s). A lookup stops searching as far out as a later step could still come within
    the gate.

    Args:
        points_map: (N, 3) finite scan points at the true pose, map frame.
        cand: (C, N, 3) candidate displacements, map frame.
        offset: (3,) D, map frame.
        map_index: the map.
        cost: the target's model cost (plane residuals need the map's normals; without them the
            point residual is used).
    """
    C, n, _ = cand.shape
    a = np.arange(steps + 1) / steps
    if cost.kind == "plane" and map_index.normals is not None:
        q = (points_map[None, None] + cand[:, None] + a[None, :, None, None] * offset)
        flat = q.reshape(-1, 3)  # (C (K+1) N, 3)
        dist, idx = map_index.query(flat)
        near = np.minimum(idx, len(map_index) - 1)  # idx == M (no neighbour) is masked below
        r = np.einsum("ij,ij->i", map_index.normals[near], flat - map_index.points[near])
        r = np.where(np.isfinite(dist), r, np.inf)
        e = rho(r, cost).reshape(C, steps + 1, n)
        return np.diff(e, axis=1)
    start = (points_map[None] + cand).reshape(-1, 3)  # (C N, 3): each line's first point
    shift = a[:, None] * offset  # (K+1, 3): the steps along D, as the full product forms them
    r = np.empty((steps + 1, start.shape[0]))
    low = np.full(start.shape[0], -np.inf)  # a lower bound of each step's distance to the map
    beyond = cost.d_max * (1.0 + 1e-9) + 1e-9  # margins far above the rounding of a distance
    way = [float(np.linalg.norm(shift[k] - shift[k - 1])) for k in range(1, steps + 1)]
    for k in range(steps + 1):
        if k:
            low = low - way[k - 1]
        ask = ~(low > beyond)
        r[k] = cost.d_max  # rho is flat from the gate on
        # the search stops where no later step of the line can come within the gate: a point
        # farther comes back as inf (rho(inf) is rho(d_max), as for its distance) and is not
        # looked up again
        bound = beyond + sum(way[k:]) * (1.0 + 1e-9) + 1e-9
        near = map_index.query(start[ask] + shift[k], bound)[0]
        r[k, ask] = near
        low[ask] = np.where(np.isfinite(near), near, bound)
    e = rho(r, cost).reshape(steps + 1, C, n).transpose(1, 0, 2)
    return np.ascontiguousarray(np.diff(e, axis=1))  # the layout einsum sums in (choose)


def choose(climbs: np.ndarray, rounds: int = ROUNDS) -> np.ndarray:
    """Per point, the candidate (N,) int whose choice makes the largest climb of the summed cost
    over the line's steps as small as this finds.

    The problem ``min over choices of max_k sum_i climbs[c_i, k, i]`` relaxed to mixed choices is a
    linear programme whose dual, ``max over step weights mu (a simplex) of
    sum_i min_c mu . climbs[c, :, i]``, has only K variables; it is solved by Kelley's cutting
    planes ("The cutting-plane method for solving convex programs", J. SIAM 1960): each round
    picks every point's best candidate for the current weights, and the next weights maximise the
    lower envelope of the rounds' climb totals. The weights the master programme puts on the rounds
    mix their choices; each point takes the candidate with the largest mixed weight, and the result
    is kept only if no single round's choice climbs less. scipy's HiGHS on the full programme
    (N C variables) gave the same largest climb to 1.5% but took 73 s against 0.3 s here
    (N = 10,000, C = 14, K = 8), so the small dual is solved instead.

    Args:
        climbs: (C, K, N) from :func:`line_climbs`.
        rounds: cutting-plane rounds.
    """
    C, K, n = climbs.shape
    cols = np.arange(n)
    mu = np.full(K, 1.0 / K)
    picks: list[np.ndarray] = []
    totals: list[np.ndarray] = []
    mix = np.array([1.0])
    for _ in range(rounds):
        pick = np.einsum("k,ckn->cn", mu, climbs).argmin(axis=0)
        picks.append(pick)
        totals.append(climbs[pick, :, cols].sum(axis=0))  # (K,)
        S = np.array(totals)
        # master: max z s.t. z <= S mu (each round's envelope), mu on the simplex
        res = linprog(np.r_[np.zeros(K), -1.0], A_ub=np.c_[-S, np.ones(len(S))],
                      b_ub=np.zeros(len(S)), A_eq=np.r_[np.ones(K), 0.0][None], b_eq=[1.0],
                      bounds=[(0.0, None)] * K + [(None, None)], method="highs")
        if res.status != 0:
            break
        mix = np.maximum(-res.ineqlin.marginals, 0.0)
        if np.allclose(res.x[:K], mu):
            break
        mu = res.x[:K]
    weight = np.zeros((C, n))
    for lam_j, pick in zip(mix / max(mix.sum(), 1e-300), picks, strict=False):
        weight[pick, cols] += lam_j
    best = weight.argmax(axis=0)
    best_max = climbs[best, :, cols].sum(axis=0).max()
    for pick, total in zip(picks, totals, strict=True):
        if total.max() < best_max:
            best, best_max = pick, total.max()
    return best


def valley_displacement(points_map: np.ndarray, rotation: np.ndarray, offset: np.ndarray,
                        map_index: Any, budget_m: float, cost: CostSpec,
                        steps: int = LINE_STEPS) -> np.ndarray:
    """Displacements (N, 3), sensor frame, each of norm <= lambda, that make the model cost fall
    along the line from the true pose to the pose shifted by ``offset`` (module docstring).

    Args:
        points_map: (N, 3) scan points at the true pose, map frame (non-finite rows stay still).
        rotation: (3, 3) rotation of the true pose (sensor to map).
        offset: (3,) horizontal offset D, map frame, metres.
        map_index: the map (:class:`~icpbench.core.mapindex.MapIndex`).
        budget_m: lambda.
        cost: the evaluated target's model cost (:func:`~icpbench.core.cost_sensitivity.cost_of`).
        steps: steps of the line on which the climbs are modelled (:func:`line_climbs`).
    """
    delta = np.zeros_like(points_map)
    ok = np.isfinite(points_map).all(axis=1)
    if not ok.any() or not np.linalg.norm(offset) > 0:
        return delta
    p = points_map[ok]
    cand = candidates(p, offset, map_index, budget_m)
    pick = choose(line_climbs(p, cand, offset, map_index, cost, steps))
    delta[ok] = cand[pick, np.arange(p.shape[0])]
    return delta @ rotation  # R^T delta per row: sensor frame


class ValleyAttack(SpoofAttack):
    """Spoof a wrong pose with each point's move chosen so the target's cost falls all the way
    there (module docstring).

    Args:
        queries: queries per scan, >= 1.
        directions: headings of the first sweep, >= 1.
        screen: headings ranked by the map's misfit before the sweep (``spoof``'s setting).
        line_steps: steps of the line from the true pose to D on which each plan models the
            cost's climbs, >= 1. The plan's nearest-neighbour queries, most of its time, grow
            with ``line_steps + 1``; on the first 16 scans of the ``town`` board, 4 steps took
            0.63-0.76x the default 8's time at 0.96-1.01x its error
            (results/valley-line-steps).
        kernel_model: how the plan models the target's robust kernel
            (:data:`~icpbench.core.cost_sensitivity.KERNEL_MODELS`): ``"geman-mcclure"`` (the
            standard protocol's from v3) models a Geman-McClure kernel (KISS-ICP's) as itself and
            every other kernel as Cauchy's; ``"cauchy"`` (v2's) also KISS-ICP's as none;
            ``"own"`` every target's own kernel. On KISS-ICP's 32 scans of the two boards,
            Geman-McClure raised the worst case 1.15-1.17x over v2's plan at the same time per
            scan; Huber's own kernel lowered ``valley``'s error on p2plane (Huber) to 0.74-0.92x.
    """

    name: ClassVar[str] = "valley"
    cost_class: ClassVar[int] = 3
    description: ClassVar[str] = (
        "Spoof a pose shifted by D, each point's move (within lambda) chosen so the target's model "
        "cost falls along the line to D; D searched with queries; any target (beyond the paper)"
    )
    ladder: ClassVar[tuple[float, ...]] = (2.5, 3.0)
    param_ranges: ClassVar[dict[str, Range]] = {**SpoofAttack.param_ranges,
                                                "line_steps": Range(1, 10_000)}

    def __init__(self, *, strict: bool = False, queries: int = 16, directions: int = 8,
                 screen: int = 0, line_steps: int = LINE_STEPS,
                 kernel_model: KernelModel = "geman-mcclure",
                 **params: Any) -> None:
        if isinstance(line_steps, bool) or int(line_steps) != line_steps or int(line_steps) < 1:
            raise InputError(f"{self.name} line_steps must be an integer >= 1, got {line_steps!r}")
        if kernel_model not in KERNEL_MODELS:
            raise InputError(f"{self.name} kernel_model must be one of {', '.join(KERNEL_MODELS)}, "
                             f"got {kernel_model!r}")
        self.line_steps = int(line_steps)
        self.kernel_model = kernel_model
        super().__init__(strict=strict, queries=queries, directions=directions, screen=screen,
                         line_steps=self.line_steps, kernel_model=kernel_model, **params)

    @classmethod
    def settings_on(cls, settings: Mapping[str, Any], target: Any) -> dict[str, Any]:
        """``settings`` with ``kernel_model`` as it acts on ``target`` (:func:`acting_kernel_model`)."""
        return {**settings, "kernel_model": acting_kernel_model(settings.get("kernel_model"),
                                                                target)}

    def displacement(self, points_map: np.ndarray, rotation: np.ndarray, offset: np.ndarray,
                     map_index: Any, budget_m: float, oracle: QueryOracle) -> np.ndarray:
        """:func:`valley_displacement` with the evaluated target's model cost."""
        return valley_displacement(points_map, rotation, offset, map_index, budget_m,
                                   cost_of(oracle.target, kernel_model=self.kernel_model),
                                   self.line_steps)
