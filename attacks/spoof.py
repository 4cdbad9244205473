"""Attack ``spoof``: make the scan agree with the map at a wrong pose, then ask the target how far
it follows (queries only, any target).

Beyond the paper; a *targeted* attack in the sense of Carlini and Wagner ("Towards evaluating the
robustness of neural networks", IEEE S&P 2017), where the target is a pose. Every ICP, whatever
its cost (point-to-plane, point-to-point, GICP), returns a pose at which the scan lies on the map.
Let ``p_i`` be scan point i at the true pose (map frame) and ``D`` a horizontal offset (map
frame). Moving the point by

    delta_i(D) = P_lambda( m_i(D) - p_i - D ),   m_i(D) = nearest map point of p_i + D,

(``P_lambda``: projection onto the lambda-ball) puts it *on the map at the pose shifted by D*
wherever the map comes within lambda of ``p_i + D``: on every surface D slides along (the walls of
a street, the road, a facade), on repeated structure, and near surfaces whose offset is small.
The points that pin the pose along D (cross walls, poles), where the map is farther than lambda,
are moved lambda towards agreement. With ``|D| = lambda`` on a map that is invariant along D this
is the paper's uniform translation; with ``|D|`` beyond lambda the scan still agrees with the map
at ``T_gt + D`` exactly where an ICP is weakest, and the target is led there or stops in between.
An ICP starts at its initial guess, so whether it reaches D depends on its basin: on the
``lidar-sim`` test scans point-to-point ICPs follow ``|D|`` of 2-2.5 lambda on most scans and fall
back towards lambda beyond (docs/methods.md, "The spoof attack"). Hence a search over D with the
evaluated target's answers:

1. ``directions`` headings (a random rotation of an even fan, per scan) at ``|D| = 2 lambda``;
   with ``screen`` > ``directions``, a fan of ``screen`` headings is ranked first without a query
   by the map's *misfit* at the shifted pose (:func:`misfit`: how far the scan points lie from the
   map at ``p + D`` beyond what lambda can close), and only the ``directions`` best are queried;
2. the two best headings at ``|D|`` = 2.5, 3 and 4 lambda (:data:`LADDER`);
3. the remaining queries: random steps from the best ``(heading, |D|)`` (heading by a normal step
   of half the fan's spacing, ``|D|`` by a log-normal factor), kept when the error grows.

One query per scan and step, every scan of the batch in one call; the scan with the largest error
on the target is returned. The displacement is recomputed from the *clean* scan for every D, so
each point moves at most lambda. Frames: scans in the sensor frame, displacements computed in the
map frame at the true pose and rotated back with ``R_gt^T``.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, SampleGenerators
from icpbench.attacks.sector_adaptive import score
from icpbench.core.errors import InputError
from icpbench.core.projection import clip_displacements
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

#: ``|D|`` / lambda of the first sweep over headings.
FIRST_OFFSET = 2.0
#: ``|D|`` / lambda tried along the two best headings after the sweep.
LADDER = (2.5, 3.0, 4.0)
#: Headings of the sweep that get the ladder.
LADDER_HEADINGS = 2
#: Misfit of one point (metres) is capped here, in units of lambda (a point far from the map at
#: the shifted pose counts the same however far it is).
MISFIT_CAP = 2.0
#: Bounds of ``|D|`` / lambda in the random steps, and the log-normal scale of a step.
OFFSET_BOUNDS = (1.0, 8.0)
OFFSET_STEP = 0.2


def spoofed_displacement(points_map: np.ndarray, rotation: np.ndarray, offset: np.ndarray,
                         map_index: Any, budget_m: float) -> np.ndarray:
    """Displacements (N, 3), sensor frame, that put the scan on the map at the pose shifted by
    ``offset`` wherever the map is within ``budget_m`` (module docstring).

    Args:
        points_map: (N, 3) scan points at the true pose, map frame (non-finite rows stay still).
        rotation: (3, 3) rotation of the true pose (sensor to map).
        offset: (3,) offset D of the wrong pose's translation, map frame, metres.
        map_index: the map (:class:`~icpbench.core.mapindex.MapIndex`: ``query`` and ``points``).
        budget_m: lambda; every row of the result has norm <= lambda.
    """
    target = points_map + offset
    _, idx = map_index.query(target)
    found = idx < len(map_index)
    delta = np.zeros_like(points_map)
    delta[found] = map_index.points[idx[found]] - target[found]
    return clip_displacements(delta, budget_m) @ rotation  # R^T delta per row: sensor frame


def misfit(points_map: np.ndarray, offset: np.ndarray, map_index: Any, budget_m: float) -> float:
    """How badly the scan can be made to agree with the map at the pose shifted by ``offset``:
    the mean over finite points of ``min(max(d_i - lambda, 0), MISFIT_CAP lambda)``, ``d_i`` the
    distance of ``p_i + D`` to its nearest map point (metres; 0 where every point can be put on
    the map). A heading along which the scene repeats (a street, a facade) has a small misfit;
    one that crosses walls a large one. Costs one nearest-neighbour query of the scan, no target
    query.

    Args:
        points_map: (N, 3) scan points at the true pose, map frame.
        offset: (3,) offset D, map frame, metres.
        map_index: the map (``query``).
        budget_m: lambda.
    """
    ok = np.isfinite(points_map).all(axis=1)
    if not ok.any():
        return 0.0
    dist, _ = map_index.query(points_map[ok] + offset)
    cap = MISFIT_CAP * budget_m
    return float(np.mean(np.minimum(np.maximum(dist - budget_m, 0.0), cap)))  # inf: no map


class SpoofAttack(Attack):
    """Lead the target to a wrong pose the scan is made to agree with (module docstring).

    Args:
        queries: queries per scan, >= 1 (the schedule is cut short below
            ``directions + LADDER_HEADINGS * len(LADDER)``).
        directions: headings of the first sweep, >= 1.
        screen: headings ranked by :func:`misfit` before the sweep, of which the ``directions``
            best are queried (0 or <= ``directions``: no screen, the sweep is an even fan).
    """

    name: ClassVar[str] = "spoof"
    cost_class: ClassVar[int] = 2
    description: ClassVar[str] = (
        "Make the scan agree with the map at a pose shifted by D (each point within lambda) and "
        "search D with queries; any target (beyond the paper)"
    )
    needs_oracle: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        "queries": Range(1, 10_000_000), "directions": Range(1, 100_000),
        "screen": Range(0, 100_000)}
    #: ``|D|`` / lambda of the first sweep and of the ladder (subclasses may change the schedule).
    first_offset: ClassVar[float] = FIRST_OFFSET
    ladder: ClassVar[tuple[float, ...]] = LADDER

    def __init__(self, *, strict: bool = False, queries: int = 24, directions: int = 8,
                 screen: int = 0, **params: Any) -> None:
        for nm, v, lo in (("queries", queries, 1), ("directions", directions, 1),
                          ("screen", screen, 0)):
            if isinstance(v, bool) or int(v) != v or int(v) < lo:
                raise InputError(f"{self.name} {nm} must be an integer >= {lo}, got {v!r}")
        self.queries, self.directions = int(queries), int(directions)
        self.screen = int(screen) if int(screen) > self.directions else 0
        if self.screen:
            params["screen"] = self.screen
        super().__init__(strict=strict, queries=self.queries, directions=self.directions, **params)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: SampleGenerators, oracle: QueryOracle
                 ) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        adv, err, offset = self.spoof(batch, budget_m, oracle, generator)
        extra = {"spoof_err": err, "spoof_offset_m": offset}
        return torch.as_tensor(adv, dtype=batch.scans.dtype), extra

    def displacement(self, points_map: np.ndarray, rotation: np.ndarray, offset: np.ndarray,
                     map_index: Any, budget_m: float, oracle: QueryOracle) -> np.ndarray:
        """Displacements (N, 3), sensor frame, each of norm <= lambda, that lead the target towards
        the pose shifted by ``offset`` (map frame); here :func:`spoofed_displacement`."""
        return spoofed_displacement(points_map, rotation, offset, map_index, budget_m)

    def spoof(self, batch: Batch, budget_m: float, oracle: QueryOracle,
              generator: SampleGenerators) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run the schedule. Returns the best scans (B, N, 3) float64 (sensor frame), their errors
        on the target (B,) in metres (NaN where every query diverged) and the length ``|D|`` (B,)
        in metres of the offset that gave them."""
        clean = batch.scans.detach().to(torch.float64).numpy()
        B = clean.shape[0]
        T_gt = batch.T_gt.to(torch.float64).numpy()
        R = T_gt[:, :3, :3]
        p_map = np.einsum("bij,bnj->bni", R, clean) + T_gt[:, None, :3, 3]
        maps = batch.maps
        K = self.directions
        fan = self.screen or K  # headings of the first sweep's fan
        spacing = 2 * math.pi / fan
        start = generator.rand(dtype=torch.float64).numpy() * spacing  # (B,)
        # the headings (B, K) of the sweep: the whole fan, or its K best by misfit
        heads = start[:, None] + np.arange(fan)[None] * spacing
        if self.screen:
            bad = np.array([[misfit(p_map[b], self.first_offset * budget_m
                                    * np.array([math.cos(h), math.sin(h), 0.0]), maps[b],
                                    budget_m) for h in heads[b]] for b in range(B)])
            keep = np.sort(np.argsort(bad, axis=1, kind="stable")[:, :K], axis=1)
            heads = np.take_along_axis(heads, keep, axis=1)

        best = clean.copy()
        best_err = np.full(B, np.nan)
        best_hm = np.full((B, 2), np.nan)  # (heading rad, |D| / lambda) of the best
        sweep_err = np.full((B, K), -np.inf)

        def query(hm: np.ndarray) -> np.ndarray:
            """Evaluate (heading, |D| / lambda) per scan (B, 2); keep the best; errors (B,)."""
            adv = clean.copy()
            for b in range(B):
                h, m = hm[b]
                D = m * budget_m * np.array([math.cos(h), math.sin(h), 0.0])
                adv[b] += self.displacement(p_map[b], R[b], D, maps[b], budget_m, oracle)
            err = oracle.errors(adv)
            better = score(err) > score(best_err)
            best[better], best_err[better], best_hm[better] = adv[better], err[better], hm[better]
            return err

        used = 0
        for k in range(min(K, self.queries)):
            sweep_err[:, k] = score(query(np.stack([heads[:, k],
                                                    np.full(B, self.first_offset)], 1)))
            used += 1
        top = np.argsort(-sweep_err, axis=1, kind="stable")[:, :LADDER_HEADINGS]
        for j in range(min(LADDER_HEADINGS, K)):
            for m in self.ladder:
                if used >= self.queries:
                    break
                query(np.stack([np.take_along_axis(heads, top[:, j:j + 1], 1)[:, 0],
                                np.full(B, m)], 1))
                used += 1
        lo, hi = OFFSET_BOUNDS
        while used < self.queries:
            hm = best_hm.copy()
            for b in range(B):
                g = generator[b]
                if np.isnan(hm[b, 0]):  # every query diverged so far: a fresh heading
                    hm[b] = (float(torch.rand(1, generator=g)) * 2 * math.pi, self.first_offset)
                    continue
                z = torch.randn(2, generator=g, dtype=torch.float64).numpy()
                hm[b, 0] += 0.5 * spacing * z[0]
                hm[b, 1] = float(np.clip(hm[b, 1] * math.exp(OFFSET_STEP * z[1]), lo, hi))
            query(hm)
            used += 1
        return best, best_err, best_hm[:, 1] * budget_m
