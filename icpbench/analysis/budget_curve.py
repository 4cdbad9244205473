"""How an ensemble's worst case grows with its query budget, from one large-budget run.

The ``ensemble`` attack records, with a search budget above 20 queries, its error had the search
stopped after q queries (``extra.search_best_at_<q>``, q in
:data:`~icpbench.attacks.search.TRACE_QUERIES`), besides the error of its uniform member
(``extra.err_uniform``), of the fixed members before the search and its final error. This module
turns the rows of such a run into one curve per target: mean error (metres) against search queries.
"""

from __future__ import annotations

import re

import numpy as np
import pandas as pd

from icpbench.attacks.ensemble import MEMBERS, column
from icpbench.core.errors import InputError

_TRACE = re.compile(r"^extra\.search_best_at_(\d+)$")


def budget_curve(rows: pd.DataFrame, search_queries: int) -> pd.DataFrame:
    """Mean worst-case error per target and search budget.

    Args:
        rows: a results table (:func:`icpbench.harness.results.load_results`) holding ``ensemble``
            rows with search traces.
        search_queries: the ensemble's search budget (its ``queries`` setting): the final point.

    Returns:
        One row per (target, budget, queries): ``queries`` = 0 is the ensemble before its search
        (the best of the other members), then every traced count and the final budget; columns
        ``scans``, ``mean`` and ``median`` error (metres, NaN-free scans only), ``uniform`` (mean
        error of the uniform member on the same scans) and ``over_uniform`` (their ratio).

    Raises:
        InputError: no ensemble rows, or none with a search trace.
    """
    e = rows[rows.attack == "ensemble"]
    if e.empty:
        raise InputError("no ensemble rows to trace")
    traced = sorted((int(m.group(1)), c) for c in e.columns if (m := _TRACE.match(c)))
    if not traced:
        raise InputError("the ensemble rows hold no search trace (run it with "
                         "--attack-param ensemble.queries=N, N > 20)")
    # the members that run before the search (the search runs last); a member that did not run
    # has no column
    fixed = [f"extra.{column(m)}" for m in MEMBERS[:MEMBERS.index("search")]]
    searched = f"extra.{column('search')}"
    out = []
    for (target, budget), g in e.groupby(["target", "budget"], sort=True):
        points = [(0, g[[c for c in fixed if c in g]].max(axis=1, skipna=True))]
        points += [(q, g[c]) for q, c in traced]
        points.append((int(search_queries),
                       g[[c for c in (*fixed, searched) if c in g]].max(axis=1, skipna=True)))
        uni = g[f"extra.{column('uniform')}"]
        for q, err in points:
            ok = np.isfinite(err.to_numpy(dtype=float))
            # the means of no scan are NaN, as pandas gives them
            mean, uniform = float(err[ok].mean()), float(uni[ok].mean())
            out.append({"target": target, "budget": float(budget), "queries": q,
                        "scans": int(ok.sum()), "mean": mean, "median": float(err[ok].median()),
                        "uniform": uniform, "over_uniform": mean / uniform if ok.any() else np.nan})
    return pd.DataFrame(out)
