"""Compare attack runs with a ``normal`` run on the same scans: one line per run and budget.

Each RUN folder holds a ``results.csv`` of ``icpbench run`` whose non-``normal`` attack is the
candidate; the ``normal`` rows come from ``--normal-run`` (default: the first RUN), paired on
``sample_id``, ``target``, ``budget`` and ``seed``. Printed per run and budget: converged runs of
the candidate, converged pairs, "% larger than normal" over converged pairs (the paper's
statistic) and over all runs (:func:`icpbench.harness.report.pct_reference_larger`, as in
Table 1), mean ``trans_err_xy`` of converged and of all runs (metres), and attack seconds per scan.

    python scripts/compare_to_normal.py results/lidar-sim-validation/lambda5/*/
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from icpbench.harness.report import pct_reference_larger

METRIC = "trans_err_xy"


def compare(run: Path, normal: pd.DataFrame) -> list[str]:
    """Lines of the comparison for one run folder (see the module docstring)."""
    d = pd.read_csv(run / "results.csv")
    cand = d[d["attack"] != "normal"]
    if cand["attack"].nunique() != 1:
        raise SystemExit(f"{run}: need exactly one attack besides normal, got "
                         f"{sorted(cand['attack'].unique())}")
    name = cand["attack"].iloc[0]
    lines = []
    for lam, c in cand.groupby("budget"):
        n = normal[normal["budget"] == lam]
        c = c[c["sample_id"].isin(n["sample_id"])]
        if c.empty:
            raise SystemExit(f"{run}: no normal rows for budget {lam}")
        both = pd.concat([c, n])
        pct, pairs = pct_reference_larger(both, "normal", name, METRIC)
        pct_all, _ = pct_reference_larger(both, "normal", name, METRIC, converged_only=False)
        conv = c["converged"].astype(bool)
        lines.append(
            f"{run.name:24s} λ={lam:g} {name}: converged {int(conv.sum())}/{len(c)}, "
            f"pairs {pairs}, % > normal {pct if pct is not None else float('nan'):.1f} "
            f"(all runs {pct_all:.1f}), mean converged {c[METRIC][conv].mean():.2f} m, "
            f"mean all {c[METRIC].mean():.2f} m, {c['attack_time_s'].mean():.2f} s/scan")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders with results.csv")
    ap.add_argument("--normal-run", type=Path, default=None,
                    help="folder whose normal rows are the reference (default: first run)")
    args = ap.parse_args()
    src = args.normal_run or args.runs[0]
    d = pd.read_csv(src / "results.csv")
    normal = d[d["attack"] == "normal"]
    if normal.empty:
        raise SystemExit(f"{src}: no normal rows")
    for run in args.runs:
        print("\n".join(compare(run, normal)))


if __name__ == "__main__":
    main()
