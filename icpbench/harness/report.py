"""Reports generated from results only: Table 1 and the transfer table.

Table 1 (Zhang et al. 2025): rows = attacks, and per budget two columns, "Trans Pose Error [m]"
(mean ± std of ``trans_err_xy`` over converged samples) and "% Ours is Larger" (the share of paired
samples where the reference attack's error is larger than the row attack's). Pairs share
(sample, target, budget, seed) and are kept only when both rows converged; a tie counts as "not
larger". Non-converged and failed rows are excluded and counted.

Where that rule leaves too little (fewer than two converged runs for a mean ± std, no converged pair
for the share), a cell shows the same figure over all runs with a finite error instead (non-converged
runs at their final error), marked with :data:`ALL_RUNS_MARK` and explained under the table. A second
table of the same shape gives each cell's counts (runs / converged / pairs). The unit is metres, or
"units" for datasets with normalised coordinates (:data:`NORMALISED_DATASETS`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from tabulate import tabulate

from icpbench.core.errors import InputError
from icpbench.harness.outputs import write_file
from icpbench.harness.worst_case import WORST, WORST_DISPLAY, winner_note, worst_rows

Format = Literal["md", "latex", "csv"]
#: Which runs a figure covers: "converged" (the paper's rule) or "all" (every finite error).
Basis = Literal["converged", "all"]
PAIR_KEYS = ["sample_id", "target", "budget", "seed"]

#: Display names and the paper's row order; unknown attacks go before the reference.
DISPLAY = {"none": "Original", "uniform": "Uniform", "normal": "Normal",
           "sector": "Sector (analytic)", "sector-iter": "Sector, iterated",
           "pgd": "PGD (oracle)", "generator": "Ours",
           "generator-refine": "Ours + 3 steps"}
ORDER = ["none", "uniform", "normal", "sector", "sector-iter", "pgd"]
DISPLAY[WORST] = WORST_DISPLAY

#: Datasets whose coordinates are normalised (each object scaled to the unit sphere), not metres.
NORMALISED_DATASETS = frozenset({"objects", "meshes"})
#: Mark of a cell that shows the all-runs figure because the converged-runs rule leaves too little.
ALL_RUNS_MARK = "†"
#: Cell text where no run (or no pair) has a finite error.
EMPTY = "—"
#: Fewest runs for a mean ± std; with fewer the cell falls back to all runs (or shows one value).
MIN_RUNS_FOR_STD = 2


def attack_order(attacks: list[str], reference: str | None) -> list[str]:
    """Paper order: Original, Uniform, Normal, others (alphabetical), ..., reference, then the
    worst of all attacks (:mod:`icpbench.harness.worst_case`) last."""
    known = [a for a in ORDER if a in attacks and a != reference]
    other = sorted(a for a in attacks if a not in ORDER and a not in (reference, WORST))
    tail = [reference] if reference in attacks else []
    return known + other + tail + ([WORST] if WORST in attacks and reference != WORST else [])


def error_unit(metric: str = "trans_err_xy", dataset: str | None = None) -> str:
    """Unit of ``metric`` (no brackets): "rad" for rotation errors; for translation errors "units" on
    a dataset with normalised coordinates (:data:`NORMALISED_DATASETS`), else "m"."""
    if not metric.startswith("trans"):
        return "rad"
    return "units" if dataset in NORMALISED_DATASETS else "m"


def run_dataset(results_dir: str | Path) -> str | None:
    """The dataset name a results folder's ``manifest.json`` records (``config.dataset``), or None
    when there is no manifest or it names none. ``results_dir`` may also be the results CSV."""
    from icpbench.harness.results import read_manifest

    p = Path(results_dir)
    manifest = read_manifest(p if p.is_dir() else p.parent)
    name = ((manifest or {}).get("config") or {}).get("dataset")
    return name if isinstance(name, str) else None


@dataclass
class Cell:
    """One (attack, budget) cell of Table 1: the statistics of both bases.

    ``mean``, ``std`` (population std, ddof=0, in the metric's unit) and ``n`` cover the converged
    runs with a finite error (NaN, NaN, 0 when none); ``dropped`` = ``runs`` - ``n`` (not converged
    or failed). ``pct_ref_larger`` [%] and ``n_pairs``: share of pairs where the reference's error is
    larger, over pairs where both runs converged (None, 0 when there is none, and for the reference
    itself). The ``*_all`` fields and ``n_finite`` are the same over every run with a finite error,
    non-converged runs at their final error; ``runs`` counts every row of the cell.
    """

    mean: float
    std: float
    n: int
    dropped: int
    pct_ref_larger: float | None
    n_pairs: int
    runs: int = 0
    mean_all: float = float("nan")
    std_all: float = float("nan")
    n_finite: int = 0
    pct_all: float | None = None
    n_pairs_all: int = 0


@dataclass(frozen=True)
class Figure:
    """What a cell shows: ``value`` (a mean error, or a share in percent; None: nothing to show),
    ``std`` (None: a single value, no spread), ``count`` (runs or pairs behind it) and ``basis``
    ("converged": the paper's rule; "all": every run or pair with a finite error; None: nothing)."""

    value: float | None
    std: float | None
    count: int
    basis: Basis | None


def error_figure(cell: Cell) -> Figure:
    """The error a cell shows: mean ± std over converged runs when at least
    :data:`MIN_RUNS_FOR_STD` converged; else mean ± std over all runs with a finite error when there
    are that many; else the one value there is, without a std (converged basis when it converged)."""
    if cell.n >= MIN_RUNS_FOR_STD:
        return Figure(cell.mean, cell.std, cell.n, "converged")
    if cell.n_finite >= MIN_RUNS_FOR_STD:
        return Figure(cell.mean_all, cell.std_all, cell.n_finite, "all")
    if cell.n == 1:
        return Figure(cell.mean, None, 1, "converged")
    if cell.n_finite == 1:
        return Figure(cell.mean_all, None, 1, "all")
    return Figure(None, None, 0, None)


def pct_figure(cell: Cell) -> Figure:
    """The "% Ours is Larger" a cell shows: over pairs where both runs converged when there is one,
    else over all pairs with a finite error, else nothing."""
    if cell.n_pairs:
        return Figure(cell.pct_ref_larger, None, cell.n_pairs, "converged")
    if cell.n_pairs_all:
        return Figure(cell.pct_all, None, cell.n_pairs_all, "all")
    return Figure(None, None, 0, None)


def format_figure(fig: Figure, decimals: int, suffix: str = "") -> str:
    """``value[suffix] ± std``, without the ± for a single value, ending in :data:`ALL_RUNS_MARK` on
    the all-runs basis; :data:`EMPTY` when there is nothing to show."""
    if fig.basis is None or fig.value is None:
        return EMPTY
    text = f"{fig.value:.{decimals}f}{suffix}"
    if fig.std is not None:
        text += f" ± {fig.std:.{decimals}f}"
    return text + (f" {ALL_RUNS_MARK}" if fig.basis == "all" else "")


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


def select_target(df: pd.DataFrame, target: str | None = None) -> pd.DataFrame:
    """The rows of one target (default: the only target in ``df``).

    Raises:
        InputError: no rows, several targets and none chosen, or an unknown target.
    """
    if df.empty:
        raise InputError("no result rows to tabulate")
    targets = sorted(df["target"].unique())
    if target is None:
        if len(targets) > 1:
            raise InputError(f"results hold several targets {targets}; choose one with --target")
        target = targets[0]
    elif target not in targets:
        raise InputError(f"target {target!r} not in results; available: {', '.join(targets)}")
    return df[df["target"] == target]


def _stats(values: np.ndarray) -> tuple[float, float, int]:
    """Mean, population std (ddof=0) and count of the finite ``values`` (NaN, NaN, 0 when none)."""
    v = values[np.isfinite(values)]
    if not v.size:
        return float("nan"), float("nan"), 0
    return float(v.mean()), float(v.std(ddof=0)), int(v.size)


def table1_cells(df: pd.DataFrame, reference: str = "generator", target: str | None = None,
                 metric: str = "trans_err_xy") -> dict[tuple[str, float], Cell]:
    """Compute every cell of Table 1 for one target (default: the only target in ``df``)."""
    d = select_target(df, target)
    has_ref = reference in set(d["attack"])
    cells = {}
    for (attack, budget), g in d.groupby(["attack", "budget"]):
        err = g[metric].to_numpy(dtype=float)
        mean, std, n = _stats(err[g["converged"].to_numpy(dtype=bool)])
        mean_all, std_all, n_finite = _stats(err)
        pct, n_pairs, pct_all, n_pairs_all = None, 0, None, 0
        if has_ref and attack != reference:
            at_b = d[d["budget"] == budget]
            pct, n_pairs = pct_reference_larger(at_b, attack, reference, metric)
            pct_all, n_pairs_all = pct_reference_larger(at_b, attack, reference, metric,
                                                        converged_only=False)
        cells[(attack, float(budget))] = Cell(
            mean=mean, std=std, n=n, dropped=int(len(g) - n), pct_ref_larger=pct, n_pairs=n_pairs,
            runs=int(len(g)), mean_all=mean_all, std_all=std_all, n_finite=n_finite,
            pct_all=pct_all, n_pairs_all=n_pairs_all)
    return cells


def auto_decimals(budgets) -> int:
    """Decimals that resolve the smallest budget to ~1%: 2 for metres-scale budgets (as in the
    paper), 4 for the normalised objects budgets 0.02/0.05."""
    smallest = float(np.min(np.asarray(list(budgets), dtype=float)))
    return 2 if smallest >= 1.0 else 2 + int(np.ceil(-np.log10(smallest)))


def _grid(cells: dict[tuple[str, float], Cell], reference: str,
          text: Callable[[str, float, Cell | None], dict[str, str]],
          attacks: list[str] | None = None) -> pd.DataFrame:
    """A frame with one row per attack (paper order, "Method" = display name) and the columns
    ``text(attack, budget, cell)`` returns for each budget (cell None: not run at that budget)."""
    if attacks is None:
        attacks = attack_order(sorted({a for a, _ in cells}), reference)
    budgets = sorted({b for _, b in cells})
    rows = []
    for a in attacks:
        row = {"Method": DISPLAY.get(a, a)}
        for b in budgets:
            row.update(text(a, b, cells.get((a, b))))
        rows.append(row)
    return pd.DataFrame(rows)


def _pct_text(attack: str, cell: Cell | None, reference: str, has_ref: bool) -> str:
    """A "% Ours is Larger" cell: the share with two decimals, "-" for the reference itself."""
    if not has_ref:
        return f"({reference} not run)"
    if attack in (reference, WORST):  # the worst of all includes the reference: never below it
        return "-"
    return EMPTY if cell is None else format_figure(pct_figure(cell), 2, "%")


def _main_frame(cells: dict[tuple[str, float], Cell], reference: str, unit: str,
                decimals: int | None) -> pd.DataFrame:
    """Table 1 strings from computed cells (see :func:`table1_frame`)."""
    if decimals is None:
        decimals = auto_decimals(b for _, b in cells)
    has_ref = reference in {a for a, _ in cells}

    def text(a: str, b: float, c: Cell | None) -> dict[str, str]:
        err = EMPTY if c is None else format_figure(error_figure(c), decimals)
        return {f"λ={b:g} Trans Pose Error [{unit}]": err,
                f"λ={b:g} % Ours is Larger": _pct_text(a, c, reference, has_ref)}

    return _grid(cells, reference, text)


def table1_frame(df: pd.DataFrame, reference: str = "generator", target: str | None = None,
                 metric: str = "trans_err_xy", decimals: int | None = None, *,
                 dataset: str | None = None) -> pd.DataFrame:
    """Table 1 as a DataFrame of strings: rows = attacks (paper order), per budget λ two columns.

    "λ=<b> Trans Pose Error [<unit>]": mean ± std of ``metric`` (:func:`error_figure`; unit from
    :func:`error_unit` and ``dataset``). "λ=<b> % Ours is Larger": share of pairs where the
    reference's error is larger (:func:`pct_figure`), "-" in the reference's own row. A cell on the
    all-runs basis ends in :data:`ALL_RUNS_MARK`; :data:`EMPTY` where no run or pair has a finite error.
    """
    cells = table1_cells(df, reference, target, metric)
    return _main_frame(cells, reference, error_unit(metric, dataset), decimals)


def table1_counts(df: pd.DataFrame, reference: str = "generator",
                  target: str | None = None) -> pd.DataFrame:
    """Long form, one row per (attack, budget): ``n`` converged runs, ``dropped`` (not converged or
    failed), ``pairs`` (pairs with the reference, both converged), ``runs`` (all rows) and
    ``pairs_all`` (pairs with a finite error)."""
    cells = table1_cells(df, reference, target)
    return pd.DataFrame(
        [{"attack": a, "budget": b, "n": c.n, "dropped": c.dropped, "pairs": c.n_pairs,
          "runs": c.runs, "pairs_all": c.n_pairs_all}
         for (a, b), c in sorted(cells.items())])


#: What the three numbers of a counts cell are.
COUNTS_HEADER = "runs / converged / pairs"


def _counts_grid(cells: dict[tuple[str, float], Cell], reference: str) -> pd.DataFrame:
    """Counts table from computed cells (see :func:`counts_frame`)."""
    has_ref = reference in {a for a, _ in cells}

    def text(a: str, b: float, c: Cell | None) -> dict[str, str]:
        if c is None:
            return {f"λ={b:g}": "0 / 0 / 0"}
        pairs = str(c.n_pairs) if has_ref and a not in (reference, WORST) else "-"
        return {f"λ={b:g}": f"{c.runs} / {c.n} / {pairs}"}

    return _grid(cells, reference, text)


def counts_frame(df: pd.DataFrame, reference: str = "generator",
                 target: str | None = None) -> pd.DataFrame:
    """The counts behind Table 1, same rows (attacks) and one column "λ=<b>" per budget; each cell
    ``runs / converged / pairs`` (:data:`COUNTS_HEADER`): all rows, converged runs with a finite error
    (the paper's mean ± std), and pairs with the reference where both converged (its "% Ours is
    Larger"); pairs are "-" in the reference's row or when the reference was not run."""
    return _counts_grid(table1_cells(df, reference, target), reference)


def share_interval(pct: float, n: int, level: float = 0.95) -> tuple[float, float]:
    """The ``level`` interval [%] of a share ``pct`` [%] of ``n`` pairs: Wilson's score interval
    for a binomial proportion (E. B. Wilson, "Probable inference, the law of succession, and
    statistical inference", JASA 1927), from ``scipy.stats.binomtest``; it stays inside [0, 100]
    and is not degenerate at 0% or 100%, where a 10-pair cell needs it most."""
    from scipy.stats import binomtest

    k = int(round(pct * n / 100.0))
    ci = binomtest(k, n).proportion_ci(confidence_level=level, method="wilson")
    return 100.0 * float(ci.low), 100.0 * float(ci.high)


def _share_text(pct: float | None, n: int, decimals: int = 1) -> str:
    """``<share>% [<lo>-<hi>] of <pairs>``, the 95% Wilson interval in brackets."""
    if pct is None or n == 0:
        return EMPTY
    lo, hi = share_interval(pct, n)
    return f"{pct:.{decimals}f}% [{lo:.0f}-{hi:.0f}] of {n}"


def _all_pairs_grid(cells: dict[tuple[str, float], Cell], reference: str,
                    converged: bool = False) -> pd.DataFrame:
    """Shares with their 95% intervals from computed cells, over all pairs with a finite error
    (see :func:`all_pairs_frame`) or, with ``converged``, over the pairs where both converged
    (the main table's basis)."""
    attacks = attack_order(sorted({a for a, _ in cells}), reference)
    if reference not in attacks:
        return pd.DataFrame()

    def text(a: str, b: float, c: Cell | None) -> dict[str, str]:
        if c is None:
            return {f"λ={b:g}": EMPTY}
        return {f"λ={b:g}": _share_text(c.pct_ref_larger, c.n_pairs) if converged else
                _share_text(c.pct_all, c.n_pairs_all)}

    return _grid(cells, reference, text, [a for a in attacks if a not in (reference, WORST)])


def all_pairs_frame(df: pd.DataFrame, reference: str = "generator",
                    target: str | None = None) -> pd.DataFrame:
    """"% Ours is Larger" over every pair with a finite error (non-converged runs at their final
    error), one column "λ=<b>" per budget, cells ``<share>% [<lo>-<hi>] of <pairs>`` with the 95%
    Wilson interval (:func:`share_interval`); the reference's row left out, and no rows at all
    when the reference was not run."""
    return _all_pairs_grid(table1_cells(df, reference, target), reference)


def displacement_frame(df: pd.DataFrame, reference: str = "generator",
                       unit: str = "m") -> pd.DataFrame:
    """Budget audit of the attack base class, one row per attack with a non-zero displacement and
    one column "λ=<b>" per budget: ``<largest point displacement [unit]> / <mean share [%] of points
    moved beyond λ>`` over all samples (soft-bound attacks can exceed λ). Empty when ``df`` has no
    ``disp_max``/``frac_over_budget`` columns."""
    if df.empty or not {"disp_max", "frac_over_budget"} <= set(df.columns):
        return pd.DataFrame()
    moved = df.groupby("attack")["disp_max"].apply(lambda s: bool((s.fillna(0) > 0).any()))
    attacks = attack_order([a for a, m in moved.items() if m], reference)
    budgets = sorted(df["budget"].unique())
    rows = []
    for a in attacks:
        g = df[df["attack"] == a]
        row = {"Method": DISPLAY.get(a, a)}
        for b in budgets:
            gb = g[g["budget"] == b]
            row[f"λ={b:g}"] = (f"{gb['disp_max'].max():.3g} / {100 * gb['frac_over_budget'].mean():.2f}%"
                               if len(gb) else EMPTY)
        rows.append(row)
    return pd.DataFrame(rows)


def _reused_s(extra: Any) -> float:
    """``reused_s`` of a row's ``extra`` (a dict or its JSON text): seconds per scan the attack took
    from work another row of the same batch had done (0 when absent)."""
    if isinstance(extra, str):
        try:
            extra = json.loads(extra)
        except ValueError:
            return 0.0
    v = extra.get("reused_s", 0.0) if isinstance(extra, dict) else 0.0
    return float(v) if v == v else 0.0


def _scan_times(df: pd.DataFrame) -> pd.DataFrame:
    """Mean attack wall time per scan [s] per attack, over all budgets (one row per scan, budget
    and seed: a scan attacked once is timed once whatever the number of targets): column ``run``
    (what the attack took in this run) and ``alone`` (plus the work it reused from another row of
    the batch, e.g. the generator's prior computed by ``sector-iter``: what it costs on its own)."""
    d = df.drop_duplicates(["sample_id", "attack", "budget", "seed"]).copy()
    reused = d["extra"].map(_reused_s) if "extra" in d.columns else 0.0
    d["alone"] = d["attack_time_s"] + reused
    return d.groupby("attack").agg(run=("attack_time_s", "mean"), alone=("alone", "mean"))


def timing_frame(df: pd.DataFrame, reference: str = "generator") -> pd.DataFrame:
    """Attack wall time per scan: columns "Method", "Attack time per scan [s]" (mean over all
    budgets, from ``attack_time_s``: one attack pass per batch divided by its size), "Alone [s]"
    (the same plus the work it reused from another row of its batch) and "Ratio to <reference>"
    of the times alone ("-" in the reference's row or when it has no time). Empty without
    timings."""
    if df.empty or "attack_time_s" not in df.columns:
        return pd.DataFrame()
    t = _scan_times(df)
    ref = t["alone"].get(reference)
    name = DISPLAY.get(reference, reference)
    rows = []
    for a in attack_order(list(t.index), reference):
        alone = t.loc[a, "alone"]
        ratio = f"{alone / ref:.2g}x" if ref and ref > 0 and a != reference else "-"
        rows.append({"Method": DISPLAY.get(a, a), "Attack time per scan [s]": f"{t.loc[a, 'run']:.3g}",
                     "Alone [s]": f"{alone:.3g}", f"Ratio to {name}": ratio})
    return pd.DataFrame(rows)


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
    return out + grid_notes(df) + provenance_notes(df)


def grid_notes(df: pd.DataFrame) -> list[str]:
    """Warnings that the table covers only part of its run's grid: a run still writes to the
    folder, the run did not finish (interrupted, or stopped by an error), or rows of the grid
    (configured attacks x targets x budgets x seeds over the samples present) are missing."""
    out = []
    if df.attrs.get("in_use"):
        out.append("warning: a run is still writing to this folder; the table shows only the rows "
                   "written so far")
    elif df.attrs.get("finished") is False:
        out.append("warning: the run that wrote this folder did not finish (interrupted or "
                   "stopped); the table covers part of its grid; re-run the same `icpbench run` "
                   "command to complete it")
    cfg = df.attrs.get("config") or {}
    axes = {"attack": cfg.get("attacks"), "target": cfg.get("targets"),
            "budget": cfg.get("budgets"), "seed": cfg.get("seeds")}
    if all(isinstance(v, list) and v for v in axes.values()) and "all" not in axes["attack"]:
        expected = (df["sample_id"].nunique() * len(set(axes["attack"])) * len(set(axes["target"]))
                    * len({float(b) for b in axes["budget"]}) * len(set(axes["seed"])))
        have = len(df[df["attack"].isin(axes["attack"]) & df["target"].isin(axes["target"])
                      & df["budget"].isin([float(b) for b in axes["budget"]])
                      & df["seed"].isin(axes["seed"])])
        if have < expected:
            out.append(f"warning: the grid is incomplete: {expected - have} of {expected} rows "
                       "(sample x attack x target x budget x seed) are missing; re-run the same "
                       "`icpbench run` command to compute them")
    return out


def provenance_notes(df: pd.DataFrame) -> list[str]:
    """A warning when the rows were written by runs of different software (package versions or
    commit), as the manifest's ``provenance`` records per range of rows."""
    from icpbench.harness.results import software_of

    entries = df.attrs.get("provenance") or []
    kinds = {software_of(e) for e in entries}
    if len(kinds) <= 1:
        return []
    starts = ", ".join(f"from row {e.get('rows_from')}: commit "
                       f"{((e.get('git') or {}).get('commit') or 'unknown')[:10]}, icpbench "
                       f"{(e.get('versions') or {}).get('icpbench', '?')}, torch "
                       f"{(e.get('versions') or {}).get('torch', '?')}" for e in entries)
    return [f"warning: the rows were written by {len(kinds)} different software versions or "
            f"commits (resumed runs; manifest.json 'provenance'): {starts}"]


#: First-line prefixes of the tables :func:`render` writes (Table 1 and the transfer table).
TABLE_HEADS = ("| Method", "| Attack", "\\begin{tabular}", "Method,", "Attack,")


def is_table_text(text: str) -> bool:
    """Whether ``text`` is a table written by ``icpbench table`` (by its first line)."""
    first = text.lstrip().split("\n", 1)[0]
    return first.startswith(TABLE_HEADS)


def check_table_destination(path: str | Path) -> None:
    """Refuse any ``table --out`` destination but a new file or a table ``icpbench table`` wrote.

    An existing file is overwritten only when it is a regular file (not a link) whose first line is
    that of one of our tables (:func:`is_table_text`); a results folder's own files
    (``results.csv``, ``manifest.json``, its lock) are refused even when reached through a link or
    a linked folder.

    Raises:
        InputError: ``path`` is empty, a folder, a link, a results folder's own file, or an
            existing file that is not a table written by ``icpbench table``.
    """
    from icpbench.harness.results import STORE_FILES, is_results_dir

    p = Path(path)
    if str(path) == "":
        raise InputError("--out is empty ('')")
    if p.is_symlink():
        raise InputError(f"refusing to write a table through the link {p} (it points at "
                         f"{os.readlink(p)}); give the path of a new file or of a table written "
                         "by `icpbench table`")
    if p.is_dir():
        raise InputError(f"--out {p} is a folder; give a file name, e.g. {p / 'table1.md'}")
    real = p.resolve()
    if real.name in STORE_FILES and is_results_dir(real.parent):
        raise InputError(f"refusing to write a table over {p}: it is a file of the results folder "
                         f"{real.parent} (written by `icpbench run`); choose another --out")
    if p.exists():
        if not p.is_file():
            raise InputError(f"refusing to write a table over {p}: it is not a regular file")
        try:
            with open(p, "rb") as f:
                ours = is_table_text(f.read(4096).decode("utf-8", errors="strict"))
        except (OSError, UnicodeDecodeError):
            ours = False
        if not ours:
            raise InputError(f"refusing to overwrite {p}: it is not a table written by "
                             "`icpbench table` (only a new file or such a table is written); "
                             "choose another --out")


def write_table(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` after :func:`check_table_destination`, through a temporary file
    in the same folder renamed over it (a link at ``path`` is refused, never followed)."""
    p = Path(path)
    check_table_destination(p)
    write_file(p, text)


def render(frame: pd.DataFrame, fmt: Format = "md") -> str:
    """Render a table frame as Markdown (GitHub), LaTeX (booktabs) or CSV."""
    if fmt == "md":
        return tabulate(frame, headers="keys", tablefmt="github", showindex=False)
    if fmt == "latex":
        return tabulate(frame, headers="keys", tablefmt="latex_booktabs", showindex=False)
    if fmt == "csv":
        return frame.to_csv(index=False)
    raise InputError(f"unknown format {fmt!r}; valid: md, latex, csv")


def table1_long(df: pd.DataFrame, reference: str = "generator", target: str | None = None,
                metric: str = "trans_err_xy", *, dataset: str | None = None) -> pd.DataFrame:
    """Table 1 in long form for CSV, one row per (attack, budget) in the paper's order.

    Columns: ``Method`` (display name), ``attack``, ``target``, ``budget`` (λ, in ``unit``),
    ``metric``, ``unit`` ("m", "units" or "rad"); the shown error ``mean``, ``std`` (empty for a single
    value), ``error_basis`` ("converged" or "all", empty when no finite error) and ``error_runs``
    (runs behind it); the shown share ``pct_ours_larger`` [%] (the reference's error larger; empty in
    its own row), ``pct_basis`` and ``pct_pairs``; the counts ``runs``, ``converged``, ``pairs``
    (both converged); ``pct_all_pairs`` [%] and ``all_pairs`` (every pair with a finite error);
    ``disp_max`` [unit] and ``frac_over_budget_pct`` [%] (budget audit) and ``attack_time_s`` (mean
    per scan at this budget) where the results hold them.
    """
    sub = select_target(df, target)
    cells = table1_cells(df, reference, target, metric)
    unit = error_unit(metric, dataset)
    rows = []
    for a in attack_order(sorted({a for a, _ in cells}), reference):
        for b in sorted(bb for aa, bb in cells if aa == a):
            c = cells[(a, b)]
            err, pct = error_figure(c), pct_figure(c)
            rows.append({
                "Method": DISPLAY.get(a, a), "attack": a, "target": sub["target"].iloc[0], "budget": b,
                "metric": metric, "unit": unit, "mean": err.value, "std": err.std,
                "error_basis": err.basis, "error_runs": err.count,
                "pct_ours_larger": pct.value, "pct_basis": pct.basis, "pct_pairs": pct.count,
                "runs": c.runs, "converged": c.n, "pairs": c.n_pairs,
                "pct_all_pairs": c.pct_all, "all_pairs": c.n_pairs_all,
                **_audit_columns(sub[(sub["attack"] == a) & (sub["budget"] == b)])})
    return pd.DataFrame(rows)


#: Columns of :func:`table1_long` that name a row rather than hold a figure.
_ID_COLUMNS = ("Method", "attack", "target", "budget", "metric", "unit")
#: Count columns of :func:`table1_long` (integers; empty where an attack did not run at a budget).
_COUNT_COLUMNS = ("error_runs", "pct_pairs", "runs", "converged", "pairs", "all_pairs")


def table1_csv_frame(df: pd.DataFrame, reference: str = "generator", target: str | None = None,
                     metric: str = "trans_err_xy", *, dataset: str | None = None) -> pd.DataFrame:
    """Table 1 for CSV: the rows of :func:`table1_frame` (attacks, paper order) and its display
    columns first, then ``attack``, ``target``, ``unit`` and, per budget, every figure column of
    :func:`table1_long` named ``λ=<b> <column>`` (e.g. ``λ=1 mean``, ``λ=1 error_basis``,
    ``λ=1 converged``): numbers, bases and counts a program can read without parsing the text."""
    cells = table1_cells(df, reference, target, metric)
    display = _main_frame(cells, reference, error_unit(metric, dataset), None)
    long = table1_long(df, reference, target, metric, dataset=dataset)
    values = [c for c in long.columns if c not in _ID_COLUMNS]
    wide = long.pivot(index="attack", columns="budget", values=values)
    budgets = sorted(long["budget"].unique())
    wide = wide[[(v, b) for b in budgets for v in values]]
    wide.columns = [f"λ={b:g} {v}" for v, b in wide.columns]
    for col in wide.columns:
        if col.split(" ", 1)[1] in _COUNT_COLUMNS:
            wide[col] = wide[col].astype("Int64")
    attacks = list(dict.fromkeys(long["attack"]))
    ids = long.drop_duplicates("attack").set_index("attack")[["target", "unit"]]
    out = pd.concat([ids.loc[attacks], wide.loc[attacks]], axis=1).reset_index()
    return pd.concat([display, out], axis=1)


def _audit_columns(g: pd.DataFrame) -> dict[str, float]:
    """``disp_max``, ``frac_over_budget_pct`` and ``attack_time_s`` of one cell's rows, for the
    columns the results hold."""
    out = {}
    if "disp_max" in g.columns:
        out["disp_max"] = float(g["disp_max"].max())
    if "frac_over_budget" in g.columns:
        out["frac_over_budget_pct"] = float(100 * g["frac_over_budget"].mean())
    if "attack_time_s" in g.columns:
        out["attack_time_s"] = float(g["attack_time_s"].mean())
    return out


def _latex_text(text: str) -> str:
    """``text`` with LaTeX's special characters in prose (% & _ #) escaped."""
    for ch in "%&_#":
        text = text.replace(ch, "\\" + ch)
    return text


def table1_footnotes(frame: pd.DataFrame, reference: str = "generator") -> list[str]:
    """Lines explaining the marks a Table 1 frame uses (:data:`ALL_RUNS_MARK`, :data:`EMPTY`)."""
    cells = frame.drop(columns="Method").to_numpy().ravel().tolist()
    name = DISPLAY.get(reference, reference)
    out = []
    if any(str(c).endswith(ALL_RUNS_MARK) for c in cells):
        out.append(f"{ALL_RUNS_MARK} over all runs, non-converged ones at their final error: the "
                   f"paper's rule (converged runs; pairs with {name} where both converged) leaves "
                   f"fewer than {MIN_RUNS_FOR_STD} runs for mean ± std, or no pair for the %.")
    if EMPTY in cells:
        out.append(f"{EMPTY} no run (or no pair) with a finite error at this budget.")
    return out


def _section(title: str, frame: pd.DataFrame, fmt: Format) -> str:
    """A titled secondary table (empty string for an empty frame)."""
    if frame.empty:
        return ""
    if fmt == "latex":
        return f"\\medskip\n\\noindent {_latex_text(title)}\n\n{render(frame, fmt)}"
    return f"{title}\n\n{render(frame, fmt)}"


def table1(df: pd.DataFrame, fmt: Format = "md", reference: str = "generator",
           target: str | None = None, *, dataset: str | None = None) -> str:
    """Table 1 text.

    A run of two or more attacks gets a last row, the worst of all attacks per scan
    (:func:`~icpbench.harness.worst_case.worst_rows`), and a line naming which attack won how many
    scans. md/latex: Table 1 (:func:`table1_frame`) and the lines explaining its marks; then, as tables of
    the same format, the counts per cell (:func:`counts_frame`), "% Ours is Larger" over all pairs
    (:func:`all_pairs_frame`), the displacement audit (:func:`displacement_frame`) and the attack
    time per scan (:func:`timing_frame`); then the load and health warnings, one per line (LaTeX:
    as comments). csv: :func:`table1_csv_frame`. ``dataset`` picks the unit (:func:`error_unit`).
    """
    sub = select_target(df, target)
    worst = worst_rows(sub)
    with_worst = pd.concat([df, worst.drop(columns="winner")], ignore_index=True) \
        if not worst.empty else df
    if fmt == "csv":
        return render(table1_csv_frame(with_worst, reference, target, dataset=dataset), fmt)
    cells = table1_cells(with_worst, reference, target)
    unit = error_unit("trans_err_xy", dataset)
    main = _main_frame(cells, reference, unit, None)
    name = DISPLAY.get(reference, reference)
    text = render(main, fmt)
    notes = table1_footnotes(main, reference)
    if not worst.empty:
        notes.append(winner_note(worst))
    if notes and fmt == "latex":
        text += "\n\n" + "\n\n".join(_latex_text(n) for n in notes)  # one paragraph each
    elif notes:
        text += "\n\n" + "\n".join(notes)
    sections = [
        (f"Runs per cell: {COUNTS_HEADER} (runs: all; converged: the runs behind mean ± std; pairs: "
         f"pairs with {name} where both converged, behind the %)", _counts_grid(cells, reference)),
        (f"% {name} is larger over converged pairs (the table's %) with its 95% interval "
         "(Wilson; share [interval] of pairs)", _all_pairs_grid(cells, reference, True)),
        (f"% {name} is larger incl. non-converged runs (all pairs with a finite error; share "
         "[95% Wilson interval] of pairs)", _all_pairs_grid(cells, reference)),
        (f"Displacement audit: largest point displacement [{unit}] / mean share of points moved "
         "beyond λ", displacement_frame(sub, reference, unit)),
        ("Attack time per scan [s], mean over all budgets", timing_frame(sub, reference)),
    ]
    for title, frame in sections:
        part = _section(title, frame, fmt)
        if part:
            text += "\n\n" + part
    warnings = load_notes(df) + health_warnings(sub)
    if warnings:
        prefix = "% " if fmt == "latex" else ""
        text += "\n\n" + "\n".join(prefix + w for w in warnings)
    return text + "\n"


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
