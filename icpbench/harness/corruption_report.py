"""The corruption table: pose error per corruption and severity, apart from Table 1.

Corruption rows (:mod:`icpbench.harness.corruption_units`) are not attacks: their "budget" is a
severity level, and Table 1's "% Ours is Larger" has no meaning for them. :func:`split_rows` takes
them out of the results before Table 1 is built, and :func:`corruption_frame` gives them a table of
their own: rows = corruptions, one column per severity, each cell the mean ± std of
``trans_err_xy`` (metres) over converged runs and the share of runs (all runs with a finite error,
non-converged ones at their final error) whose error exceeds ``fail_m``.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from icpbench.harness.corruption_units import SEVERITY_KEY
from icpbench.harness.report import Format, render, select_target

#: Error above which a run counts as a failure in the corruption table (metres).
FAIL_M = 0.5


def corruption_mask(df: pd.DataFrame) -> pd.Series:
    """(rows,) bool: True for the rows of corruptions (their ``extra`` holds the severity).

    Works on frames loaded with or without ``expand`` (:func:`icpbench.harness.results.load_results`).
    """
    col = f"extra.{SEVERITY_KEY}"
    if col in df.columns:
        return df[col].notna()
    if "extra" not in df.columns:
        return pd.Series(False, index=df.index)
    return df["extra"].map(lambda s: isinstance(s, str) and SEVERITY_KEY in json.loads(s or "{}"))


def split_rows(df: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(attack rows, corruption rows) of a results frame; ``attrs`` (load notes) kept on both."""
    mask = corruption_mask(df)
    attacks, corruptions = df[~mask].copy(), df[mask].copy()
    attacks.attrs, corruptions.attrs = dict(df.attrs), dict(df.attrs)
    return attacks, corruptions


def corruption_frame(df: pd.DataFrame, target: str | None = None, fail_m: float = FAIL_M,
                     metric: str = "trans_err_xy") -> pd.DataFrame:
    """Corruptions x severities: ``"mean ± std (k/n > fail_m)"`` per cell (see module doc).

    Args:
        df: results holding corruption rows (other rows are ignored).
        target: the target (needed when the rows hold several).
        fail_m: failure threshold, metres.
        metric: the error column.
    """
    d = df[corruption_mask(df)] if len(df) else df
    if d.empty:
        return pd.DataFrame()
    d = select_target(d, target)
    d = d[d["status"] != "error"]
    out = []
    for name, g in d.groupby("attack", sort=True):
        row = {"Corruption": name}
        for sev, h in g.groupby("budget", sort=True):
            err = pd.to_numeric(h[metric], errors="coerce").to_numpy(float)
            finite = np.isfinite(err)
            conv = err[finite & h["converged"].to_numpy(bool)]
            mean = f"{conv.mean():.3f} ± {conv.std():.3f}" if conv.size else "—"
            row[f"severity {int(sev)}"] = (f"{mean} ({int((err[finite] > fail_m).sum())}/"
                                           f"{int(finite.sum())} > {fail_m:g} m)")
        out.append(row)
    return pd.DataFrame(out).fillna("")


def corruption_section(df: pd.DataFrame, fmt: Format = "md", target: str | None = None,
                       fail_m: float = FAIL_M) -> str:
    """The corruption table with its title (empty text when ``df`` has no corruption rows)."""
    frame = corruption_frame(df, target, fail_m)
    if frame.empty:
        return ""
    title = (f"Corruptions: trans_err_xy [m], mean ± std over converged runs (runs with an error "
             f"> {fail_m:g} m / runs with a finite error, non-converged included)")
    if fmt == "latex":
        title = "% " + title
    return f"{title}\n\n{render(frame, fmt)}\n"
