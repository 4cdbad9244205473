"""Object case study (Zhang et al. 2025, §IV-C2, figure 4): how the adversarial-loss weights
shape the learned perturbation.

Generators trained on ``objects`` with the ``theta-only``, ``x-only`` and ``xy`` weights, and the
baselines, attack the same held-out objects. The study writes a per-model table (heading error,
x error, x-y error, largest point displacement) and a figure with each adversarial cloud and its
per-point displacement ``X_adv - X`` drawn as arrows coloured by their direction in the x-y plane,
annotated with the heading error and the x-y error of ICP (as in the paper's figure 4).

Every attack is strict by default: each point's displacement lies in its lambda-ball (models
with the bounded output satisfy this by construction; any other model is projected onto the
balls). ``soft_bound=True`` adds the paper's unprojected output of each model as extra rows
labelled ``"<name> (soft-bound)"``; such rows may move points further than lambda (their
``disp_max`` column shows by how much) and are never drawn in the figure.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from icpbench.analysis.plotting import pyplot, save
from icpbench.attacks.base import Attack
from icpbench.core import registry
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.targets.p2plane import PointToPlaneICP

#: Suffix of the rows of the paper's unprojected (soft-bound) model outputs.
SOFT_SUFFIX = " (soft-bound)"
#: Arrows drawn per figure panel (a fixed, evenly spaced subset of the points).
ARROWS_PER_PANEL = 160


def _attack(name: str, **params: Any) -> Attack:
    """A registered attack set up for ``objects``: the objects ICP preset (d_max 0.3, not the
    lidar default) for attacks that take one, the dataset for attacks that want the context."""
    cls = registry.attacks.get(name)
    if cls.wants_context:
        params = {"dataset": "objects", **params}
    if "icp_preset" in inspect.signature(cls.__init__).parameters:
        params = {"icp_preset": "objects", **params}
    return cls(**params)


def study(models: dict[str, str], budget: float, n_objects: int = 24, n_figure: int = 4,
          baselines: tuple[str, ...] = ("uniform", "normal", "sector"), seed: int = 0,
          soft_bound: bool = False) -> tuple[pd.DataFrame, dict[str, np.ndarray], list]:
    """Run every model (name -> checkpoint) and baseline on ``n_objects`` test objects.

    Args:
        models: name -> generator checkpoint; each runs strict (within the lambda-balls).
        budget: lambda (normalised units: objects have radius 1).
        n_objects, n_figure: objects in the table and in the figure's clouds.
        baselines: registered attacks run beside the models (strict as well).
        seed: dataset and attack seed.
        soft_bound: also run each model without the projection (rows ``name + SOFT_SUFFIX``).

    Returns:
        (rows per (attack, sample) with heading/x/xy errors and the sample's largest point
        displacement, adversarial clouds of the first ``n_figure`` objects per attack
        (n_figure, N, 3) in the map frame plus the clean ones under ``"_clean"``, the samples).
    """
    ds = registry.datasets.get("objects").create(seed=seed, split="test", n_samples=n_objects)
    samples = ds.take(n_objects)
    batch = Batch.from_samples(samples)
    target = PointToPlaneICP("objects")
    attacks: dict[str, Attack] = {"original": _attack("none")}
    for b in baselines:
        attacks[b] = _attack(b, strict=True)
    for name, ckpt in models.items():
        attacks[name] = _attack("generator", checkpoint=ckpt, strict=True)
    if soft_bound:
        for name, ckpt in models.items():
            attacks[name + SOFT_SUFFIX] = _attack("generator", checkpoint=ckpt)
    rows, clouds = [], {}
    for name, atk in attacks.items():
        out = atk.run(batch, budget, surrogate=target, generator=seed)
        reg = target.register(out.scans, batch.maps, batch.T_init)
        e = pose_error_components(reg.T, batch.T_gt)
        for i, s in enumerate(samples):
            rows.append({"attack": name, "sample_id": s.id, "category": s.meta.get("category"),
                         "converged": bool(reg.converged[i]),
                         "heading_err_deg": float(torch.rad2deg(e["yaw_err"][i])),
                         "x_err": float(e["rho_x"][i].abs()), "xy_err": float(e["trans_err_xy"][i]),
                         "disp_max": float(out.stats["disp_max"][i])})
        T = batch.T_gt[:n_figure]
        P = out.scans[:n_figure].to(torch.float64)
        clouds[name] = (P @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]).numpy()
    clean = batch.scans[:n_figure].to(torch.float64)
    clouds["_clean"] = (clean @ batch.T_gt[:n_figure, :3, :3].transpose(1, 2)
                        + batch.T_gt[:n_figure, None, :3, 3]).numpy()
    return pd.DataFrame(rows), clouds, samples


def summary_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Per attack: mean heading, x and x-y errors over converged samples, the largest point
    displacement over all samples (``disp_max``, to compare with lambda) and the sample counts."""
    ok = rows[rows["converged"]]
    t = ok.groupby("attack", sort=False)[["heading_err_deg", "x_err", "xy_err"]].mean()
    t["disp_max"] = rows.groupby("attack", sort=False)["disp_max"].max()
    t["n"] = ok.groupby("attack", sort=False).size()
    t["n_total"] = rows.groupby("attack", sort=False).size()
    return t.reset_index()


def figure(rows: pd.DataFrame, clouds: dict[str, np.ndarray], path: str | Path,
           budget: float | None = None) -> Path:
    """Grid: objects x (original, attacks...); each attacked panel shows the adversarial cloud and
    its displacement arrows (a fixed subset of points, magnified so that lambda is 0.15 units
    long), coloured by their direction in the x-y plane (hsv). Soft-bound rows are not drawn.
    ``budget`` (lambda) defaults to the largest displacement in the drawn clouds."""
    plt = pyplot()

    listed = set(rows["attack"])  # panels need their row (errors to annotate)
    names = [n for n in clouds if n in listed and not n.endswith(SOFT_SUFFIX)]
    clean = clouds["_clean"]
    k = clean.shape[0]
    if budget is None:
        budget = max((float(np.linalg.norm(clouds[n] - clean, axis=-1).max()) for n in names),
                     default=0.0) or 1.0
    mag = 0.15 / budget
    # one row per object: its panels share both axes, so the clouds are drawn at the same scale
    fig, axes = plt.subplots(k, len(names), figsize=(2.6 * len(names), 2.6 * k), squeeze=False,
                             sharex="row", sharey="row")
    ids = list(dict.fromkeys(rows["sample_id"]))[:k]
    for i in range(k):
        step = max(1, clean.shape[1] // ARROWS_PER_PANEL)
        sel = np.arange(0, clean.shape[1], step)
        for j, n in enumerate(names):
            ax = axes[i, j]
            P = clouds[n][i]
            if n == "original":
                ax.scatter(P[:, 0], P[:, 1], s=0.3, c="black")
            else:
                d = P - clean[i]
                ang = np.arctan2(d[sel, 1], d[sel, 0])
                ax.scatter(P[:, 0], P[:, 1], s=0.2, c="0.7")
                ax.quiver(clean[i][sel, 0], clean[i][sel, 1], mag * d[sel, 0], mag * d[sel, 1],
                          ang, cmap="hsv", clim=(-np.pi, np.pi), angles="xy", scale_units="xy",
                          scale=1.0, width=0.006, headwidth=3, headlength=3, headaxislength=2.5)
            r = rows[(rows["attack"] == n) & (rows["sample_id"] == ids[i])].iloc[0]
            ax.text(0.98, 0.98, f"{r['heading_err_deg']:.1f}°", transform=ax.transAxes,
                    ha="right", va="top", fontsize=7)
            ax.text(0.98, 0.02, f"{r['xy_err']:.3f}", transform=ax.transAxes, ha="right",
                    va="bottom", fontsize=7)
            if n != "original" and "disp_max" in r:
                ax.text(0.02, 0.02, f"max |d| {r['disp_max']:.3f}", transform=ax.transAxes,
                        ha="left", va="bottom", fontsize=6)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
            ax.set_xlabel("x [normalised]", fontsize=7)
            if j == 0:
                ax.set_ylabel("y [normalised]", fontsize=7)
            if i == 0:
                ax.set_title(n, fontsize=9)
    fig.suptitle(f"map frame, objects normalised to radius 1, budget λ = {budget:g} (every attack "
                 f"within it); arrows: X_adv - X magnified {mag:g}x, colour = its x-y direction "
                 "(hsv)\ntop right: heading error [deg]; bottom right: x-y translation error "
                 "[normalised]; bottom left: largest point displacement", fontsize=8)
    return save(fig, path, dpi=110)
