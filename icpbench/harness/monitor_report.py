"""The monitors' table: how often each attack is detected, and the error that reaches the planner
without an alarm.

A row of a run with ``--monitors`` records in ``extra`` whether each monitor fired on the
registration it measured (:mod:`icpbench.harness.run_monitors`). Here a row's *undetected error*
is its ``trans_err_xy`` when no monitor fired and 0 when one did (the stack rejects that pose and
falls back, so no error reaches the planner unannounced); a registration whose pose is not finite
always fires. Per attack and budget the table gives the detection rate, the mean error over all
rows (the naive number, no monitor) and the mean, median and 95th percentile of the undetected
error over all rows. The ``none`` rows (clean scans of the evaluated split) give the false-alarm
rate of each monitor on data its threshold was not set on.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from icpbench.harness.report import Format, render
from icpbench.harness.run_monitors import ALARM

__all__ = ["ANY_ALARM", "monitor_names", "monitor_section", "undetected", "undetected_frame"]

#: The column that says whether any monitor fired on a row's registration.
ANY_ALARM = "extra." + ALARM + "any"


def undetected(rows: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Per row of a run with monitors: whether a monitor fired (bool) and the undetected error
    [m] (the row's ``trans_err_xy`` where none fired, 0 where one did or the pose is not finite)."""
    alarm = rows[ANY_ALARM].astype(float).to_numpy() > 0
    err = rows["trans_err_xy"].astype(float).to_numpy()
    return alarm, np.where(alarm | ~np.isfinite(err), 0.0, err)


def monitor_names(df: pd.DataFrame) -> list[str]:
    """The monitors whose alarms the rows of ``df`` record (none: an empty list)."""
    pre = "extra." + ALARM
    return [c[len(pre):] for c in df.columns if c.startswith(pre) and c != ANY_ALARM]


def undetected_frame(df: pd.DataFrame, target: str) -> pd.DataFrame:
    """Per attack and budget on ``target``: rows, detection rate [%], mean error [m] (all rows,
    no monitor), undetected error mean / median / p95 [m] (module docstring); rows of failed
    attacks (``status == "error"``) are left out."""
    sub = df[(df["target"] == target) & (df["status"] != "error") & df[ANY_ALARM].notna()]
    alarm, und = undetected(sub)
    err = sub["trans_err_xy"].astype(float).to_numpy()
    frame = sub.assign(_alarm=alarm, _und=und, _err=np.where(np.isfinite(err), err, np.nan))
    out = []
    for (attack, budget), g in frame.groupby(["attack", "budget"], sort=False):
        und = g["_und"].to_numpy()
        out.append({"attack": attack, "budget": float(budget), "rows": len(g),
                    "detected_pct": 100.0 * float(g["_alarm"].mean()),
                    "error_mean_m": float(np.nanmean(g["_err"])) if g["_err"].notna().any()
                    else float("nan"),
                    "undetected_mean_m": float(und.mean()),
                    "undetected_median_m": float(np.median(und)),
                    "undetected_p95_m": float(np.percentile(und, 95))})
    return pd.DataFrame(out)


def monitor_section(df: pd.DataFrame, fmt: Format, target: str) -> str:
    """The monitors' table of one target, with the clean false-alarm rate of each monitor;
    an empty string when the rows record no monitors."""
    names = monitor_names(df)
    if not names or ANY_ALARM not in df:
        return ""
    t = undetected_frame(df, target)
    if t.empty:
        return ""
    t = t.sort_values(["budget", "attack"], kind="stable")
    shown = pd.DataFrame({
        "Method": t["attack"], "λ": [f"{b:g}" for b in t["budget"]], "rows": t["rows"],
        "detected [%]": t["detected_pct"].round(1),
        "mean error, no monitor [m]": t["error_mean_m"].round(2),
        "undetected mean [m]": t["undetected_mean_m"].round(2),
        "median [m]": t["undetected_median_m"].round(2),
        "p95 [m]": t["undetected_p95_m"].round(2)})
    lines = [f"Monitors ({', '.join(names)}) on {target}: detection rate and the error that "
             "reaches the planner without an alarm (0 where a monitor fired); thresholds in "
             "manifest.json, `monitors`\n", render(shown, fmt)]
    clean = df[(df["target"] == target) & (df["attack"] == "none") & (df["status"] != "error")]
    if not clean.empty:
        rates = ", ".join(
            f"{n} {100 * float((clean['extra.' + ALARM + n].astype(float) > 0).mean()):.1f}%"
            for n in names)
        lines.append(f"\nClean false alarms on the evaluated split ({len(clean)} rows of attack "
                     f"none): {rates}")
    return "\n".join(lines)
