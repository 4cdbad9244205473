"""Picture of the ``spoof`` attack on one scan: the attacked scan at the true pose and at the pose
the target returns.

Runs ``spoof`` (its defaults) against one target on one ``lidar-sim`` test scan and writes, into
``--out``: ``spoof.png`` (top view, map frame: left, the clean and the attacked scan at the true
pose; right, the attacked scan at the target's estimate, its points coloured by whether they lie
on the map there: the surfaces along the shift do, the ones across it, which could move only
lambda, are out-voted) and
``manifest.json`` (settings, errors, commit).

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python scripts/spoof_figure.py --sample 17 --target p2point \
        --out results/spoof-example
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

#: A point "lies on the map" when its nearest map point is closer than this (metres; the lidar-sim
#: maps are 0.25 m voxel samples).
ON_MAP_M = 0.25
#: Points lower than this below the sensor (the road, curbs) are not drawn.
SHOWN_BELOW_SENSOR_M = 0.5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", type=int, default=17, help="index in the lidar-sim test split")
    ap.add_argument("--target", default="p2point", help="target registry name")
    ap.add_argument("--budget", type=float, default=1.0, help="lambda in metres")
    ap.add_argument("--half-width", type=float, default=35.0, help="metres shown around the sensor")
    ap.add_argument("--out", type=Path, default=Path("results/spoof-example"))
    args = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from icpbench.attacks.spoof import SpoofAttack
    from icpbench.core import registry
    from icpbench.core.types import Batch
    from icpbench.harness.outputs import save_figure, write_json
    from icpbench.harness.runner import build_target, git_commit, package_versions
    from icpbench.targets.oracle import QueryOracle

    torch.set_num_threads(1)
    ds = registry.datasets.get("lidar-sim").create(seed=0, split="test")
    sample = ds[args.sample]
    batch = Batch.from_samples([sample])
    target = build_target(args.target, "lidar")
    oracle = QueryOracle.prepared(target, batch)
    out = SpoofAttack().run(batch, args.budget, oracle=oracle, generator=0)
    adv = out.scans[0].to(torch.float64).numpy()
    T_hat, err, _ = oracle.register(adv[None])
    uniform = oracle.errors(batch.scans + args.budget * torch.tensor([1.0, 0.0, 0.0]))
    T_gt = batch.T_gt[0].numpy()

    def world(points: np.ndarray, T: np.ndarray) -> np.ndarray:
        return points @ T[:3, :3].T + T[:3, 3]

    clean_w = world(batch.scans[0].numpy(), T_gt)
    adv_true, adv_est = world(adv, T_gt), world(adv, T_hat[0])
    c = T_gt[:2, 3]
    m = sample.map
    floor = T_gt[2, 3] - SHOWN_BELOW_SENSOR_M  # the ground and the curbs are left out of the view
    keep = (np.abs(m[:, :2] - c) < args.half_width).all(axis=1) & (m[:, 2] > floor)

    fig, axes = plt.subplots(1, 2, figsize=(12, 6), sharex=True, sharey=True)
    for ax in axes:
        ax.scatter(m[keep, 0], m[keep, 1], s=4, c="0.7",
                   label=f"map (from {SHOWN_BELOW_SENSOR_M:g} m below the sensor up)")
        ax.plot(*c, "k+", ms=14, mew=2, label="true sensor position")
        ax.set_aspect("equal")
        ax.set_xlim(c[0] - args.half_width, c[0] + args.half_width)
        ax.set_ylim(c[1] - args.half_width, c[1] + args.half_width)
        ax.set_xlabel("x [m] (map frame)")
    up = clean_w[:, 2] > floor
    axes[0].scatter(clean_w[up, 0], clean_w[up, 1], s=0.4, c="tab:blue", label="clean scan")
    axes[0].scatter(adv_true[up, 0], adv_true[up, 1], s=0.4, c="tab:red",
                    label=f"spoofed scan (every point within {args.budget:g} m)")
    axes[0].set_title("at the true pose")
    axes[0].set_ylabel("y [m] (map frame)")
    on = batch.maps[0].query(adv_est)[0] < ON_MAP_M
    for sel, colour, what in ((on, "tab:red", "on"), (~on, "tab:orange", "off")):
        axes[1].scatter(adv_est[up & sel, 0], adv_est[up & sel, 1], s=0.4, c=colour,
                        label=f"spoofed scan, {what} the map (nearest map point "
                              f"{'<' if what == 'on' else '>='} {ON_MAP_M:g} m)")
    axes[1].plot(*T_hat[0, :2, 3], "rx", ms=12, mew=2, label="estimated sensor position")
    axes[1].set_title(f"at the pose {args.target} returns: {err[0]:.2f} m off "
                      f"(uniform translation: {uniform[0]:.2f} m)")
    for ax in axes:
        leg = ax.legend(loc="lower left", fontsize=7)
        for h in leg.legend_handles:
            if hasattr(h, "set_sizes"):  # the scatter dots, readable in the legend
                h.set_sizes([20])
    fig.suptitle(f"spoof on {sample.id}, λ = {args.budget:g} m: the scan made to agree with the "
                 f"map, where its points can reach it, at a pose shifted by "
                 f"{float(out.extra['spoof_offset_m'][0]):.2f} m")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    save_figure(fig, args.out / "spoof.png", dpi=110)
    plt.close(fig)
    write_json(args.out / "manifest.json", {
        "command": "python scripts/spoof_figure.py " + " ".join(
            f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
        "sample": sample.id, "target": args.target, "budget_m": args.budget,
        "spoof_error_m": float(err[0]), "spoof_offset_m": float(out.extra["spoof_offset_m"][0]),
        "uniform_error_m": float(uniform[0]), "queries": int(out.extra["queries"][0]),
        "frac_over_budget": float(out.stats["frac_over_budget"][0]),
        "git": git_commit(), "versions": package_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})


if __name__ == "__main__":
    main()
