"""Write ``icpbench/checkpoints/<dataset>/MODEL_CARD.md`` from the checkpoints' JSON cards and the
Table 1 that ``scripts/main_job.sh`` produced (``results/table1.csv``).

Usage: ``python scripts/model_card.py [--dataset lidar-sim] [--table results/table1.csv]``.
Another checkpoint folder names its own Table 1 and training script (``--table-title``,
``--table-source``, ``--script``).
Nothing here is typed by hand: training settings, wall times and held-out numbers come from the
cards that ``icpbench train`` wrote, the Table 1 cells from the CSV.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd

from icpbench.harness.outputs import write_file

ROOT = Path(__file__).resolve().parents[1]


def describe(path: Path) -> list[str]:
    meta = json.loads(path.read_text())
    card, cfg = meta.get("card", {}), meta.get("config", {})
    out = [f"### `{path.with_suffix('.pt').name}`", ""]
    out.append(f"- data: {card.get('data')}")
    out.append(f"- budgets trained [m]: {card.get('budgets_m')}; weights: {card.get('weights')}; "
               f"output: {cfg.get('output')}; conditioned: {cfg.get('conditioned')}")
    out.append(f"- epochs: {card.get('epochs_done')} (pretraining {card.get('pretrain_epochs')}); "
               f"optimiser: {card.get('optimiser')}; ICP during training: {card.get('icp_preset')} "
               f"({card.get('icp_backprop', 'unrolled')} gradient)")
    out.append(f"- training wall time: {card.get('train_wall_s')} s "
               f"(+ {card.get('data_prep_s')} s index precompute) on {card.get('hardware')}")
    if card.get("init_checkpoint"):
        out.append(f"- fine-tuned from `{card['init_checkpoint']}`; whole chain "
                   f"{card.get('train_wall_s_total', '?')} s of training; its stages, newest first:")
        out += [f"  - {stage}" for stage in lineage(card.get("init_card"))]
    if card.get("notes"):
        out.append(f"- notes: {card['notes']}")
    if card.get("sector_iter"):
        out.append(f"- prior during training (iterated sector attack settings): {card['sector_iter']}; "
                   "at run time the generator attack's own `sector_iter` settings apply")
    ev = card.get("heldout_eval") or {}
    for lam, r in ev.items():
        out.append(f"- held-out (test passes, first {r['samples']} scans) λ={lam} m: mean "
                   f"trans_err_xy {r['trans_err_xy_mean']:.3f} m over {r['converged']} converged, "
                   f"mean max displacement {r['disp_max_mean']:.3f} m")
    return out + [""]


def lineage(card: dict | None) -> list[str]:
    """One line per ancestor stage of a fine-tuned model (``card["init_card"]`` chain)."""
    out = []
    while card:
        opt, data = card.get("optimiser") or {}, card.get("data") or {}
        out.append(f"{card.get('epochs_done')} epoch(s) x {data.get('samples')} scans, "
                   f"lr {opt.get('lr')}, ICP {card.get('icp_preset')} "
                   f"({card.get('icp_backprop', 'unrolled')}), {card.get('train_wall_s')} s"
                   + (f", from `{card['init_checkpoint']}`" if card.get("init_checkpoint") else
                      " (from scratch)"))
        card = card.get("init_card")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--dataset", default="lidar-sim")
    ap.add_argument("--table", default=str(ROOT / "results" / "table1.csv"))
    ap.add_argument("--table-title", default="`results/table1.csv`, target p2plane, lidar-sim test passes")
    ap.add_argument("--table-source", default="the Table 1 of `scripts/main_job.sh`")
    ap.add_argument("--script", default="scripts/train_lidar.sh", help="the training script named")
    args = ap.parse_args()
    d = ROOT / "icpbench" / "checkpoints" / args.dataset
    cards = sorted(d.glob("generator*.json"))
    if not cards:
        raise SystemExit(f"no generator checkpoints in {d}")
    lines = [f"# Generator checkpoints for `{args.dataset}`", "",
             "Written by `python scripts/model_card.py` from the JSON cards beside the weights and "
             f"from {args.table_source}. Training commands: `{args.script}`.",
             "The attack loads `generator-l<λ>.pt` when it exists, else `generator.pt`.", ""]
    for c in cards:
        lines += describe(c)
    table = Path(args.table)
    if table.is_file():
        t = pd.read_csv(table)
        shown = [c for c in t.columns if c == "Method" or "Trans Pose Error" in c or "% Ours" in c]
        lines += [f"## Table 1 ({args.table_title})", "",
                  t[shown].to_markdown(index=False), ""]
    write_file(d / "MODEL_CARD.md", "\n".join(lines))
    print(f"wrote {d / 'MODEL_CARD.md'}")


if __name__ == "__main__":
    main()
