"""Reports generated from results only: Table 1 and the transfer table.

Table 1 (Zhang et al. 2025): rows = attacks, and per budget two columns, "Trans Pose Error [m]"
(mean ± std of ``trans_err_xy`` over converged samples) and "% Ours is Larger" (the share of paired
samples where the reference attack's error is larger than the row attack's). Pairs share
(sample, target, budget, seed) and are kept only when both rows converged; a tie counts as "not
larger". Non-converged and failed rows are excluded and counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
from tabulate import tabulate

from icpbench.core.errors import InputError

Format = Literal["md", "latex", "csv"]
PAIR_KEYS = ["sample_id", "target", "budget", "seed"]

#: Display names and the paper's row order; unknown attacks go before the reference.
DISPLAY = {"none": "Original", "uniform": "Uniform", "normal": "Normal",
           "sector": "Sector (analytic)", "sector-iter": "Sector, iterated",
           "pgd": "PGD (oracle)", "generator": "Ours",
           "generator-refine": "Ours + 3 steps"}
ORDER = ["none", "uniform", "normal", "sector", "sector-iter", "pgd"]


def attack_order(attacks: list[str], reference: str | None) -> list[str]:
    """Paper order: Original, Uniform, Normal, others (alphabetical), ..., reference last."""
    known = [a for a in ORDER if a in attacks and a != reference]
    other = sorted(a for a in attacks if a not in ORDER and a != reference)
    tail = [reference] if reference in attacks else []
    return known + other + tail


@dataclass
class Cell:
    """One (attack, budget) cell of Table 1."""

    mean: float
    std: float
    n: int
    dropped: int
    pct_ref_larger: float | None
    n_pairs: int


def pct_reference_larger(df: pd.DataFrame, attack: str, reference: str,
                         metric: str = "trans_err_xy", *, converged_only: bool = True
                         ) -> tuple[float | None, int]:
    """Share (percent) of pairs where ``reference``'s error exceeds ``attack``'s, and the pair count.

    Pairs: same (sample_id, target, budget, seed), both rows converged (``converged_only=False``:
    every row with a finite error, non-converged ones at their final error). Ties are not "larger".
    Returns (None, 0) when there is no pair.
    """
    ok = df[df["converged"]] if converged_only else df[np.isfinite(df[metric].astype(float))]
    a = ok[ok["attack"] == attack][PAIR_KEYS + [metric]]
    r = ok[ok["attack"] == reference][PAIR_KEYS + [metric]]
    m = a.merge(r, on=PAIR_KEYS, suffixes=("_a", "_r"))
    if m.empty:
        return None, 0
    return float(100.0 * (m[f"{metric}_r"] > m[f"{metric}_a"]).mean()), int(len(m))


def table1_cells(df: pd.DataFrame, reference: str = "generator", target: str | None = None,
                 metric: str = "trans_err_xy") -> dict[tuple[str, float], Cell]:
    """Compute every cell of Table 1 for one target (default: the only target in ``df``)."""
    if df.empty:
        raise InputError("no result rows to tabulate")
    targets = sorted(df["target"].unique())
    if target is None:
        if len(targets) > 1:
            raise InputError(f"results hold several targets {targets}; choose one with --target")
        target = targets[0]
    elif target not in targets:
        raise InputError(f"target {target!r} not in results; available: {', '.join(targets)}")
    d = df[df["target"] == target]
    cells = {}
    for (attack, budget), g in d.groupby(["attack", "budget"]):
        ok = g[g["converged"]][metric].to_numpy(dtype=float)
        pct, n_pairs = (None, 0)
        if reference in set(d["attack"]) and attack != reference:
            pct, n_pairs = pct_reference_larger(d[d["budget"] == budget], attack, reference, metric)
        cells[(attack, float(budget))] = Cell(
            mean=float(ok.mean()) if ok.size else float("nan"),
            std=float(ok.std(ddof=0)) if ok.size else float("nan"),
            n=int(ok.size), dropped=int(len(g) - ok.size), pct_ref_larger=pct, n_pairs=n_pairs)
    return cells


def auto_decimals(budgets) -> int:
    """Decimals that resolve the smallest budget to ~1%: 2 for metres-scale budgets (as in the
    paper), 4 for the normalised objects budgets 0.02/0.05."""
    smallest = float(np.min(np.asarray(list(budgets), dtype=float)))
    return 2 if smallest >= 1.0 else 2 + int(np.ceil(-np.log10(smallest)))


def table1_frame(df: pd.DataFrame, reference: str = "generator", target: str | None = None,
                 metric: str = "trans_err_xy", decimals: int | None = None) -> pd.DataFrame:
    """Table 1 as a DataFrame of strings (rows = attacks, two columns per budget)."""
    cells = table1_cells(df, reference, target, metric)
    if decimals is None:
        decimals = auto_decimals(b for _, b in cells)
    attacks = attack_order(sorted({a for a, _ in cells}), reference)
    budgets = sorted({b for _, b in cells})
    has_ref = reference in attacks
    unit = "[m]" if metric.startswith("trans") else "[rad]"
    rows = []
    for a in attacks:
        row = {"Method": DISPLAY.get(a, a)}
        for b in budgets:
            c = cells.get((a, b))
            lam = f"λ={b:g}"
            if c is None:
                row[f"{lam} Trans Pose Error {unit}"] = "n/a"
                row[f"{lam} % Ours is Larger"] = "n/a"
                continue
            row[f"{lam} Trans Pose Error {unit}"] = (f"{c.mean:.{decimals}f} ± {c.std:.{decimals}f}"
                                                     if c.n else "n/a")
            if not has_ref:
                row[f"{lam} % Ours is Larger"] = f"({reference} not run)"
            elif a == reference:
                row[f"{lam} % Ours is Larger"] = "-"
            elif c.pct_ref_larger is None:
                row[f"{lam} % Ours is Larger"] = "no pairs"
            else:
                row[f"{lam} % Ours is Larger"] = f"{c.pct_ref_larger:.2f}%"
        rows.append(row)
    return pd.DataFrame(rows)


def table1_counts(df: pd.DataFrame, reference: str = "generator",
                  target: str | None = None) -> pd.DataFrame:
    """Per (attack, budget): converged n, dropped (not converged or failed) and pair counts."""
    cells = table1_cells(df, reference, target)
    return pd.DataFrame(
        [{"attack": a, "budget": b, "n": c.n, "dropped": c.dropped, "pairs": c.n_pairs}
         for (a, b), c in sorted(cells.items())])


def health_warnings(df: pd.DataFrame, threshold: float = 0.10) -> list[str]:
    """Warnings for cells (attack, target, budget) where more than ``threshold`` of the samples
    did not converge or failed (as AutoAttack's reliability checks flag suspicious evaluations)."""
    out = []
    for (a, t, b), g in df.groupby(["attack", "target", "budget"]):
        bad = 1.0 - g["converged"].mean()
        if bad > threshold:
            reasons = g.loc[~g["converged"], "status"].value_counts().to_dict()
            out.append(f"warning: {a} on {t} at λ={b:g}: {100 * bad:.0f}% of {len(g)} samples "
                       f"not converged/failed ({', '.join(f'{k}: {v}' for k, v in reasons.items())})")
    return out


def all_pairs_notes(df: pd.DataFrame, reference: str) -> list[str]:
    """Footer: "% Ours is Larger" over every pair with a finite error, non-converged runs counted
    at their final error (the table itself pairs converged runs only, as the paper does)."""
    if df.empty or reference not in set(df["attack"]):
        return []
    parts = []
    for a in attack_order(sorted(set(df["attack"]) - {reference}), reference):
        for b in sorted(df["budget"].unique()):
            pct, n = pct_reference_larger(df[df["budget"] == b], a, reference, converged_only=False)
            if pct is not None:
                parts.append(f"{DISPLAY.get(a, a)} λ={b:g}: {pct:.1f}% of {n}")
    if not parts:
        return []
    return [f"% {DISPLAY.get(reference, reference)} is larger incl. non-converged runs: "
            + "; ".join(parts)]


def timing_notes(df: pd.DataFrame, reference: str) -> list[str]:
    """Footer: mean attack wall time per scan (all budgets), and each attack's ratio to the
    reference's, from the ``attack_time_s`` column (one attack pass per batch, divided by B)."""
    if df.empty or "attack_time_s" not in df.columns:
        return []
    t = df.drop_duplicates(["sample_id", "attack", "budget", "seed"]).groupby("attack")[
        "attack_time_s"].mean()
    ref = t.get(reference)
    parts = []
    for a in attack_order(list(t.index), reference):
        ratio = f" ({t[a] / ref:.2g}x {DISPLAY.get(reference, reference)})" if (
            ref and ref > 0 and a != reference) else ""
        parts.append(f"{DISPLAY.get(a, a)} {t[a]:.3g}{ratio}")
    return ["attack time per scan [s]: " + "; ".join(parts)]


def displacement_notes(df: pd.DataFrame) -> list[str]:
    """One footer line per attack with a non-zero displacement: per budget the largest point
    displacement over all samples and the mean share of points moved beyond lambda (the budget
    audit of the attack base class; soft-bound attacks can exceed lambda)."""
    need = {"disp_max", "frac_over_budget"}
    if df.empty or not need <= set(df.columns):
        return []
    out = []
    for a, g in df.groupby("attack", sort=True):
        if not (g["disp_max"].fillna(0) > 0).any():
            continue
        parts = [f"λ={b:g}: max {gb['disp_max'].max():.3g}, "
                 f"{100 * gb['frac_over_budget'].mean():.2f}% of points over λ"
                 for b, gb in g.groupby("budget")]
        out.append(f"displacement audit {DISPLAY.get(a, a)}: " + "; ".join(parts))
    return out


def load_notes(df: pd.DataFrame) -> list[str]:
    """Footer: rows :func:`~icpbench.harness.results.load_results` left out (half-written lines, and the
    earlier rows of keys stored twice)."""
    out = []
    if df.attrs.get("incomplete_rows"):
        out.append(f"warning: {df.attrs['incomplete_rows']} incomplete (half-written) row(s) "
                   "ignored; re-run the same `icpbench run` command to compute them again")
    if df.attrs.get("duplicate_rows"):
        out.append(f"warning: {df.attrs['duplicate_rows']} row(s) stored twice under the same key; "
                   "the last of each was used")
    return out


#: First-line prefixes of the tables :func:`render` writes (Table 1 and the transfer table).
TABLE_HEADS = ("| Method", "| Attack", "\\begin{tabular}", "Method,", "Attack,")


def is_table_text(text: str) -> bool:
    """Whether ``text`` is a table written by ``icpbench table`` (by its first line)."""
    first = text.lstrip().split("\n", 1)[0]
    return first.startswith(TABLE_HEADS)


def check_table_destination(path: str | Path) -> None:
    """Refuse to write a table over a file of a results folder that is not a table of ours.

    Raises:
        InputError: ``path`` is a results folder's own file (``results.csv``, ``manifest.json``,
            its lock), or an existing file in a results folder that is not a table written by
            ``icpbench table``.
    """
    from icpbench.harness.results import STORE_FILES, is_results_dir

    p = Path(path)
    if str(path) == "":
        raise InputError("--out is empty ('')")
    if p.is_dir():
        raise InputError(f"--out {p} is a folder; give a file name, e.g. {p / 'table1.md'}")
    if not is_results_dir(p.parent):
        return
    if p.name in STORE_FILES:
        raise InputError(f"refusing to write a table over {p}: it is a file of the results folder "
                         f"{p.parent} (written by `icpbench run`); choose another --out")
    if p.exists():
        try:
            ours = is_table_text(p.read_text(errors="strict"))
        except (OSError, UnicodeDecodeError):
            ours = False
        if not ours:
            raise InputError(f"refusing to overwrite {p}: it is in the results folder {p.parent} "
                             "and is not a table written by `icpbench table`; choose another --out")


def render(frame: pd.DataFrame, fmt: Format = "md") -> str:
    """Render a table frame as Markdown (GitHub), LaTeX (booktabs) or CSV."""
    if fmt == "md":
        return tabulate(frame, headers="keys", tablefmt="github", showindex=False)
    if fmt == "latex":
        return tabulate(frame, headers="keys", tablefmt="latex_booktabs", showindex=False)
    if fmt == "csv":
        return frame.to_csv(index=False)
    raise InputError(f"unknown format {fmt!r}; valid: md, latex, csv")


def table1(df: pd.DataFrame, fmt: Format = "md", reference: str = "generator",
           target: str | None = None) -> str:
    """Table 1 text, with the counts and health warnings as a footer (md/latex comments)."""
    frame = table1_frame(df, reference, target)
    text = render(frame, fmt)
    if fmt == "csv":
        return text
    counts = table1_counts(df, reference, target)
    sub = df if target is None else df[df["target"] == target]
    notes = ["n converged / dropped / pairs per cell: " + "; ".join(
        f"{DISPLAY.get(r.attack, r.attack)} λ={r.budget:g}: {r.n}/{r.dropped}/{r.pairs}"
        for r in counts.itertuples())]
    notes += load_notes(df)
    notes += all_pairs_notes(sub, reference)
    notes += displacement_notes(sub)
    notes += timing_notes(sub, reference)
    notes += health_warnings(sub)
    prefix = "% " if fmt == "latex" else ""
    return text + "\n\n" + "\n".join(prefix + n for n in notes) + "\n"


def transfer_frame(df: pd.DataFrame, budget: float | None = None, metric: str = "trans_err_xy",
                   decimals: int | None = None) -> pd.DataFrame:
    """Attacks x targets table of mean ± std (converged rows) at one budget."""
    budgets = sorted(df["budget"].unique())
    if budget is None:
        budget = budgets[0]
    if not np.any(np.isclose(budgets, budget)):
        raise InputError(f"budget {budget} not in results; available: {budgets}")
    d = df[np.isclose(df["budget"], budget)]
    if decimals is None:
        decimals = auto_decimals([budget])
    attacks = attack_order(sorted(d["attack"].unique()), "generator")
    targets = list(dict.fromkeys(d["target"]))
    rows = []
    for a in attacks:
        row = {"Attack": DISPLAY.get(a, a)}
        for t in targets:
            g = d[(d["attack"] == a) & (d["target"] == t)]
            ok = g[g["converged"]][metric]
            row[t] = (f"{ok.mean():.{decimals}f} ± {ok.std(ddof=0):.{decimals}f} (n={len(ok)})"
                      if len(ok) else f"n/a (0/{len(g)} converged)")
        rows.append(row)
    return pd.DataFrame(rows)


def transfer_vs_baseline(df: pd.DataFrame, budget: float | None = None, baseline: str = "normal",
                         metric: str = "trans_err_xy") -> pd.DataFrame:
    """Attacks x targets: does an attack crafted on the surrogate still beat ``baseline`` on each
    target? Cell: difference of the means (converged rows) and the share of samples where the
    attack's error exceeds the baseline's (all pairs with a finite error, non-converged runs at
    their final error), e.g. ``+1.98 m, 95% of 20``."""
    budgets = sorted(df["budget"].unique())
    budget = budgets[0] if budget is None else budget
    d = df[np.isclose(df["budget"], budget)]
    if baseline not in set(d["attack"]):
        raise InputError(f"baseline attack {baseline!r} not in results")
    targets = list(dict.fromkeys(d["target"]))
    attacks = [a for a in attack_order(sorted(d["attack"].unique()), "generator")
               if a not in (baseline, "none")]
    rows = []
    for a in attacks:
        row = {"Attack": f"{DISPLAY.get(a, a)} vs {DISPLAY.get(baseline, baseline)}"}
        for t in targets:
            dt = d[d["target"] == t]
            ma = dt[(dt["attack"] == a) & dt["converged"]][metric].mean()
            mb = dt[(dt["attack"] == baseline) & dt["converged"]][metric].mean()
            pct, n = pct_reference_larger(dt, baseline, a, metric, converged_only=False)
            row[t] = ("n/a" if pct is None or not np.isfinite(ma - mb)
                      else f"{ma - mb:+.2f} m, {pct:.0f}% of {n}")
        rows.append(row)
    return pd.DataFrame(rows)
