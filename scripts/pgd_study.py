"""What do PGD solutions look like next to the generator's and the sector attack's? (issue 14 study)

For K lidar-sim scans of the validation pass (pass 7, disjoint from the training passes 3-6 and the
Table 1 passes 1-2) and budgets lambda, runs the sector attack, the shipped generator and PGD (the
oracle, default settings) and measures, per attack:

* ``err``: ICP translation error (p2plane, lidar preset, all runs at their final error), metres;
* ``full``: share of points moved by >= 0.95 lambda (does it spend the budget?);
* ``normal``: mean |cos| between a point's displacement and its map normal (sensor frame): how
  much of the move changes the point-to-plane residual;
* ``agree_sector``: share of associated points whose signed normal component has the sign the
  sector attack picks (sign of the one-step sensitivity of its worst axis), among points moved
  along the normal by > 0.5 lambda;
* ``mode_agree_sector``: ``max(agree, 1 - agree)``: the sector attack maximises ``+rho_j``; the
  mirrored sign pattern, which drives ``-rho_j``, is an equally strong attack;
* ``coherence``: mean cosine between a point's displacement and those of its 8 nearest scan
  neighbours (1: locally rigid groups; 0: random);
* ``wall_s``: attack time per scan.

Writes ``OUT/study.csv`` (one row per scan, budget, attack), ``OUT/fields.npz`` (displacements of
the first scan) and ``OUT/pgd_study.png`` (top view of the first scan's displacement fields,
coloured by the signed normal component), and prints a summary by attack, budget and stretch.

    python scripts/pgd_study.py --samples 8 --budgets 1,4 --out docs/figures/pgd-study
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from scipy.spatial import cKDTree

from icpbench.analysis import sector_math as sector
from icpbench.core import registry
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.targets.p2plane import PointToPlaneICP


def field_stats(clean: np.ndarray, adv: np.ndarray, lam: float, normals: np.ndarray,
                valid: np.ndarray, sector_sign: np.ndarray | None) -> dict[str, float]:
    """Statistics of one displacement field (N, 3) (see the module docstring)."""
    d = adv - clean
    mag = np.linalg.norm(d, axis=1)
    out = {"full": float(np.mean(mag >= 0.95 * lam)), "disp_mean_frac": float(mag.mean() / lam)}
    dn = np.einsum("ij,ij->i", d, normals)
    cos = np.abs(dn) / np.maximum(mag, 1e-12)
    out["normal"] = float(cos[valid & (mag > 1e-6)].mean()) if np.any(valid & (mag > 1e-6)) else np.nan
    if sector_sign is not None:
        m = valid & (np.abs(dn) > 0.5 * lam)
        a = float(np.mean(np.sign(dn[m]) == sector_sign[m])) if m.any() else np.nan
        out["agree_sector"] = a
        out["mode_agree_sector"] = max(a, 1.0 - a)  # the mirrored pattern (-x for +x) is as bad
        out["along_normal_frac"] = float(np.mean(m))
    tree = cKDTree(clean)
    _, nb = tree.query(clean, k=9)
    u = d / np.maximum(mag, 1e-12)[:, None]
    out["coherence"] = float(np.mean(np.einsum("ij,ikj->ik", u, u[nb[:, 1:]])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--budgets", default="1,4")
    ap.add_argument("--pgd-steps", type=int, default=30)
    ap.add_argument("--out", default="docs/figures/pgd-study")
    ap.add_argument("--plot-only", action="store_true",
                    help="redraw the figure from OUT/fields.npz (no attacks are run)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    budgets = [float(b) for b in args.budgets.split(",")]
    ds = registry.datasets.get("lidar-sim")(seed=0, split="test", n_passes=7, test_passes=[7])
    samples = ds.take(args.samples)
    if args.plot_only:
        f = np.load(out / "fields.npz")
        fields = {k: f[k] for k in f.files if k != "scan"}
        plot_fields(f["scan"], fields, budgets, n_sensor_first(samples[0]), out / "pgd_study.png")
        return
    attacks = {
        "sector": registry.attacks.get("sector")(),
        "generator": registry.attacks.get("generator")(dataset="lidar-sim"),
        "pgd": registry.attacks.get("pgd")(steps=args.pgd_steps),
    }
    surrogate = PointToPlaneICP("lidar-train")
    target = PointToPlaneICP("lidar")
    rows, fields = [], {}
    for si, s in enumerate(samples):
        batch = Batch.from_samples([s])
        scan = s.scan.astype(np.float64)
        assoc = sector.associate(scan, s.T_gt, batch.maps[0], 5.0)
        R = s.T_gt[:3, :3]
        n_sensor = assoc.normals_map @ R  # R^T n per row
        for lam in budgets:
            sec_sign = None
            for name, atk in attacks.items():
                t0 = time.perf_counter()
                res = atk.run(batch, lam, surrogate=surrogate, generator=0)
                wall = time.perf_counter() - t0
                adv = res.scans[0].double().numpy()
                if name == "sector":
                    dn = np.einsum("ij,ij->i", adv - scan, n_sensor)
                    sec_sign = np.sign(dn)
                reg = target.register(res.scans.double(), batch.maps, batch.T_init)
                e = pose_error_components(reg.T, batch.T_gt)
                st = field_stats(scan, adv, lam, n_sensor, assoc.valid,
                                 None if name == "sector" else sec_sign)
                rows.append({"sample": s.id, "stretch": s.meta.get("stretch"), "budget_m": lam,
                             "attack": name, "err": float(e["trans_err_xy"][0]),
                             "converged": bool(reg.converged[0]), "wall_s": wall, **st})
                if si == 0:
                    fields[f"{name}_l{lam:g}"] = (adv - scan).astype(np.float32)
                print(f"{s.id} λ={lam:g} {name:9s} err {rows[-1]['err']:6.2f} m  "
                      f"full {st['full']:.2f} normal {st['normal']:.2f} coh {st['coherence']:.2f}  "
                      f"{wall:5.1f} s", flush=True)
    df = pd.DataFrame(rows)
    df.to_csv(out / "study.csv", index=False)
    s0 = samples[0]
    np.savez_compressed(out / "fields.npz", scan=s0.scan, **fields)
    cols = ["err", "full", "normal", "mode_agree_sector", "along_normal_frac", "coherence", "wall_s"]
    print(df.groupby(["budget_m", "attack"])[cols].mean().round(3).to_string())
    print(df.groupby(["budget_m", "stretch", "attack"])["err"].mean().round(2).to_string())
    plot_fields(s0.scan, fields, budgets, n_sensor_first(samples[0]), out / "pgd_study.png")


def n_sensor_first(s) -> np.ndarray:
    """Map normals of the first sample's scan points in its sensor frame (N, 3)."""
    b = Batch.from_samples([s])
    a = sector.associate(s.scan.astype(np.float64), s.T_gt, b.maps[0], 5.0)
    return a.normals_map @ s.T_gt[:3, :3]


def plot_fields(scan: np.ndarray, fields: dict[str, np.ndarray], budgets: list[float],
                normals: np.ndarray, path: Path) -> None:
    """Top view (x forward, y left; metres) of each attack's field, coloured by d.n / lambda."""
    from icpbench.analysis.plotting import pyplot, save

    plt = pyplot()
    names = ["sector", "generator", "pgd"]
    fig, axes = plt.subplots(len(budgets), 3, figsize=(15, 5 * len(budgets)), squeeze=False)
    for r, lam in enumerate(budgets):
        for c, name in enumerate(names):
            ax = axes[r, c]
            d = fields[f"{name}_l{lam:g}"]
            dn = np.einsum("ij,ij->i", d, normals) / lam
            keep = np.abs(scan[:, 0]) < 40
            sc = ax.scatter(scan[keep, 0], scan[keep, 1], c=dn[keep], cmap="coolwarm", vmin=-1,
                            vmax=1, s=2)
            ax.set_title(f"{name}, λ = {lam:g} m")
            ax.set_xlabel("x (forward) [m]")
            ax.set_ylabel("y (left) [m]")
            ax.set_aspect("equal")
            ax.set_ylim(-40, 40)
            fig.colorbar(sc, ax=ax, shrink=0.8, label="displacement along map normal [fraction of λ]")
    save(fig, path)


if __name__ == "__main__":
    main()
