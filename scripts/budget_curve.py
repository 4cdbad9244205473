"""The worst case against the search budget, from large-budget ensemble runs.

Reads one or more ``icpbench run`` folders whose ``ensemble`` ran with a search budget above 20
queries (it then records its error after 20, 50, 100, ... search queries) and writes, into the
parent folder of the first: ``budget_curve.csv`` (run folder, target, budget, queries, scans, mean, median,
uniform, over_uniform), ``budget_curve.md`` and ``budget_curve.png``.

Usage (from the repository root)::

    python scripts/budget_curve.py results/large-budget/p2point [more run folders]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from icpbench.analysis.budget_curve import budget_curve
from icpbench.harness.outputs import save_figure, write_csv, write_file
from icpbench.harness.results import load_results, read_manifest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="icpbench run folders")
    args = ap.parse_args()
    curves = []
    for run in args.runs:
        manifest = read_manifest(run) or {}
        q = manifest.get("attacks", {}).get("ensemble", {}).get("queries")
        if q is None:
            raise SystemExit(f"{run}: no ensemble settings in its manifest.json")
        c = budget_curve(load_results(run), int(q))
        c.insert(0, "run", run.name)  # the folder names the variant (e.g. a target's settings)
        curves.append(c)
    curve = pd.concat(curves, ignore_index=True)
    out = args.runs[0].parent
    write_csv(out / "budget_curve.csv", curve, index=False)
    lines = ["# Worst case against the search budget", "",
             "Mean `trans_err_xy` [m] of the `ensemble` had its search stopped after q queries "
             "(q = 0: the best of the members before the search: uniform, normal, sector, "
             "sector-adaptive, PGD), over the scans of each run; `x uniform` divides by the mean "
             "of its uniform member on the same scans. Written by `scripts/budget_curve.py` from "
             + ", ".join(f"`{r}`" for r in args.runs) + ".", ""]
    for (run, target, lam), g in curve.groupby(["run", "target", "budget"], sort=False):
        lines += [f"## {run} (target `{target}`), λ = {lam:g} m ({int(g.scans.max())} scans)", "",
                  "| search queries | mean [m] | median [m] | x uniform |", "|---|---|---|---|"]
        lines += [f"| {int(r.queries)} | {r['mean']:.2f} | {r['median']:.2f} | {r.over_uniform:.2f} |"
                  for _, r in g.iterrows()]
        lines.append("")
    write_file(out / "budget_curve.md", "\n".join(lines))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for (run, lam), g in curve.groupby(["run", "budget"], sort=False):
        g = g[g.queries > 0]
        label = f"{run}, λ = {lam:g} m ({int(g.scans.max())} scans)"
        ax.plot(g.queries, g.over_uniform, marker="o", label=label)
    ax.axhline(2.0, color="grey", ls="--", lw=1, label="2x uniform")
    ax.set_xscale("log")
    ax.set_xlabel("search queries per scan")
    ax.set_ylabel("ensemble mean error / uniform's")
    ax.set_title("Worst case against the query budget")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "budget_curve.png", dpi=120)
    print(f"wrote {out / 'budget_curve.md'}, .csv, .png")


if __name__ == "__main__":
    main()
