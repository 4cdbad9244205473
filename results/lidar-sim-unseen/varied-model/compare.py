"""Side-by-side Table 1 numbers of two generators on the same unseen-town scans (issue 16).

Usage (from the repository root): ``python results/lidar-sim-unseen/varied-model/compare.py``
prints the markdown table in ``results/lidar-sim-unseen/README.md``, computed from the two results
folders (``shipped``: the session-5 sensitivity-prior model, shipped when the varied model was
trained; ``varied``) with :mod:`icpbench.harness.report` (nothing typed by hand): per budget λ [m], "% Ours is
Larger" vs normal, uniform and sector (converged pairs, as in Table 1; in brackets every pair with
a finite error, non-converged runs at their final error), Ours' mean translational error (x-y, m,
converged runs) and its converged share; then, scan by scan (final errors, converged or not), on how
many scans the varied model's error exceeds the shipped model's, with a two-sided sign test.
"""

from __future__ import annotations

import sys
from pathlib import Path

from scipy.stats import binomtest

from icpbench.harness.report import pct_reference_larger, table1_cells
from icpbench.harness.results import load_results

HERE = Path(__file__).resolve().parent
RUNS = {"shipped": HERE.parent / "session5-model" / "run", "varied": HERE / "run"}
VS = ("normal", "uniform", "sector")


def rows(run: Path) -> dict[float, dict[str, str]]:
    """Per budget: the formatted cells of one run."""
    df = load_results(run)
    cells = table1_cells(df, "generator")
    out = {}
    for b in sorted(df["budget"].unique()):
        b = float(b)
        d = df[df["budget"] == b]
        r = {}
        for a in VS:
            c = cells[(a, b)]
            pct_all, _ = pct_reference_larger(d, a, "generator", converged_only=False)
            r[a] = f"{c.pct_ref_larger:.1f} ({pct_all:.1f})"
        g = cells[("generator", b)]
        r["mean"] = f"{g.mean:.2f}"
        r["conv"] = f"{g.n}/{g.n + g.dropped}"
        out[b] = r
    return out


def head_to_head() -> dict[float, str]:
    """Per budget: scans where the varied generator's final error exceeds the shipped one's."""
    gen = {k: load_results(v).query("attack == 'generator'") for k, v in RUNS.items()}
    m = gen["shipped"].merge(gen["varied"], on=["sample_id", "target", "budget", "seed"],
                             suffixes=("_s", "_v"))
    out = {}
    for b, g in m.groupby("budget"):
        k = int((g["trans_err_xy_v"] > g["trans_err_xy_s"]).sum())
        out[float(b)] = f"{k}/{len(g)} (p = {binomtest(k, len(g)).pvalue:.2g})"
    return out


def main() -> None:
    runs = {k: rows(v) for k, v in RUNS.items()}
    h2h = head_to_head()
    cols = [f"vs {a} [%]" for a in VS] + ["Ours mean [m]", "Ours converged"]
    keys = [*VS, "mean", "conv"]
    head = ("| λ [m] | " + " | ".join(f"{c} shipped / varied" for c in cols)
            + " | varied > shipped, scans |")
    lines = [head, "|" + "---|" * (len(cols) + 2)]
    for b in runs["shipped"]:
        cells = [f"{runs['shipped'][b][k]} / {runs['varied'][b][k]}" for k in keys]
        lines.append(f"| {b:g} | " + " | ".join(cells) + f" | {h2h[b]} |")
    sys.stdout.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
