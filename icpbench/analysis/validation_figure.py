"""The validation's route figure: one top view of the route per quantity.

Panel one shows the realistic error at the headline severity (metres, capped at
:data:`icpbench.analysis.danger_map.ERROR_CAP_M`); every other panel colours each place by the
*danger percentile* of one quantity (0 = the safest place of the route by that quantity, 1 = the most
dangerous), so quantities with different units share one colour scale. In every panel, the places
that fail under realistic corruption are ringed in black: a quantity that predicts trouble puts its
dark (dangerous) places inside the rings.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from icpbench.analysis.danger_map import ERROR_CAP_M
from icpbench.analysis.plotting import pyplot, save
from icpbench.core.errors import InputError


def danger_percentile(values: np.ndarray, sign: int) -> np.ndarray:
    """(n,) percentile rank in [0, 1] of ``sign * values`` (ties share their mean rank; NaN stays
    NaN; ``inf`` is the largest)."""
    v = pd.Series(sign * np.asarray(values, dtype=np.float64))
    return v.rank(pct=True, method="average").to_numpy()


def plot_validation_route(places: pd.DataFrame, quantities: dict[str, int], severity: int,
                          fail_m: float, path: str | Path, *, title: str = "") -> Path:
    """Write the figure (see the module doc) for ``places`` (columns ``x``, ``y`` in metres,
    ``realistic_s<severity>`` and the quantities) to ``path``.

    Raises:
        InputError: the places have no route position.
    """
    if not {"x", "y"} <= set(places.columns):
        raise InputError("the places have no route position (meta.x, meta.y); the route figure "
                         "needs a route dataset")
    plt = pyplot()
    real = places[f"realistic_s{severity}"].to_numpy(float)
    fails = real > fail_m
    names = list(quantities)
    n = len(names) + 1
    cols = 3
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.0 * cols, 4.3 * rows), squeeze=False)
    x, y = places["x"].to_numpy(float), places["y"].to_numpy(float)

    def ring(ax) -> None:
        ax.scatter(x[fails], y[fails], s=90, facecolors="none", edgecolors="black", linewidths=1.2)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")

    ax = axes[0, 0]
    sc = ax.scatter(x, y, c=np.clip(np.nan_to_num(real, posinf=ERROR_CAP_M), 0, ERROR_CAP_M),
                    cmap="inferno_r", vmin=0, vmax=ERROR_CAP_M, s=22)
    fig.colorbar(sc, ax=ax, shrink=0.8, label="largest error over corruptions [m]")
    ring(ax)
    ax.set_title(f"realistic error, severity {severity} ({int(fails.sum())} fail > {fail_m:g} m)",
                 fontsize=9)
    for k, q in enumerate(names, start=1):
        ax = axes[k // cols, k % cols]
        pct = danger_percentile(places[q].to_numpy(float), quantities[q])
        sc = ax.scatter(x, y, c=pct, cmap="inferno_r", vmin=0, vmax=1, s=22)
        fig.colorbar(sc, ax=ax, shrink=0.8, label="danger percentile [0-1]")
        ring(ax)
        ax.set_title(q + ("" if quantities[q] > 0 else " (negated)"), fontsize=9)
    for k in range(n, rows * cols):
        fig.delaxes(axes[k // cols, k % cols])
    if title:
        fig.suptitle(f"{title}: black rings = places that fail under realistic corruption")
    return save(fig, path, dpi=100)
