"""Error versus attack time per scan: where each attack configuration sits between the one-step
attacks and the PGD oracle, and what a cheaper setting of the same attack costs in error.

The configurations are data: ``scripts/frontier.yaml`` (name -> attack, its settings, and the plot
family it belongs to). Each runs ``icpbench run`` on the same lidar-sim test scans (default: the
first 48 of Table 1's test passes) at lambda = 1 and 4 m, target p2plane (lidar preset, 100
iterations), into ``OUT/runs/<config>/`` (resumable: re-running the command continues where it
stopped; each configuration runs alone, so its attack time is what it costs on its own), then writes

* ``OUT/frontier.csv``: per configuration and budget, the mean translation error over all runs
  at their final error (``err_all_m``) and over converged runs (``err_conv_m``), the share converged,
  the mean attack wall time per scan (``attack_s``, one torch thread) and the ratio to PGD-30's error;
* ``OUT/frontier.png``: error versus attack time per scan (log axis), one panel per budget.

    python scripts/frontier.py --out results/frontier --run-arg=--executor --run-arg=ray
    python scripts/frontier.py --samples 4 --out runs/frontier-smoke --only normal,generator
    python scripts/frontier.py --out results/frontier --summarise-only   # tables from the folders
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from icpbench.harness.outputs import write_csv

CONFIG_FILE = Path(__file__).with_name("frontier.yaml")


def load_configs(path: Path = CONFIG_FILE) -> dict[str, dict[str, Any]]:
    """The configurations of ``path``: name -> ``{"attack": str, "params": dict, "family": str
    | None}``, in file order.

    Raises:
        ValueError: an entry without an attack, or with unknown keys.
    """
    raw = yaml.safe_load(path.read_text()) or {}
    out = {}
    for name, entry in raw.items():
        entry = dict(entry or {})
        unknown = set(entry) - {"attack", "params", "family"}
        if "attack" not in entry or unknown:
            raise ValueError(f"{path}: configuration {name!r} needs 'attack' and may have 'params' "
                             f"and 'family' (unknown: {sorted(unknown)})")
        out[str(name)] = {"attack": str(entry["attack"]), "params": dict(entry.get("params") or {}),
                          "family": entry.get("family")}
    return out


def attack_args(config: dict[str, Any]) -> list[str]:
    """``--attack-param`` values of a configuration (``ATTACK.KEY=VALUE``; mappings in YAML flow
    style, as the CLI reads them)."""
    out = []
    for k, v in config["params"].items():
        value = yaml.safe_dump(v, default_flow_style=True).strip().removesuffix("...").strip()
        out.append(f"{config['attack']}.{k}={value}")
    return out


CONFIGS = load_configs()


def run_config(name: str, out: Path, samples: int, budgets: str, extra: list[str],
               cli: list[str]) -> Path:
    """Run (or resume) one configuration into ``out/runs/name``; return that folder."""
    config = CONFIGS[name]
    folder = out / "runs" / name
    cmd = [*cli, "run", "--dataset", "lidar-sim", "--attacks", config["attack"], "--targets",
           "p2plane", "--budgets", budgets, "--samples", str(samples), "--batch-size", "4",
           "--out", str(folder)]
    for p in attack_args(config):
        cmd += ["--attack-param", p]
    cmd += extra
    print(f"[frontier] {name}: {' '.join(cmd)}", flush=True)
    subprocess.run(cmd, check=True)
    return folder


def summarise(out: Path, names: list[str]) -> pd.DataFrame:
    """Per configuration and budget: errors, convergence and attack time per scan.

    Configurations without a ``out/runs/<name>/results.csv`` are skipped.
    """
    rows = []
    for name in names:
        csv = out / "runs" / name / "results.csv"
        if not csv.is_file():
            continue
        df = pd.read_csv(csv)
        df = df[df["status"] != "error"]
        for lam, g in df.groupby("budget"):
            conv = g[g["converged"].astype(bool)]
            rows.append({"config": name, "budget_m": float(lam), "n": len(g),
                         "err_all_m": g["trans_err_xy"].mean(),
                         "err_conv_m": conv["trans_err_xy"].mean(),
                         "converged": len(conv) / max(len(g), 1),
                         "attack_s": g["attack_time_s"].mean(),
                         "disp_max_m": g["disp_max"].max()})
    res = pd.DataFrame(rows)
    if res.empty:
        return res
    ref = res[res["config"] == "pgd-30"].set_index("budget_m")["err_all_m"]
    res["vs_pgd30"] = [r.err_all_m / ref.get(r.budget_m, float("nan")) for r in res.itertuples()]
    return res


def plot(res: pd.DataFrame, path: Path) -> None:
    """Error versus attack time per scan, one panel per budget."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from icpbench.analysis.plotting import pyplot, save

    plt = pyplot()
    budgets = sorted(res["budget_m"].unique())
    fig, axes = plt.subplots(1, len(budgets), figsize=(6 * len(budgets), 4.5), squeeze=False)
    families: dict[str, list[str]] = {}
    for name, c in CONFIGS.items():
        if c["family"]:
            families.setdefault(c["family"], []).append(name)
    styles = ["o-", "s--", "v-.", "x:", "d-", "*-"]
    for ax, lam in zip(axes[0], budgets, strict=True):
        sub = res[res["budget_m"] == lam]
        for (fam, members), style in zip(families.items(), styles * 4, strict=False):
            # each family in the order of the file, not of the measured time
            f = sub[sub["config"].isin(members)]
            f = f.sort_values("config", key=lambda c: c.map(members.index))
            if not f.empty:
                ax.plot(f["attack_s"], f["err_all_m"], style, label=fam)
        for r in sub.itertuples():
            ax.annotate(r.config, (r.attack_s, r.err_all_m), fontsize=8, xytext=(3, 3),
                        textcoords="offset points")
            if not CONFIGS.get(r.config, {}).get("family"):
                ax.plot([r.attack_s], [r.err_all_m], "k.")
        ax.set_xscale("log")
        ax.set_xlabel("attack wall time per scan [s] (one torch thread)")
        ax.set_ylabel("mean translation error [m]")
        ax.set_title(f"λ = {lam:g} m")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="results/frontier")
    ap.add_argument("--samples", type=int, default=48)
    ap.add_argument("--budgets", default="1,4")
    ap.add_argument("--only", default=",".join(CONFIGS), help="comma-separated configurations")
    ap.add_argument("--run-arg", action="append", default=[],
                    help="extra argument passed to every `icpbench run` (repeatable)")
    ap.add_argument("--summarise-only", action="store_true",
                    help="run nothing; rewrite frontier.csv/png from the run folders present")
    ap.add_argument("--cli", default="icpbench",
                    help="command that runs the icpbench CLI (default: icpbench)")
    args = ap.parse_args()
    names = [n for n in args.only.split(",") if n]
    unknown = [n for n in names if n not in CONFIGS]
    if unknown:
        sys.exit(f"error: unknown configuration(s) {unknown}; valid: {', '.join(CONFIGS)}")
    out = Path(args.out)
    if not args.summarise_only:
        for n in names:
            run_config(n, out, args.samples, args.budgets, args.run_arg, args.cli.split())
    # the summary covers every configuration run so far, not only those of this call
    res = summarise(out, list(CONFIGS))
    if res.empty:
        sys.exit(f"error: no run folders with results under {out / 'runs'}")
    write_csv(out / "frontier.csv", res, index=False, float_format="%.4g")
    plot(res, out / "frontier.png")
    print(res.to_string(index=False, float_format=lambda v: f"{v:.3g}"))


if __name__ == "__main__":
    main()
