"""Clean convergence of every ICP target with its lidar settings, on clean lidar-sim test scans.

Runs the benchmark with the ``none`` attack (clean scans) for every target with its registered
defaults, then the variants of two black boxes (Open3D point-to-point, small_gicp PLANE_ICP) in a
second run (the runner takes one setting per target name), and writes a table per target:
% converged (status ``ok``), median / mean / 95th percentile of ``trans_err_xy`` (metres), median
and largest iteration count (``-1``: Open3D does not report it) and the mean registration time per
scan (seconds, ``icp_time_s``: batch time over the batch size, one torch / library thread).

Usage (from the repository root; about 15 minutes on two cores)::

    OMP_NUM_THREADS=1 python scripts/clean_convergence.py --out results/clean-convergence

Writes ``OUT/clean_convergence.{md,csv}``, ``OUT/manifest.json`` (commands, commit, versions) and
the two run folders ``OUT/runs/{defaults,variants}`` (each with the runner's ``results.csv`` and
``manifest.json``). Re-running resumes the runs; each run's manifest keeps, per range of rows,
the commit that made them (``provenance``), this script's manifest gathers them, and the table warns
when they differ.
"""

from __future__ import annotations

import argparse
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd

from icpbench.harness.outputs import write_csv, write_file, write_json
from icpbench.harness.report import provenance_notes
from icpbench.harness.results import commits_of, row_makers, software_of

TARGETS = ["p2plane", "p2point", "open3d", "kiss-icp", "small-gicp", "kiss-icp-replica",
           "small-gicp-replica"]
VARIANTS = {"open3d": "mode=point", "small-gicp": "registration_type=PLANE_ICP"}


def _icpbench() -> str:
    exe = Path(sys.executable).with_name("icpbench")
    return str(exe) if exe.exists() else (shutil.which("icpbench") or "icpbench")


def commands(out: Path, samples: int) -> dict[str, list[str]]:
    """The two ``icpbench run`` command lines."""
    common = ["run", "--dataset", "lidar-sim", "--attacks", "none", "--budgets", "1",
              "--samples", str(samples), "--threads", "1"]
    variants = [*common, "--targets", ",".join(VARIANTS), "--out", str(out / "runs" / "variants")]
    for name, kv in VARIANTS.items():
        variants += ["--target-param", f"{name}.{kv}"]
    return {"defaults": [*common, "--targets", ",".join(TARGETS),
                         "--out", str(out / "runs" / "defaults")],
            "variants": variants}


def summarise(rows: pd.DataFrame) -> pd.DataFrame:
    """One line per target (``target`` column already names the variant)."""
    out = []
    for target, g in rows.groupby("target", sort=False):
        e = g["trans_err_xy"]
        out.append({
            "target": target, "scans": len(g),
            "converged_pct": round(100.0 * float((g["status"] == "ok").mean()), 1),
            "median_err_m": round(float(e.median()), 4), "mean_err_m": round(float(e.mean()), 4),
            "p95_err_m": round(float(e.quantile(0.95)), 4),
            "median_iterations": float(g["iterations"].median()),
            "max_iterations": int(g["iterations"].max()),
            "s_per_scan": round(float(g["icp_time_s"].mean()), 3),
        })
    return pd.DataFrame(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/clean-convergence"))
    ap.add_argument("--samples", type=int, default=48)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    cmds = commands(args.out, args.samples)
    t0 = time.time()
    for cmd in cmds.values():
        subprocess.run([_icpbench(), *cmd], check=True)
    parts, provenance = [], {}
    for name in cmds:
        run_dir = args.out / "runs" / name
        provenance[name] = row_makers(run_dir)  # the entries that made its rows
        df = pd.read_csv(run_dir / "results.csv")
        if name == "variants":
            df["target"] = df["target"].map(lambda t: f"{t} ({VARIANTS[t]})")
        parts.append(df)
    rows = pd.concat(parts, ignore_index=True)
    rows.attrs["provenance"] = [e for entries in provenance.values() for e in entries]
    makers = list({software_of(e): e for e in rows.attrs["provenance"]}.values())
    table = summarise(rows)
    write_csv(args.out / "clean_convergence.csv", table, index=False)
    md = ["# Clean convergence of the ICP targets (lidar settings)", "",
          f"{args.samples} clean `lidar-sim` test scans (attack `none`), each target with its "
          "registered defaults (variants: the setting in brackets). `converged_pct`: status `ok`; "
          "errors are `trans_err_xy` in metres; iterations `-1`: not reported by the library; "
          "`s_per_scan`: mean registration time per scan, one thread, on a shared 2-core machine.",
          "", table.to_markdown(index=False), "",
          "Command: `OMP_NUM_THREADS=1 python scripts/clean_convergence.py --out "
          f"{args.out}`, which runs:", ""]
    md += [f"    icpbench {' '.join(c)}" for c in cmds.values()]
    notes = provenance_notes(rows)  # rows made by more than one commit
    md += ["", *notes] if notes else []
    write_file(args.out / "clean_convergence.md", "\n".join(md) + "\n")
    manifest = {"script": "scripts/clean_convergence.py", "samples": args.samples,
                "commands": {k: ["icpbench", *v] for k, v in cmds.items()},
                # the software that made the rows (the runs' own manifests say which rows)
                "git": makers[0].get("git") if len(makers) == 1 else None,
                "versions": makers[0].get("versions") if len(makers) == 1 else None,
                "provenance": provenance, "rows_made_by": commits_of(rows.attrs["provenance"]),
                "machine": {"platform": platform.platform(), "processor": platform.processor()},
                "wall_s_this_invocation": round(time.time() - t0, 1),
                "date": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
    write_json(args.out / "manifest.json", manifest)
    print(table.to_markdown(index=False))


if __name__ == "__main__":
    main()
