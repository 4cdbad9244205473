"""Attack ``drift``: the whole scan translated rigidly by at most lambda, its heading and length
searched with queries: the largest error a motion-prior gate lets through (queries only, any
target).

Beyond the paper. A rigid translation ``v`` of the scan (sensor frame) is explained exactly by a
pose moved by ``-R v``: the scan still lies on the map, so the checks that look at the registration
alone (residuals, inlier share, the Hessian's conditioning) see a clean registration, and only a
motion prior (an odometry prediction, :mod:`icpbench.monitors.odometry`) can notice it. Against
such a gate of radius ``r`` around a prediction ``t_pred`` (unknown to the attacker, drawn around the
true pose), the error that passes is largest along the direction of ``t_pred - t_gt`` and is then
``|t_pred - t_gt| + r`` at most: the attack has to find that direction and the gate's edge. It is the
spoofing pattern inertial gates are designed against (a slow pull-off; cf. Tippenhauer et al., "On
the requirements for successful GPS spoofing attacks", CCS 2011), written for one registration.

Schedule per scan (``queries`` candidates; the oracle's error is NaN where the pose diverged or,
through a :class:`~icpbench.monitors.oracle.MonitoredOracle`, where a monitor fired):

1. ``directions`` headings (a random rotation of an even fan, map frame x-y) at length lambda;
2. a best-first bisection on the length of the headings whose lambda candidate was NaN: each step
   halves the interval ``[lo, hi]`` (``lo``: longest length seen to pass, 0 at first, the clean scan;
   ``hi``: shortest length seen to fail) of the heading with the largest ``hi`` (ties: the one
   halved least often, then the largest ``lo``; so every heading is tried at lambda / 2 before any
   at 3 lambda / 4), until every interval is shorter than lambda / :data:`RESOLUTION`;
3. the remaining queries: random steps of the heading (normal, a quarter of the fan's spacing) from
   the best candidate at its length.

Without monitors every heading passes at lambda and the attack is ``uniform`` with its heading
searched. The scan with the largest finite error is returned. Every point moves by the same vector
of length <= lambda, so the displacement audit shows 0% over lambda.

Frames: the heading and length in the map frame at the true pose, the scan moved by
``R_gt^T e`` in the sensor frame. Units: metres, radians.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, SampleGenerators
from icpbench.attacks.sector_adaptive import score
from icpbench.core.errors import InputError
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

#: The bisection stops once a heading's interval is shorter than lambda / RESOLUTION.
RESOLUTION = 32


class DriftAttack(Attack):
    """Rigid translation of the scan, heading and length (<= lambda) searched with queries
    (module docstring).

    Args:
        queries: candidates per scan, >= 1.
        directions: headings of the first sweep, >= 1.
    """

    name: ClassVar[str] = "drift"
    cost_class: ClassVar[int] = 2
    description: ClassVar[str] = (
        "Translate the whole scan rigidly by at most lambda, heading and length searched with "
        "queries: the largest error a motion-prior gate lets through (beyond the paper)"
    )
    needs_oracle: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {"queries": Range(1, 10_000_000),
                                                "directions": Range(1, 100_000)}

    def __init__(self, *, strict: bool = False, queries: int = 24, directions: int = 8,
                 **params: Any) -> None:
        for nm, v in (("queries", queries), ("directions", directions)):
            if isinstance(v, bool) or int(v) != v or int(v) < 1:
                raise InputError(f"{self.name} {nm} must be an integer >= 1, got {v!r}")
        self.queries, self.directions = int(queries), int(directions)
        super().__init__(strict=strict, queries=self.queries, directions=self.directions, **params)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: SampleGenerators, oracle: QueryOracle
                 ) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        adv, err, heading, length = self.drift(batch, budget_m, oracle, generator)
        extra = {"drift_err": err, "drift_heading": heading, "drift_m": length}
        return torch.as_tensor(adv, dtype=batch.scans.dtype), extra

    def drift(self, batch: Batch, budget_m: float, oracle: QueryOracle,
              generator: SampleGenerators
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Run the schedule. Returns the best scans (B, N, 3) float64 (sensor frame), their errors
        (B,) in metres (NaN where every candidate failed), and the heading (B,) in radians (map
        frame) and length (B,) in metres of their translation (NaN where none passed)."""
        clean = batch.scans.detach().to(torch.float64).numpy()
        B, H = clean.shape[0], self.directions
        R = batch.T_gt.detach().to(torch.float64).numpy()[:, :3, :3]
        spacing = 2 * math.pi / H
        heads = generator.rand(dtype=torch.float64).numpy()[:, None] + np.arange(H) * spacing
        lo = np.zeros((B, H))  # longest length seen to pass per heading (0: the clean scan)
        hi = np.full((B, H), np.inf)  # shortest length seen to fail (inf: none yet)
        halved = np.zeros((B, H))  # bisection steps per heading
        tol = budget_m / RESOLUTION
        best = clean.copy()
        best_err = np.full(B, np.nan)
        best_hm = np.full((B, 2), np.nan)  # (heading, length) of the best

        def candidate(b: int, used: int) -> tuple[float, float, int]:
            """Scan b's next (heading, length) and the heading's index (-1: a random step)."""
            if used < H:
                return heads[b, used], budget_m, used
            open_ = np.isfinite(hi[b]) & (hi[b] - lo[b] > tol)
            if open_.any():
                order = np.lexsort((-lo[b][open_], halved[b][open_], -hi[b][open_]))
                k = int(np.flatnonzero(open_)[order[0]])
                return heads[b, k], 0.5 * (lo[b, k] + hi[b, k]), k
            h0, m0 = best_hm[b] if np.isfinite(best_hm[b, 0]) else (heads[b, 0], tol)
            z = float(torch.randn(1, generator=generator[b], dtype=torch.float64))
            return h0 + 0.25 * spacing * z, m0, -1

        for used in range(self.queries):
            picks = [candidate(b, used) for b in range(B)]
            hm = np.array([(h, m) for h, m, _ in picks])
            e = hm[:, 1:] * np.stack([np.cos(hm[:, 0]), np.sin(hm[:, 0]),
                                      np.zeros(B)], axis=1)  # (B, 3) map frame
            adv = clean + np.einsum("bji,bj->bi", R, e)[:, None, :]  # R^T e per scan
            err = oracle.errors(adv)
            for b, (_, m, k) in enumerate(picks):
                if k >= 0:
                    halved[b, k] += used >= H
                    if np.isfinite(err[b]):
                        lo[b, k] = max(lo[b, k], m)
                    else:
                        hi[b, k] = min(hi[b, k], m)
            better = score(err) > score(best_err)
            best[better], best_err[better], best_hm[better] = adv[better], err[better], hm[better]
        return best, best_err, best_hm[:, 0], best_hm[:, 1]
