"""The leaderboard's figures: each variant's worst case with its 95% interval, and the same variants
on two boards (two data domains) against each other.

Both read a board as :func:`icpbench.harness.leaderboard.summarise` makes it (one row per variant
and budget): ``worst_mean`` and its bootstrap interval ``worst_lo`` / ``worst_hi`` (metres), the
budget ``budget`` (lambda, metres) and ``amplification`` = ``worst_mean`` / lambda. A board read
back from ``leaderboard.csv`` has the same columns.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from icpbench.harness.outputs import save_figure


def _interval(rows: pd.DataFrame) -> np.ndarray:
    """(2, V) distances from each row's amplification down to and up to its 95% interval (in
    units of lambda; 0 where the board holds no interval)."""
    amp = rows.amplification.to_numpy(float)
    if not {"worst_lo", "worst_hi"} <= set(rows.columns):
        return np.zeros((2, len(rows)))
    lo = rows.worst_lo.to_numpy(float) / rows.budget.to_numpy(float)
    hi = rows.worst_hi.to_numpy(float) / rows.budget.to_numpy(float)
    err = np.stack([amp - lo, hi - amp])
    return np.where(np.isfinite(err), np.maximum(err, 0.0), 0.0)


def board_figure(board: pd.DataFrame, path: Path, safe_amplification: float) -> None:
    """Grouped horizontal bars of the mean amplification per variant and budget, each with its 95%
    bootstrap interval over scans (PNG at ``path``).

    Args:
        board: the board (module docstring), variants in ranking order.
        path: the PNG to write.
        safe_amplification: the amplification up to which a scan counts as held (a dotted line).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    budgets = sorted(board.budget.unique())
    order = list(dict.fromkeys(board.variant))
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(order) * len(budgets) ** 0.5 + 1.6))
    h = 0.8 / len(budgets)
    y = np.arange(len(order))
    for j, lam in enumerate(budgets):
        r = board[np.isclose(board.budget, lam)].set_index("variant").reindex(order)
        ok = r.amplification.notna().to_numpy()
        ax.barh((y + (j - (len(budgets) - 1) / 2) * h)[ok], r.amplification[ok], height=h,
                xerr=_interval(r[ok]), capsize=3, error_kw={"lw": 1}, label=f"λ = {lam:g} m")
    ax.axvline(1.0, color="k", ls="--", lw=1)
    ax.text(1.0, -0.9, " rigid translation", fontsize=8, va="center")
    ax.axvline(safe_amplification, color="grey", ls=":", lw=1)
    ax.set_yticks(y, order)
    ax.invert_yaxis()
    ax.set_xlabel("worst-case error / λ (mean over scans, 95% interval; lower is more robust)")
    ax.set_title("ICP variants under the attack ensemble (most robust on top)")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=130)
    plt.close(fig)


def _label_heights(y: pd.Series, lo: float, hi: float) -> dict[str, float]:
    """Heights of the points' labels on a log axis from ``lo`` to ``hi``: each at its point,
    moved up just enough to keep 3% of the axis between neighbouring labels."""
    gap = 0.03 * np.log10(hi / lo)
    out: dict[str, float] = {}
    last = -np.inf
    for v, val in y.sort_values().items():
        last = max(np.log10(val), last + gap)
        out[str(v)] = float(10**last)
    return out


def ranking_rows(board: pd.DataFrame) -> pd.DataFrame:
    """The rows of ``board`` at its ranking (middle) budget, indexed by variant."""
    budgets = sorted(board.budget.unique())
    mid = budgets[len(budgets) // 2]
    return board[np.isclose(board.budget, mid)].set_index("variant")


def domain_figure(board: pd.DataFrame, other: pd.DataFrame, path: Path, *, label: str,
                  other_label: str, title: str) -> int:
    """Each variant both boards rank as one point: its mean amplification on ``other`` (x) and on
    ``board`` (y), at each board's ranking budget, with the 95% intervals as bars, on log axes with
    the line y = x (PNG at ``path``). A ranking that carries over puts the points in the same
    order along both axes.

    Args:
        board, other: two boards (module docstring).
        path: the PNG to write.
        label, other_label: the axes' names of the two boards (e.g. their domains).
        title: the figure's title (e.g. Kendall's tau of the two rankings).

    Returns:
        The number of variants drawn (nothing is written below 2).
    """
    mine, theirs = ranking_rows(board), ranking_rows(other)
    common = [v for v in mine.index if v in theirs.index
              and np.isfinite(mine.amplification[v]) and np.isfinite(theirs.amplification[v])]
    if len(common) < 2:
        return len(common)
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, b = mine.loc[common], theirs.loc[common]
    fig, ax = plt.subplots(figsize=(6.5, 6))
    ax.errorbar(b.amplification, a.amplification, xerr=_interval(b), yerr=_interval(a), fmt="o",
                ms=5, capsize=2, lw=1)
    lo = 0.8 * min(a.amplification.min(), b.amplification.min())
    hi = 1.25 * max(a.amplification.max(), b.amplification.max())
    for v, y in _label_heights(a.amplification, lo, hi).items():
        ax.annotate(v, (b.amplification[v], a.amplification[v]), xytext=(b.amplification[v] * 1.1,
                    y), fontsize=7, va="center", arrowprops={"arrowstyle": "-", "lw": 0.5,
                                                              "color": "grey"})
    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.plot([lo, hi], [lo, hi], color="grey", ls=":", lw=1)
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel(f"worst-case error / λ [m / m], {other_label}")
    ax.set_ylabel(f"worst-case error / λ [m / m], {label}")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=130)
    plt.close(fig)
    return len(common)
