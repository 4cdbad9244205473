"""Matplotlib helpers shared by the figures: a headless pyplot, a save, and the axis-unit check.

Convention for every figure: each axis that shows numeric tick labels (colour bars included) has a
label naming its quantity and its unit in brackets, ``"x [m]"`` or ``"y, lateral (m)"``; an axis
whose ticks are category names (a violin per attack) needs none, and an axis whose tick labels are
hidden because it shares them with a labelled neighbour is covered by that neighbour.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

UNIT = re.compile(r"\[[^\]]+\]|\([^)]+\)")
"""A unit in a label: anything in square or round brackets, ``[m]``, ``(deg)``, ``[normalised]``."""


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: str | Path, dpi: int = 120) -> Path:
    """Lay out, write ``fig`` to ``path`` (creating folders) and close it."""
    from icpbench.harness.outputs import save_figure

    fig.tight_layout()
    path = save_figure(fig, path, dpi=dpi)
    pyplot().close(fig)
    return path


def axes_without_units(fig: Any) -> list[str]:
    """Describe each axis of ``fig`` that shows numeric tick labels but has no label with a unit
    (see the module docstring); an empty list means every axis is labelled. Draws the figure once
    (Agg) so that tick labels exist."""
    fig.canvas.draw()
    missing = []
    for k, ax in enumerate(fig.axes):
        for name, axis, shared in (("x", ax.xaxis, ax.get_shared_x_axes()),
                                   ("y", ax.yaxis, ax.get_shared_y_axes())):
            shown = [t.get_text() for t in axis.get_ticklabels() if t.get_visible()]
            if not any(_is_number(t) for t in shown):
                continue  # no numbers on this axis (hidden, shared, or category names)
            labels = [getattr(a, f"get_{name}label")() for a in shared.get_siblings(ax)]
            if not any(UNIT.search(lab) for lab in labels):
                title = ax.get_title() or ax.get_label() or f"axes {k}"
                missing.append(f"{title!r}: {name} axis label {axis.get_label_text()!r} has no unit")
    return missing


def _is_number(text: str) -> bool:
    try:
        float(text.replace("\u2212", "-"))  # matplotlib writes a typographic minus
    except ValueError:
        return False
    return True
