"""Dangerous locations along a route (Zhang et al. 2025, §IV-D, figures 5 and 6).

From the results of one attack at one budget over every location of a route, the worst-case error
per location is the error the attack induced there (``trans_err_xy``, and the larger of the
longitudinal/lateral components ``max(|rho_x|, |rho_y|)`` used for the comparison with the
analytic method). Locations are matched across repeat passes by ``meta.frame`` (the teach vertex),
so with several passes the per-location mean (as in the paper's figure 5) and per-pass maps exist.
Non-converged ICP runs are kept: a diverged localisation at a location is exactly the danger the
map should show (their error is capped for plotting).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from icpbench.analysis.plotting import pyplot, save
from icpbench.core.errors import InputError
from icpbench.core.filenames import safe_component
from icpbench.harness.monitor_report import ANY_ALARM, undetected

LOCATION = "meta.frame"
ERROR_CAP_M = 3.0  # colour scale cap of figure 5


def location_errors(df: pd.DataFrame, attack: str, budget: float) -> pd.DataFrame:
    """Per (location, pass) rows of one attack: x, y, stretch, trans_err_xy, lon_lat_max.

    Raises:
        InputError: the results lack the attack/budget or route metadata.
    """
    need = {LOCATION, "meta.x", "meta.y"}
    if not need <= set(df.columns):
        raise InputError(f"results lack route metadata {sorted(need - set(df.columns))}; "
                         "danger maps need a route dataset such as lidar-sim")
    d = df[(df["attack"] == attack) & np.isclose(df["budget"], budget)
           & (df["status"] != "error")].copy()
    if d.empty:
        have = sorted({(a, b) for a, b in zip(df["attack"], df["budget"], strict=True)})
        raise InputError(f"no rows for attack {attack!r} at budget {budget:g}; have {have}")
    d["lon_lat_max"] = np.maximum(d["rho_x"].abs(), d["rho_y"].abs())
    if ANY_ALARM in d.columns:  # a run with monitors: what reaches the planner unannounced
        alarm, d["undetected_err"] = undetected(d)
        d["detected"] = alarm.astype(float)
    cols = {LOCATION: "location", "meta.x": "x", "meta.y": "y", "meta.stretch": "stretch",
            "meta.pass": "pass"}
    out = d.rename(columns=cols)
    keep = [c for c in ("location", "pass", "x", "y", "stretch", "sample_id", "trans_err_xy",
                        "lon_lat_max", "converged", "seed", "detected", "undetected_err")
            if c in out.columns]
    return out[keep].reset_index(drop=True)


def per_location_mean(loc: pd.DataFrame) -> pd.DataFrame:
    """Mean over passes (and seeds) per location; x, y, stretch of the first pass."""
    agg = {"x": "first", "y": "first", "trans_err_xy": "mean", "lon_lat_max": "mean",
           "converged": "mean"}
    agg.update({c: "mean" for c in ("detected", "undetected_err") if c in loc.columns})
    if "stretch" in loc.columns:
        agg["stretch"] = "first"
    out = loc.groupby("location", as_index=False).agg(agg)
    out["n_passes"] = loc.groupby("location")["pass"].nunique().to_numpy() if "pass" in loc else 1
    return out.sort_values("location").reset_index(drop=True)


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """Area under the ROC curve of scores: P(score_pos > score_neg) + 0.5 P(tie) (Mann-Whitney)."""
    positive, negative = np.asarray(positive, float), np.asarray(negative, float)
    if positive.size == 0 or negative.size == 0:
        return float("nan")
    u = stats.mannwhitneyu(positive, negative, alternative="two-sided").statistic
    return float(u / (positive.size * negative.size))


def open_vs_dense_auc(per_loc: pd.DataFrame, column: str = "trans_err_xy",
                      open_labels: tuple[str, ...] = ("open", "highway"),
                      dense_labels: tuple[str, ...] = ("dense",)) -> float:
    """AUC of 'open (fields, parking lots, highway) vs dense streets' from per-location error."""
    if "stretch" not in per_loc:
        raise InputError("no stretch labels in the results")
    pos = per_loc.loc[per_loc["stretch"].isin(open_labels), column]
    neg = per_loc.loc[per_loc["stretch"].isin(dense_labels), column]
    return auc(pos.to_numpy(), neg.to_numpy())


def pass_rank_correlation(loc: pd.DataFrame, column: str = "trans_err_xy") -> tuple[float, int]:
    """Spearman correlation of per-location errors between the first two passes, and the count
    of shared locations."""
    passes = sorted(loc["pass"].unique()) if "pass" in loc else []
    if len(passes) < 2:
        return float("nan"), 0
    a = loc[loc["pass"] == passes[0]].groupby("location")[column].mean()
    b = loc[loc["pass"] == passes[1]].groupby("location")[column].mean()
    j = a.to_frame("a").join(b.to_frame("b"), how="inner")
    if len(j) < 3:
        return float("nan"), len(j)
    return float(stats.spearmanr(j["a"], j["b"]).statistic), len(j)


def plot_route(per_loc: pd.DataFrame, path: str | Path, *, column: str = "trans_err_xy",
               title: str = "", cap: float = ERROR_CAP_M, n_labels: int = 5,
               diverging: bool = False, label: str = "worst-case translation error [m]") -> Path:
    """Top view of the route coloured by ``column`` (capped), most dangerous places labelled."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(8, 7))
    v = per_loc[column].to_numpy(dtype=float)
    if diverging:
        lim = max(np.nanmax(np.abs(v)), 1e-6)
        sc = ax.scatter(per_loc["x"], per_loc["y"], c=np.clip(v, -lim, lim), cmap="coolwarm",
                        vmin=-lim, vmax=lim, s=14)
    else:
        sc = ax.scatter(per_loc["x"], per_loc["y"], c=np.clip(v, 0, cap), cmap="inferno_r",
                        vmin=0, vmax=cap, s=14)
    fig.colorbar(sc, ax=ax, shrink=0.8, label=label)
    top = per_loc.assign(_v=v).sort_values("_v", ascending=False)
    picked: list[tuple[float, float]] = []
    for _, r in top.iterrows():  # label distinct places (at least 120 m apart)
        if len(picked) >= n_labels:
            break
        if any(np.hypot(r["x"] - x, r["y"] - y) < 120 for x, y in picked):
            continue
        picked.append((r["x"], r["y"]))
        tag = chr(ord("a") + len(picked) - 1)
        ax.annotate(f"{tag}: {r['_v']:.2f} m" + (f" ({r['stretch']})" if "stretch" in r else ""),
                    (r["x"], r["y"]), xytext=(8, 8), textcoords="offset points", fontsize=8,
                    bbox={"boxstyle": "round", "fc": "white", "alpha": 0.8})
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    return save(fig, path, dpi=120)


def comparison(df: pd.DataFrame, ours: str, other: str, budget: float) -> pd.DataFrame:
    """Per location: ``max(|rho_x|, |rho_y|)`` of ``ours`` minus that of ``other`` (same budget),
    averaged over passes (paper figure 6)."""
    a = per_location_mean(location_errors(df, ours, budget))
    b = per_location_mean(location_errors(df, other, budget))
    j = a.merge(b[["location", "lon_lat_max"]], on="location", suffixes=("_ours", "_other"))
    j["difference"] = j["lon_lat_max_ours"] - j["lon_lat_max_other"]
    return j


def plot_comparison(cmp: pd.DataFrame, path: str | Path, ours: str, other: str) -> Path:
    """Figure 6: route coloured by the difference, and a violin plot with the IQR marked."""
    plt = pyplot()

    fig, (ax, av) = plt.subplots(1, 2, figsize=(12, 6), gridspec_kw={"width_ratios": [3, 1]})
    v = cmp["difference"].to_numpy(dtype=float)
    lim = max(np.nanmax(np.abs(v)), 1e-6)
    sc = ax.scatter(cmp["x"], cmp["y"], c=v, cmap="coolwarm", vmin=-lim, vmax=lim, s=14)
    fig.colorbar(sc, ax=ax, shrink=0.8, label=f"{ours} - {other} [m]")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"max(|lon|, |lat|) error: {ours} minus {other}")
    parts = av.violinplot(v[np.isfinite(v)], showextrema=True)
    for b in parts["bodies"]:
        b.set_alpha(0.6)
    q1, med, q3 = np.nanpercentile(v, [25, 50, 75])
    av.vlines(1, q1, q3, color="white", lw=6)
    av.scatter([1], [med], color="black", zorder=3)
    av.axhline(0, color="grey", lw=0.8, ls="--")
    av.set_xticks([1], [f"{ours} - {other}"])
    av.set_ylabel("difference [m] (white bar: IQR)")
    return save(fig, path, dpi=120)


def write_maps(df: pd.DataFrame, attack: str, budget: float, out_dir: str | Path,
               compare: str | None = None) -> dict:
    """Write the CSVs and PNGs of the danger map (and the comparison, if ``compare``); return the
    summary (AUC open-vs-dense, pass rank correlation, file list), also saved as summary.json."""
    from icpbench.harness.outputs import write_csv, write_json

    out = Path(out_dir)
    summary: dict = {"attack": attack, "budget": budget, "files": []}
    for name in [attack] + ([compare] if compare else []):
        loc = location_errors(df, name, budget)
        mean = per_location_mean(loc)
        stem = safe_component(name)
        write_csv(out / f"{stem}_locations.csv", loc, index=False)
        write_csv(out / f"{stem}_locations_mean.csv", mean, index=False)
        files = [str(plot_route(mean, out / f"{stem}_map.png",
                                title=f"{name}, λ = {budget:g} m: mean over passes"))]
        if "pass" in loc:
            for p in sorted(loc["pass"].unique()):
                files.append(str(plot_route(per_location_mean(loc[loc["pass"] == p]),
                                            out / f"{stem}_map_pass{safe_component(p)}.png",
                                            title=f"{name}, λ = {budget:g} m, pass {p}")))
        if "undetected_err" in mean:
            files.append(str(plot_route(
                mean, out / f"{stem}_undetected_map.png", column="undetected_err",
                label="undetected translation error [m]",
                title=f"{name}, λ = {budget:g} m: error no monitor catches (0 where one "
                      "fires), mean over passes")))
        rho, n = pass_rank_correlation(loc)
        s = {"locations": int(len(mean)), "passes": int(loc["pass"].nunique())
             if "pass" in loc else 1,
             "mean_trans_err_xy": float(mean["trans_err_xy"].mean()),
             "pass_rank_correlation": rho, "pass_rank_correlation_n": n}
        if "undetected_err" in mean:
            s["mean_undetected"] = float(mean["undetected_err"].mean())
            s["detected_pct"] = 100.0 * float(loc["detected"].mean())
        if "stretch" in mean:
            s["auc_open_vs_dense"] = open_vs_dense_auc(mean)
            s["mean_by_stretch"] = mean.groupby("stretch")["trans_err_xy"].mean().to_dict()
        summary[name] = s
        summary["files"] += [f"{stem}_locations.csv", f"{stem}_locations_mean.csv"] + [
            Path(f).name for f in files]
    if compare:
        cmp = comparison(df, attack, compare, budget)
        cstem = f"comparison_{safe_component(attack)}_vs_{safe_component(compare)}"
        write_csv(out / f"{cstem}.csv", cmp, index=False)
        plot_comparison(cmp, out / f"{cstem}.png", attack, compare)
        q1, med, q3 = np.nanpercentile(cmp["difference"], [25, 50, 75])
        summary["comparison"] = {"median": float(med), "q1": float(q1), "q3": float(q3),
                                 "share_ours_larger": float((cmp["difference"] > 0).mean())}
        summary["files"] += [f"{cstem}.csv", f"{cstem}.png"]
    write_json(out / "summary.json", summary)
    return summary
