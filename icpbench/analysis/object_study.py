"""Object case study (Zhang et al. 2025, §IV-C2, figure 4): how the adversarial-loss weights
shape the learned perturbation.

Generators trained on ``objects`` with the ``theta-only``, ``x-only`` and ``xy`` weights, and the
baselines, attack the same held-out objects. The study writes a per-model table (heading error,
x error, x-y error) and a figure with the original clouds and each adversarial cloud coloured by
the angle of its displacement ``X_adv - X`` in the x-y plane, annotated with the heading error and
the x-y error of ICP (as in the paper's figure 4).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from icpbench.analysis.plotting import pyplot, save
from icpbench.attacks.base import Attack
from icpbench.core import registry
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.targets.p2plane import PointToPlaneICP


def study(models: dict[str, str], budget: float, n_objects: int = 24, n_figure: int = 4,
          baselines: tuple[str, ...] = ("uniform", "normal"), seed: int = 0
          ) -> tuple[pd.DataFrame, dict[str, np.ndarray], list]:
    """Run every model (name -> checkpoint) and baseline on ``n_objects`` test objects.

    Returns (rows per (attack, sample) with heading/x/xy errors, adversarial clouds of the first
    ``n_figure`` objects per attack (n_figure, N, 3) in the map frame, the samples).
    """
    ds = registry.datasets.get("objects")(seed=seed, split="test", n_samples=n_objects)
    samples = ds.take(n_objects)
    batch = Batch.from_samples(samples)
    target = PointToPlaneICP("objects")
    attacks: dict[str, Attack] = {"original": registry.attacks.get("none")()}
    for b in baselines:
        attacks[b] = registry.attacks.get(b)()
    for name, ckpt in models.items():
        attacks[name] = registry.attacks.get("generator")(checkpoint=ckpt)
    for name, ckpt in models.items():  # the soft bound audited: same models, strict projection
        attacks[f"{name} (strict)"] = registry.attacks.get("generator")(checkpoint=ckpt,
                                                                       strict=True)
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
    """Mean heading, x and x-y errors per attack over converged samples."""
    ok = rows[rows["converged"]]
    t = ok.groupby("attack", sort=False)[["heading_err_deg", "x_err", "xy_err", "disp_max"]].mean()
    t["n"] = ok.groupby("attack", sort=False).size()
    return t.reset_index()


def figure(rows: pd.DataFrame, clouds: dict[str, np.ndarray], path: str | Path) -> Path:
    """Grid: objects x (original, attacks...), coloured by displacement angle (hsv)."""
    plt = pyplot()

    names = [n for n in clouds if n != "_clean" and not n.endswith("(strict)")]
    clean = clouds["_clean"]
    k = clean.shape[0]
    # one row per object: its panels share both axes, so the clouds are drawn at the same scale
    fig, axes = plt.subplots(k, len(names), figsize=(2.6 * len(names), 2.6 * k), squeeze=False,
                             sharex="row", sharey="row")
    ids = list(dict.fromkeys(rows["sample_id"]))[:k]
    for i in range(k):
        for j, n in enumerate(names):
            ax = axes[i, j]
            P = clouds[n][i]
            d = P - clean[i]
            ang = np.arctan2(d[:, 1], d[:, 0])
            if n == "original":
                ax.scatter(P[:, 0], P[:, 1], s=0.3, c="black")
            else:
                ax.scatter(P[:, 0], P[:, 1], s=0.3, c=ang, cmap="hsv", vmin=-np.pi, vmax=np.pi)
            r = rows[(rows["attack"] == n) & (rows["sample_id"] == ids[i])].iloc[0]
            ax.text(0.98, 0.98, f"{r['heading_err_deg']:.1f}°", transform=ax.transAxes,
                    ha="right", va="top", fontsize=7)
            ax.text(0.98, 0.02, f"{r['xy_err']:.3f}", transform=ax.transAxes, ha="right",
                    va="bottom", fontsize=7)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
            ax.set_xlabel("x [normalised]", fontsize=7)
            if j == 0:
                ax.set_ylabel("y [normalised]", fontsize=7)
            if i == 0:
                ax.set_title(n, fontsize=9)
    fig.suptitle("map frame, objects normalised to radius 1; colour: direction of X_adv - X in the "
                 "x-y plane (hsv, -180 to 180 deg)\ntop right: heading error [deg]; bottom right: "
                 "x-y translation error [normalised]", fontsize=8)
    return save(fig, path, dpi=110)
