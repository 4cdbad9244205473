"""Error versus attack time per scan: the learned attack's place between one-step attacks and PGD.

For each attack configuration (normal, sector, the generator, the generator followed by K = 1, 3, 10
projected gradient steps, PGD with 5, 10 and 30 steps from a random start and with 5 and 10 steps
from the sector attack's output, the iterated analytic attack ``sector-iter`` and PGD-5 from its
output, the same with 2-5 re-linearisations ``sector-iter-K``, ``generator-fast``: the trained
weights with a 4-iteration prior, scripts/derive_fast_generator.py, and ``generator-icp25[+K]``:
the default up to session 11, the same weights with the prior's ICPs capped at 25 iterations;
``generator+K-icp100``: the refinement steps through the 100-iteration evaluation ICP;
``sector-iter-K-icp100``: the default generator's prior, ICPs to 100 iterations, K re-linearisations;
``generator-keep-prior``: the default with ``keep_prior``; ``...-reuseR``: the same with the
surrogate ICPs' approximate correspondences, rows kept while a point moves less than R cm) runs
``icpbench run`` on the same lidar-sim test scans (default: the first 48 of Table 1's test passes)
at lambda = 1 and 4 m, target p2plane (lidar preset, 100 iterations), into ``OUT/runs/<config>/``
(resumable: re-running the command continues where it stopped), then writes

* ``OUT/frontier.csv``: per configuration and budget, the mean translation error over all runs
  at their final error (``err_all_m``) and over converged runs (``err_conv_m``), the share converged,
  the mean attack wall time per scan (``attack_s``, one torch thread; rows run under different
  machine loads compare only roughly) and the mean ratio to PGD-30's error;
* ``OUT/frontier.png``: error versus attack time per scan (log axis), one panel per budget.

    python scripts/frontier.py --out results/frontier            # ~1-2 h on 2 cores
    python scripts/frontier.py --samples 4 --out runs/frontier-smoke --only normal,generator
    python scripts/frontier.py --out results/frontier --summarise-only   # tables from the folders
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pandas as pd

_ICP25 = "icpbench/checkpoints/lidar-sim-icp25/generator.pt"
#: name suffix -> attack params of the generator followed by K projected gradient steps
_REFINE: dict[str, list[str]] = {"": [], **{f"+{k}": [f"generator.refine_steps={k}"] for k in (1, 3, 10)}}
#: the same steps through the evaluation ICP's 100 iterations (the default's prior cap) instead of
#: the 25-iteration training surrogate: the best-iterate rule then compares the errors that are
#: evaluated, so refinement cannot lower the plain generator's error on any scan
_REFINE_100 = {f"{s}-icp100": [*p, "generator.refine_icp_iterations=100"]
               for s, p in _REFINE.items() if s}



def _warm_start(iterations: int) -> list[str]:
    """PGD params of a start from sector-iter-<iterations>-icp100-reuse5."""
    return ["pgd.init=sector-iter", f"pgd.init_params={{iterations: {iterations}, "
            "icp_iterations: 100, icp_nn_reuse: 0.05}"]


#: name -> (attack, [attack params]); the generator's refinement uses the same surrogate as PGD.
CONFIGS: dict[str, tuple[str, list[str]]] = {
    "normal": ("normal", []),
    "sector": ("sector", []),
    # the default lidar-sim generator (since session 12: the trained weights with the prior's
    # surrogate ICPs run to the lidar cap, 100; session 11 ran it as "generator-icp100")
    **{f"generator{s}": ("generator", p) for s, p in _REFINE.items()},
    **{f"generator{s}": ("generator", p) for s, p in _REFINE_100.items()},
    # the default, per scan the better of its prior's attack and the corrected output (surrogate)
    "generator-keep-prior": ("generator", ["generator.keep_prior=true"]),
    # the default with its prior's approximate correspondence search (rows kept while a point moves
    # less than R cm since its last query; GeneratorConfig.prior_icp_nn_reuse)
    **{f"generator-reuse{r}": ("generator", [f"generator.prior_icp_nn_reuse={r / 100:g}"])
       for r in (2, 5)},
    # the default up to session 11: the same weights, prior ICPs capped at 25 (lidar-sim-icp25)
    **{f"generator-icp25{s}": ("generator", [f"generator.checkpoint={_ICP25}", *p])
       for s, p in _REFINE.items()},
    # the trained weights with a 4-iteration prior (scripts/derive_fast_generator.py)
    "generator-fast": ("generator",
                       ["generator.checkpoint=icpbench/checkpoints/lidar-sim-fast/generator.pt"]),
    # the same recipe trained with that 4-iteration prior (scripts/train_lidar.sh, PRIOR_ITERATIONS=4)
    "generator-iter4": ("generator",
                        ["generator.checkpoint=icpbench/checkpoints/lidar-sim-iter4/generator.pt"]),
    "pgd-5": ("pgd", ["pgd.steps=5"]),
    "pgd-10": ("pgd", ["pgd.steps=10"]),
    "pgd-30": ("pgd", ["pgd.steps=30"]),
    # the oracle with its surrogate's approximate correspondences (ICPConfig.nn_reuse_m, 5 cm)
    "pgd-30-reuse5": ("pgd", ["pgd.steps=30", "pgd.icp_nn_reuse=0.05"]),
    # beyond the list: PGD warm-started from the sector attack's output (cheaper oracle)
    "pgd-5-sector": ("pgd", ["pgd.steps=5", "pgd.init=sector"]),
    "pgd-10-sector": ("pgd", ["pgd.steps=10", "pgd.init=sector"]),
    # the iterated analytic attack (8 re-linearisations) and PGD from its output
    "sector-iter": ("sector-iter", []),
    # the same with fewer re-linearisations (the cost / error trade-off of the generator's prior)
    **{f"sector-iter-{k}": ("sector-iter", [f"sector-iter.iterations={k}"]) for k in (2, 3, 4, 5)},
    # the default generator's prior (surrogate ICPs to 100 iterations) with 2-8 re-linearisations
    **{f"sector-iter-{k}-icp100": ("sector-iter", [f"sector-iter.iterations={k}",
                                                   "sector-iter.icp_iterations=100"])
       for k in (2, 3, 4, 8)},
    # the same with the surrogate's approximate correspondence search (rows kept while a point
    # moves less than R cm since its last query; ICPConfig.nn_reuse_m)
    **{f"sector-iter-{k}-icp100-reuse{r}": ("sector-iter", [
        f"sector-iter.iterations={k}", "sector-iter.icp_iterations=100",
        f"sector-iter.icp_nn_reuse={r / 100:g}"]) for k in (2, 3, 4, 8) for r in (2, 5, 10)},
    "pgd-5-sector-iter": ("pgd", ["pgd.steps=5", "pgd.init=sector-iter"]),
    # PGD-K warm-started from sector-iter-J-icp100-reuse5, its steps through the 100-iteration
    # surrogate on the same correspondences with the implicit gradient ("-s25": through PGD's own
    # 25-iteration unrolled surrogate instead)
    **{f"pgd-{k}-sector-iter-{j}-icp100-reuse5": ("pgd", [
        f"pgd.steps={k}", *_warm_start(j), "pgd.icp_iterations=100", "pgd.icp_nn_reuse=0.05",
        "pgd.backprop=implicit"]) for k, j in ((1, 8), (2, 8), (3, 4), (5, 4))},
    # the registered cheaper oracle (its defaults are pgd-2-sector-iter-8-icp100-reuse5's settings)
    "pgd-warm": ("pgd-warm", []),
    "pgd-3-sector-iter-8-icp100-reuse5-s25": ("pgd", ["pgd.steps=3", *_warm_start(8)]),
}

#: the lines of the plot: configurations that differ only in their number of steps.
FAMILIES: dict[str, list[str]] = {
    **{g: [g + s for s in _REFINE] for g in ("generator", "generator-icp25")},
    "generator-refine100": ["generator", *(f"generator{s}" for s in _REFINE_100)],
    "pgd": ["pgd-5", "pgd-10", "pgd-30"],
    "pgd-sector": ["pgd-5-sector", "pgd-10-sector"],
    "sector-iter": ["sector-iter", "pgd-5-sector-iter"],
    "sector-iter-k": ["sector-iter-2", "sector-iter-3", "sector-iter-4", "sector-iter-5", "sector-iter"],
    "sector-iter-k-icp100": [f"sector-iter-{k}-icp100" for k in (2, 3, 4, 8)],
    "sector-iter-k-icp100-reuse5": [f"sector-iter-{k}-icp100-reuse5" for k in (2, 3, 4, 8)],
    # the cheaper oracle: its start, then 1 and 2 PGD steps (pgd-warm = 2)
    "pgd-sector-iter-8": ["sector-iter-8-icp100-reuse5", "pgd-1-sector-iter-8-icp100-reuse5",
                          "pgd-2-sector-iter-8-icp100-reuse5"],
}


def run_config(name: str, out: Path, samples: int, budgets: str, extra: list[str],
               cli: list[str]) -> Path:
    """Run (or resume) one configuration into ``out/runs/name``; return that folder."""
    attack, params = CONFIGS[name]
    folder = out / "runs" / name
    cmd = [*cli, "run", "--dataset", "lidar-sim", "--attacks", attack, "--targets", "p2plane",
           "--budgets", budgets, "--samples", str(samples), "--batch-size", "4",
           "--out", str(folder)]
    for p in params:
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
    for ax, lam in zip(axes[0], budgets, strict=True):
        sub = res[res["budget_m"] == lam]
        for fam, style in (("generator", "o-"), ("generator-refine100", "o--"),
                           ("generator-icp25", "o:"), ("pgd", "s--"),
                           ("pgd-sector", "d:"), ("sector-iter", "v-."), ("sector-iter-k", "x:"),
                           ("sector-iter-k-icp100", "x-"), ("sector-iter-k-icp100-reuse5", "+-"),
                           ("pgd-sector-iter-8", "*-")):
            # each family in the order of CONFIGS (more steps), not of the noisy measured time
            f = sub[sub["config"].isin(FAMILIES[fam])]
            f = f.sort_values("config", key=lambda c: c.map(FAMILIES[fam].index))
            if not f.empty:  # (a folder with only some configurations: no empty legend rows)
                ax.plot(f["attack_s"], f["err_all_m"], style, label=fam)
        in_family = {c for members in FAMILIES.values() for c in members}
        for r in sub.itertuples():
            ax.annotate(r.config, (r.attack_s, r.err_all_m), fontsize=8, xytext=(3, 3),
                        textcoords="offset points")
            if r.config in ("normal", "sector", "generator-fast", "generator-iter4",
                            "generator-keep-prior", "generator-reuse5"):
                ax.plot([r.attack_s], [r.err_all_m], "*" if r.config.startswith("generator") else "^",
                        label=r.config)
            elif r.config not in in_family:  # any other configuration: an unlabelled dot
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
    res.to_csv(out / "frontier.csv", index=False, float_format="%.4g")
    plot(res, out / "frontier.png")
    print(res.to_string(index=False, float_format=lambda v: f"{v:.3g}"))


if __name__ == "__main__":
    main()
