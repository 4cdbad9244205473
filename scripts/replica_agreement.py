"""Agreement of each black-box ICP target with its differentiable replica, clean and attacked.

For every pair (black box -> ``Target.replica()``) and every condition (clean scans, and the
``uniform``, ``normal`` and ``sector`` attacks at lambda = 1 m, seed 0, as the runner runs them),
registers the same scan with both from the same initial pose and records the pose difference
``log(T_replica T_blackbox^-1)``: its translation norm (metres) and rotation angle (degrees), plus
each one's error against the ground truth, status, iterations and time.

Pairs: ``open3d`` (point-to-plane) -> ``p2plane``; ``open3d`` with ``mode=point`` -> ``p2point``;
``kiss-icp`` -> ``kiss-icp-replica``; ``small-gicp`` (GICP) -> ``small-gicp-replica``; all with
their registered lidar defaults.

Usage (from the repository root; resumable, rows are appended per scan, and rows made by an
earlier commit keep it in the manifest's ``provenance``; the table warns when they differ)::

    OMP_NUM_THREADS=1 python scripts/replica_agreement.py --samples 24 --out results/replica-agreement

Writes ``OUT/agreement.csv`` (one row per pair x condition x scan), ``OUT/summary.csv`` and
``OUT/agreement.md`` (median and 95th percentile of the differences per pair and condition) and
``OUT/manifest.json``.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.datasets.lidar_sim import LidarSimDataset
from icpbench.harness.outputs import write_csv, write_file, write_json
from icpbench.harness.report import provenance_notes
from icpbench.harness.results import resume_provenance, row_makers
from icpbench.harness.runner import build_attack, build_target, software

#: pair name -> (black-box entry point, its settings)
PAIRS: dict[str, tuple[str, dict[str, Any]]] = {
    "open3d->p2plane": ("open3d", {}),
    "open3d(point)->p2point": ("open3d", {"mode": "point"}),
    "kiss-icp->kiss-icp-replica": ("kiss-icp", {}),
    "small-gicp->small-gicp-replica": ("small-gicp", {}),
}
CONDITIONS = ("none", "uniform", "normal", "sector")
BUDGET_M = 1.0
ROWS_FILE = "agreement.csv"


def _row_key(r: dict[str, Any]) -> tuple[str, str, str]:
    return (r["pair"], r["attack"], r["sample_id"])


def summarise(rows: pd.DataFrame) -> pd.DataFrame:
    """Median and 95th percentile of the translation / rotation differences per pair and attack."""
    out = []
    for (pair, attack), g in rows.groupby(["pair", "attack"], sort=False):
        out.append({
            "pair": pair, "attack": attack, "scans": len(g),
            "dt_median_mm": round(1e3 * float(g["dt_m"].median()), 4),
            "dt_p95_mm": round(1e3 * float(g["dt_m"].quantile(0.95)), 4),
            "dt_max_mm": round(1e3 * float(g["dt_m"].max()), 4),
            "dr_median_deg": round(float(g["dr_deg"].median()), 5),
            "dr_p95_deg": round(float(g["dr_deg"].quantile(0.95)), 5),
            "both_ok": int(((g["status_bb"] == "ok") & (g["status_rep"] == "ok")).sum()),
            "err_bb_median_m": round(float(g["err_bb_m"].median()), 4),
            "err_rep_median_m": round(float(g["err_rep_m"].median()), 4),
            "s_bb": round(float(g["time_bb_s"].mean()), 3),
            "s_rep": round(float(g["time_rep_s"].mean()), 3),
        })
    return pd.DataFrame(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/replica-agreement"))
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    try:
        run(args)
    except InputError as exc:
        raise SystemExit(f"error: {exc}") from None


def run(args: argparse.Namespace) -> None:
    """Register, append the rows not yet in ``args.out`` and write the summary and manifest."""
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    csv = args.out / ROWS_FILE
    done = set()
    if csv.exists():
        done = {_row_key(r) for r in pd.read_csv(csv).to_dict("records")}
    samples = LidarSimDataset.create(seed=0, split="test").take(args.samples)
    index = {s.id: MapIndex(s.map, s.map_normals) for s in samples}
    pairs = {}
    for name, (ep, params) in PAIRS.items():
        bb = build_target(ep, "lidar", params)
        pairs[name] = (bb, bb.replica(), {})
    attacks = {a: build_attack(a, strict=False) for a in CONDITIONS}
    manifest = {"script": "scripts/replica_agreement.py", "samples": args.samples,
                "seed": args.seed, "budget_m": BUDGET_M, "conditions": list(CONDITIONS),
                "pairs": {k: {"black_box": v[0], "params": v[1],
                              "replica": pairs[k][1].name,
                              "black_box_settings": pairs[k][0].settings(),
                              "replica_settings": pairs[k][1].settings()}
                          for k, v in PAIRS.items()},
                **resume_provenance(args.out, ROWS_FILE, software()),
                "machine": {"platform": platform.platform(), "processor": platform.processor()},
                "finished": False}
    write_json(args.out / "manifest.json", manifest)  # before any row, so each row has its commit
    for attack_name, attack in attacks.items():
        for s in samples:
            todo = [p for p in pairs if (p, attack_name, s.id) not in done]
            if not todo:
                continue
            batch = Batch.from_samples([s], maps=[index[s.id]])
            adv = attack.run(batch, BUDGET_M, generator=args.seed).scans.detach().double()
            rows = []
            for pair in todo:
                bb, rep, prepared = pairs[pair]
                if s.id not in prepared:
                    prepared[s.id] = bb.prepare(s.map, s.map_normals)
                t0 = time.perf_counter()
                r_bb = bb.register(adv, [prepared[s.id]], batch.T_init)
                t1 = time.perf_counter()
                with torch.no_grad():
                    r_rep = rep.register(adv, batch.maps, batch.T_init)
                t2 = time.perf_counter()
                d = pose_error_components(r_rep.T.double(), r_bb.T.double())
                e_bb = pose_error_components(r_bb.T.double(), batch.T_gt)
                e_rep = pose_error_components(r_rep.T.double(), batch.T_gt)
                rows.append({
                    "pair": pair, "attack": attack_name, "budget_m": BUDGET_M, "seed": args.seed,
                    "sample_id": s.id, "dt_m": float(d["trans_err"][0]),
                    "dr_deg": float(np.rad2deg(float(d["rot_err"][0]))),
                    "err_bb_m": float(e_bb["trans_err_xy"][0]),
                    "err_rep_m": float(e_rep["trans_err_xy"][0]),
                    "status_bb": r_bb.status[0], "status_rep": r_rep.status[0],
                    "it_bb": int(r_bb.iterations[0]), "it_rep": int(r_rep.iterations[0]),
                    "time_bb_s": t1 - t0, "time_rep_s": t2 - t1,
                })
            pd.DataFrame(rows).to_csv(csv, mode="a", header=not csv.exists(), index=False)
            print(attack_name, s.id, " ".join(f"{r['pair']}:{1e3 * r['dt_m']:.3f}mm" for r in rows),
                  flush=True)
    rows = pd.read_csv(csv)
    rows.attrs["provenance"] = row_makers(args.out, ROWS_FILE)  # the entries that made rows
    table = summarise(rows)
    write_csv(args.out / "summary.csv", table, index=False)
    md = ["# Black-box ICP targets against their differentiable replicas", "",
          f"{args.samples} `lidar-sim` test scans; conditions: clean (`none`) and the `uniform`, "
          f"`normal` and `sector` attacks at lambda = {BUDGET_M:g} m (seed {args.seed}, not strict). "
          "Both members of a pair register the same scan from the same initial pose with their "
          "registered lidar defaults; `dt` / `dr`: translation (mm) and rotation (deg) of "
          "`log(T_replica T_blackbox^-1)`; `both_ok`: scans where both report status `ok`; "
          "`err_*_median_m`: median `trans_err_xy` against the ground truth; `s_*`: seconds per "
          "scan (one thread, shared 2-core machine).", "", table.to_markdown(index=False), "",
          f"Command: `OMP_NUM_THREADS=1 python scripts/replica_agreement.py --samples "
          f"{args.samples} --out {args.out}`", "", *provenance_notes(rows)]
    write_file(args.out / "agreement.md", "\n".join(md))
    manifest.update(finished=True, wall_s_this_invocation=round(time.time() - t_start, 1),
                    date=time.strftime("%Y-%m-%d %H:%M:%S %Z"))
    write_json(args.out / "manifest.json", manifest)
    print(table.to_markdown(index=False))


if __name__ == "__main__":
    main()
