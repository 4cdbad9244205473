"""The "worst of all attacks" row: per scan, the largest error any attack of a run found.

RobustBench reports, per entry, the lowest robust figure any attack found (Croce et al.,
"RobustBench", NeurIPS 2021 datasets and benchmarks track); the ICP version is the per-scan maximum
of the pose error over every attack of a run. A run of several attacks gets this row in its Table 1
(``icpbench table``), with which attack won each scan, so that no table shows attacks side by side
and leaves the reader to take the maximum.

Rules: for each (sample, target, budget, seed) the row of the largest finite ``trans_err_xy`` among
the attacks other than ``none`` is taken; a row that moved points beyond lambda
(``frac_over_budget`` > 0) does not count (the budget is part of the question), nor does a row
without a finite error; ties go to the attack named first in the run.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

#: The attack name of the synthesised rows.
WORST = "worst"
#: Its display name in tables.
WORST_DISPLAY = "Worst of all attacks"
#: Attacks that never count towards the worst case.
NOT_ATTACKS = frozenset({"none", WORST})


def attacks_of(df: pd.DataFrame) -> list[str]:
    """The run's attacks that count towards the worst case, in the order they first appear."""
    return [a for a in dict.fromkeys(df["attack"]) if a not in NOT_ATTACKS]


def worst_rows(df: pd.DataFrame, metric: str = "trans_err_xy") -> pd.DataFrame:
    """One row per (sample_id, target, budget, seed): the counting row with the largest
    ``metric``, its ``attack`` renamed :data:`WORST` and the winner's name in ``winner``. Empty
    when the run has fewer than two attacks (then there is nothing to take the maximum over)."""
    attacks = attacks_of(df)
    if len(attacks) < 2:
        return df.iloc[:0].assign(winner=pd.Series(dtype=object))
    rank = {a: i for i, a in enumerate(attacks)}
    d = df[df["attack"].isin(attacks)].copy()
    err = pd.to_numeric(d[metric], errors="coerce").to_numpy(dtype=float)
    over = pd.to_numeric(d.get("frac_over_budget", pd.Series(0.0, index=d.index)),
                         errors="coerce").fillna(0.0).to_numpy(dtype=float) > 0
    d["_score"] = np.where(np.isfinite(err) & ~over, err, -np.inf)
    d["_rank"] = d["attack"].map(rank)
    d = d.sort_values(["_score", "_rank"], ascending=[False, True], kind="stable")
    best = d.drop_duplicates(["sample_id", "target", "budget", "seed"], keep="first")
    best = best[np.isfinite(best["_score"])]
    return best.assign(winner=best["attack"], attack=WORST).drop(columns=["_score", "_rank"])


def winner_counts(worst: pd.DataFrame) -> pd.DataFrame:
    """Scans won per attack and budget (rows: attacks in descending total; columns: budgets)."""
    if worst.empty:
        return pd.DataFrame()
    counts = worst.groupby(["winner", "budget"]).size().unstack("budget", fill_value=0)
    return counts.loc[counts.sum(axis=1).sort_values(ascending=False, kind="stable").index]


def winner_note(worst: pd.DataFrame) -> str:
    """One line per budget: which attack found the worst case on how many scans."""
    counts = winner_counts(worst)
    if counts.empty:
        return ""
    parts = []
    for b in counts.columns:
        won = counts[b][counts[b] > 0]
        parts.append(f"λ={b:g}: " + ", ".join(f"{a} {int(n)}" for a, n in won.items()))
    return f"{WORST_DISPLAY}: per scan the largest error over every attack; won by " + \
        "; ".join(parts) + " (scans)."
