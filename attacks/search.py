"""Attack ``search``: score-based random search over a low-dimensional family of corruptions,
with a query budget.

Beyond the paper; the ICP version of Square Attack (Andriushchenko, Croce, Flammarion and Hein,
"Square Attack: a query-efficient black-box adversarial attack via random search", ECCV 2020): it
needs only the evaluated target's output pose (a :class:`~icpbench.targets.oracle.QueryOracle`), so
it runs against any ICP, and gradient masking cannot hide a weakness from it.

The family. The scan is cut into regions: ``wedges`` azimuth wedges of the sensor frame times two
range rings (nearer and farther than the scan's median range). Region r carries a normal
coefficient ``s_r`` in [-1, 1] and a vector ``v_r`` with ``||v_r|| <= 1``; point i of region r is
displaced by

    d_i = P_lambda( d0_i + lambda (s_r n_i + v_r) ),

where ``n_i`` is the unit map normal of its correspondence at the true pose (sensor frame; zero
without one), ``d0`` the start's displacement and ``P_lambda`` the projection onto the point's
lambda-ball. ``s_r`` moves a region along its surfaces' normals (what a point-to-plane cost feels),
``v_r`` moves it rigidly (what a point-to-point cost feels, and what can carry a region out of the
correspondence gate, deleting its constraints).

The search. From the start (the clean scan translated by lambda in a random horizontal direction,
or a given adversarial scan), each query redraws the parameters of a random subset of regions:
with probability 1/2 a pure normal move (``s_r = +-1``, ``v_r = 0``), else a pure rigid move
(``v_r`` a random unit vector, its vertical part shrunk by 0.3). The candidate is kept when the
target's error grows. The subset shrinks as the budget is spent (Square Attack's schedule: a share
``p`` of the regions, halved after 10, 25, 50 and 75% of the queries). One query per scan and step,
every scan of the batch in one call. With a ``patience``, a scan whose error has not grown in that
many queries in a row stops (its remaining queries are not spent): the search spends queries where
it still climbs.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, SampleGenerators
from icpbench.attacks.sector_adaptive import score
from icpbench.core import sector_math
from icpbench.core.cost_sensitivity import cost_of
from icpbench.core.errors import InputError
from icpbench.core.projection import clip_displacements
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle

#: Shares of the query budget after which the share of redrawn regions halves (Square Attack).
_HALVINGS = (0.1, 0.25, 0.5, 0.75)
#: Query counts at which a search records its best errors so far (``trace``): how the worst case
#: grows with the budget, from one run.
TRACE_QUERIES = (20, 50, 100, 200, 500, 1000, 2000, 5000, 10_000, 20_000, 50_000)
#: Scale of the vertical part of a rigid move (horizontal moves shift a horizontal estimate more).
_VERTICAL = 0.3


class QuerySearchAttack(Attack):
    """Random search over per-region normal and rigid displacements (module docstring).

    Args:
        queries: queries per scan (the start's evaluation included), >= 1.
        wedges: azimuth wedges (regions = 2 x wedges: two range rings).
        p_init: initial share of the regions redrawn per query, in (0, 1].
        patience: a scan stops after this many queries in a row without a larger error
            (0: never; every scan spends the whole budget).
    """

    name: ClassVar[str] = "search"
    cost_class: ClassVar[int] = 2
    description: ClassVar[str] = (
        "Score-based random search over per-region normal/rigid displacements with a query budget; "
        "queries only, any target (beyond the paper)"
    )
    needs_oracle: ClassVar[bool] = True
    param_ranges: ClassVar[dict[str, Range]] = {
        "queries": Range(1, 10_000_000), "wedges": Range(1, 100_000),
        "p_init": Range(0.0, 1.0, lo_open=True), "patience": Range(0, 10_000_000)}

    def __init__(self, *, strict: bool = False, queries: int = 100, wedges: int = 16,
                 p_init: float = 0.5, patience: int = 0, **params: Any) -> None:
        for nm, v, lo in (("queries", queries, 1), ("wedges", wedges, 1),
                          ("patience", patience, 0)):
            if isinstance(v, bool) or int(v) != v or int(v) < lo:
                raise InputError(f"{self.name} {nm} must be an integer >= {lo}, got {v!r}")
        if not 0 < float(p_init) <= 1:
            raise InputError(f"{self.name} p_init must be in (0, 1], got {p_init}")
        self.queries, self.wedges, self.p_init = int(queries), int(wedges), float(p_init)
        self.patience = int(patience)
        if self.patience:
            params["patience"] = self.patience
        super().__init__(strict=strict, queries=self.queries, wedges=self.wedges,
                         p_init=self.p_init, **params)

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate: Target | None,
                 generator: SampleGenerators, oracle: QueryOracle
                 ) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        trace: dict[int, np.ndarray] = {}
        adv, err = self.search(batch, budget_m, oracle, generator, trace=trace)
        extra = {"search_err": err, **{f"search_err_at_{q}": e for q, e in trace.items()}}
        return torch.as_tensor(adv, dtype=batch.scans.dtype), extra

    def search(self, batch: Batch, budget_m: float, oracle: QueryOracle,
               generator: SampleGenerators, start: np.ndarray | None = None,
               start_err: np.ndarray | None = None, queries: int | None = None,
               trace: dict[int, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Search from ``start`` (B, N, 3) adversarial scans within lambda (default: a random
        horizontal translation by lambda) whose errors ``start_err`` (B,) are known (else the
        first query measures them). Returns the best scans (B, N, 3) float64 and their errors on
        the target (B,) in metres (NaN where every query diverged). ``trace``, if given, receives
        the best errors (B,) after each count of :data:`TRACE_QUERIES` queries below the budget."""
        budget_q = self.queries if queries is None else int(queries)
        clean = batch.scans.detach().to(torch.float64).numpy()
        B, N, _ = clean.shape
        normals, region = self._family(batch, clean, oracle)
        R = 2 * self.wedges
        if start is None:
            ang = generator.rand(dtype=torch.float64).numpy() * 2 * math.pi
            d_map = np.stack([np.cos(ang), np.sin(ang), np.zeros(B)], -1)
            R_init = batch.T_init[:, :3, :3].to(torch.float64).numpy()
            u = np.einsum("bji,bj->bi", R_init, d_map)  # R_init^T d: sensor frame
            d0 = np.broadcast_to(budget_m * u[:, None, :], clean.shape).copy()
            start_err = None
        else:
            d0 = np.asarray(start, dtype=np.float64) - clean
        s = np.zeros((B, R))
        v = np.zeros((B, R, 3))
        best_d = d0.copy()
        used = 0
        if start_err is None:
            best_err = oracle.errors(clean + d0)
            used = 1
        else:
            best_err = np.asarray(start_err, dtype=np.float64).copy()
        stale = np.zeros(B, dtype=np.int64)  # queries since each scan's error last grew
        for q in range(used, budget_q):
            live = np.flatnonzero(stale < self.patience) if self.patience else np.arange(B)
            if live.size == 0:  # every scan stopped: the best errors stand for the rest
                if trace is not None:
                    trace.update({t: best_err.copy() for t in TRACE_QUERIES if q < t < budget_q})
                break
            frac = q / max(budget_q, 1)
            p = self.p_init * 0.5 ** sum(frac >= h for h in _HALVINGS)
            m = max(1, int(round(p * R)))
            cand_s, cand_v = s.copy(), v.copy()
            for b in range(B):
                g = generator[b]
                pick = torch.randperm(R, generator=g)[:m].numpy()
                mode = torch.rand(m, generator=g).numpy() < 0.5
                sign = np.where(torch.rand(m, generator=g).numpy() < 0.5, -1.0, 1.0)
                dirs = torch.randn(m, 3, generator=g, dtype=torch.float64).numpy()
                dirs[:, 2] *= _VERTICAL
                dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
                cand_s[b, pick] = np.where(mode, sign, 0.0)
                cand_v[b, pick] = np.where(mode[:, None], 0.0, dirs)
            d = self._displace(d0, normals, region, cand_s, cand_v, budget_m)
            err = np.full(B, np.nan)
            err[live] = oracle.errors((clean + d)[live], live if live.size < B else None)
            better = score(err) > score(best_err)
            better[np.setdiff1d(np.arange(B), live)] = False
            stale = np.where(better, 0, stale + 1)
            s[better], v[better] = cand_s[better], cand_v[better]
            best_d[better], best_err[better] = d[better], err[better]
            if trace is not None and q + 1 in TRACE_QUERIES and q + 1 < budget_q:
                trace[q + 1] = best_err.copy()
        return clean + best_d, best_err

    def _family(self, batch: Batch, clean: np.ndarray, oracle: QueryOracle
                ) -> tuple[np.ndarray, np.ndarray]:
        """Unit map normals (B, N, 3) of each point's correspondence at the true pose, in the sensor
        frame (zero without one), and each point's region (B, N) in [0, 2 wedges)."""
        B, N, _ = clean.shape
        d_max = cost_of(oracle.target).d_max
        T_gt = batch.T_gt.to(torch.float64).numpy()
        normals = np.zeros_like(clean)
        for b in range(B):
            if batch.maps[b].normals is None:
                continue
            a = sector_math.associate(clean[b], T_gt[b], batch.maps[b], d_max)
            normals[b] = a.normals_map @ T_gt[b][:3, :3]  # R^T n per row (zeros stay zero)
        az = np.arctan2(clean[..., 1], clean[..., 0]) % (2 * math.pi)
        wedge = np.minimum((az / (2 * math.pi) * self.wedges).astype(np.int64), self.wedges - 1)
        rng = np.linalg.norm(clean, axis=-1)
        far = rng > np.median(rng, axis=1, keepdims=True)
        return normals, wedge + self.wedges * far

    @staticmethod
    def _displace(d0: np.ndarray, normals: np.ndarray, region: np.ndarray, s: np.ndarray,
                  v: np.ndarray, budget_m: float) -> np.ndarray:
        """Displacements (B, N, 3) of the family for parameters s (B, R), v (B, R, 3)."""
        sr = np.take_along_axis(s, region, axis=1)  # (B, N)
        vr = np.take_along_axis(v, region[..., None], axis=1)  # (B, N, 3)
        d = d0 + budget_m * (sr[..., None] * normals + vr)
        return clip_displacements(d, budget_m)
