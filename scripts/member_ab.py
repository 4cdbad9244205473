"""A/B of one ensemble member's settings on a board's scans, the member run alone.

The ensemble's members ``uniform``, ``sector-adaptive``, ``spoof`` and ``valley`` do not depend on
the members before them, so each can be run alone on a board's scan with the per-sample random
generators the ensemble gives it, and then gives exactly the error the board recorded for it
(arm A, a check that the board is reproduced). Arm B runs the same member with changed settings
(``--set KEY=VALUE``, repeatable) on the same scans. For each arm the script prints the member's
mean error against the board's, the share of scans where it is larger, an estimate of the
ensemble's worst case with it (per scan the larger of the board's other members and the arm's;
optimistic where the query search, which starts from the best member, would have started
elsewhere) and its seconds per scan, all measured in this run so the two arms' times compare.
It writes every row to ``--out`` (CSV: arm, sample_id, err, seconds, board_err, board_worst,
worst_estimate) and beside it a manifest (``.json``: the command, both arms' settings, the
summary, the commit).

This is how a cheaper member setting is checked before it goes into a new version of the
standard protocol, without rerunning whole boards (CHANGELOG.md, 2026-11-27: ``valley`` with
``line_steps=4``).

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python scripts/member_ab.py --board results/leaderboard \
        --variant p2point --member valley --set line_steps=4 --samples 16 --workers 2 \
        --out /tmp/valley-ab.csv
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

#: Members whose result does not depend on the members run before them.
INDEPENDENT = ("uniform", "sector-adaptive", "spoof", "valley")

_CACHE: dict[str, Any] = {}  # per worker process: the dataset and the target


def _value(text: str) -> Any:
    """A ``--set`` value: JSON where it parses (numbers, true, null), else the text."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def plan(board: Path, variant: str, member: str, changes: dict[str, Any], samples: int,
         start: int = 0) -> tuple[dict[str, Any], list[tuple[str, int]], pd.DataFrame]:
    """The work of an A/B: (setup shared by every job, the jobs (arm, scan index), the board's
    ensemble rows of ``samples`` scans from the board's scan ``start`` on).

    Raises:
        SystemExit: an unknown variant or member, a board without that variant's run, or a
            member that depends on the members before it.
    """
    from icpbench.attacks.ensemble import EnsembleAttack, column
    from icpbench.attacks.valley import LINE_STEPS
    from icpbench.harness.leaderboard import STANDARD_VARIANTS
    from icpbench.harness.results import load_results

    if member not in INDEPENDENT:
        raise SystemExit(f"--member must be one of {', '.join(INDEPENDENT)} (the others start "
                         f"from the members before them), got {member!r}")
    by_label = {v.label: v for v in STANDARD_VARIANTS}
    if variant not in by_label:
        raise SystemExit(f"unknown --variant {variant!r}; valid: {', '.join(by_label)}")
    v = by_label[variant]
    run = board / "runs" / v.slug
    if not (run / "manifest.json").is_file():
        raise SystemExit(f"{run} holds no run of {variant!r}")
    manifest = json.loads((run / "manifest.json").read_text())
    cfg = manifest["config"]
    ens_settings = {k: x for k, x in manifest["attacks"]["ensemble"].items() if k != "strict"}
    # boards made before the ensemble had this setting ran valley on its own default
    ens_settings.setdefault("valley_line_steps", LINE_STEPS)
    # and before protocol v3 modelled KISS-ICP's kernel as none, every other as Cauchy's
    ens_settings.setdefault("valley_kernel_model", "cauchy")
    ens = EnsembleAttack(**ens_settings)
    base = {k: x for k, x in ens.members[member].settings().items() if k != "strict"}
    df = load_results(run)
    rows = df[(df.attack == "ensemble") & np.isclose(df.budget, cfg["budgets"][0])]
    if f"extra.{column(member)}" not in rows:
        raise SystemExit(f"the board's {variant!r} rows have no {member!r} member")
    rows = rows.drop_duplicates("sample_id").iloc[start:start + samples]
    setup = dict(dataset=cfg["dataset"], dataset_params=cfg["dataset_params"],
                 split=cfg["split"], dataset_seed=cfg["dataset_seed"],
                 preset=manifest["icp_preset"], target=v.target, target_params=v.params,
                 member=member, budget=float(cfg["budgets"][0]), seed=int(cfg["seeds"][0]),
                 settings={"A": base, "B": {**base, **changes}})
    jobs = [(arm, start + i) for i in range(len(rows)) for arm in ("A", "B")]
    return setup, jobs, rows


def _job(args: tuple[dict[str, Any], str, int]) -> dict[str, Any]:
    """One arm on one scan (in a worker process): the member alone, as the ensemble runs it."""
    setup, arm, i = args
    import torch

    from icpbench.attacks.base import SampleGenerators
    from icpbench.core import registry
    from icpbench.core.types import Batch
    from icpbench.harness.runner import build_target
    from icpbench.targets.oracle import QueryOracle

    torch.set_num_threads(1)
    if "dataset" not in _CACHE:
        cls = registry.datasets.get(setup["dataset"])
        _CACHE["dataset"] = cls.create(seed=setup["dataset_seed"], split=setup["split"],
                                       **setup["dataset_params"])
        _CACHE["target"] = build_target(setup["target"], setup["preset"],
                                        setup["target_params"] or None)
        _CACHE["replica"] = _CACHE["target"].exact_replica()
    batch = Batch.from_samples([_CACHE["dataset"][i]])
    # queries answered by the target's exact replica where it has one, as the runner does
    oracle = QueryOracle.prepared(_CACHE["target"], batch, answer_with=_CACHE["replica"])
    attack = registry.attacks.get(setup["member"])(**setup["settings"][arm])
    gens = SampleGenerators.for_batch(batch, setup["seed"], setup["member"], setup["budget"])
    t0 = time.perf_counter()
    out = attack.run(batch, setup["budget"], oracle=oracle, generator=gens)
    seconds = time.perf_counter() - t0
    err = float(oracle.errors(out.scans.to(torch.float64))[0])
    return dict(arm=arm, sample_id=batch.samples[0].id, err=err, seconds=seconds)


def summarise(res: pd.DataFrame, rows: pd.DataFrame, member: str) -> pd.DataFrame:
    """Per arm: member mean error, the board's, share larger, estimated worst case, the board's,
    seconds per scan. ``res`` gets the columns ``board_err``, ``board_worst`` and
    ``worst_estimate``."""
    from icpbench.attacks.ensemble import MEMBERS, column

    r = rows.set_index("sample_id")
    others = [f"extra.{column(m)}" for m in MEMBERS if m != member and f"extra.{column(m)}" in r]
    res["board_err"] = r[f"extra.{column(member)}"].reindex(res.sample_id).to_numpy()
    res["board_worst"] = r.trans_err_xy.reindex(res.sample_id).to_numpy()
    rest = r[others].max(axis=1, skipna=True).reindex(res.sample_id).to_numpy()
    res["worst_estimate"] = np.fmax(rest, res.err.to_numpy())
    out = []
    for arm, x in res.groupby("arm"):
        out.append(dict(arm=arm, scans=len(x), member_mean=x.err.mean(),
                        board_member_mean=x.board_err.mean(),
                        larger_share=float(np.mean(x.err > x.board_err + 1e-9)),
                        worst_estimate=x.worst_estimate.mean(), board_worst=x.board_worst.mean(),
                        seconds=x.seconds.mean()))
    return pd.DataFrame(out).set_index("arm")


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--board", type=Path, default=Path("results/leaderboard"))
    ap.add_argument("--variant", required=True, help="a standard variant's label")
    ap.add_argument("--member", required=True, choices=INDEPENDENT)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of arm B (repeatable)")
    ap.add_argument("--samples", type=int, default=16, help="scans, from --start on")
    ap.add_argument("--start", type=int, default=0,
                    help="the board's first scan to use (0: its first; to add scans to an A/B)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    changes = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set needs KEY=VALUE, got {item!r}")
        changes[key.strip()] = _value(value.strip())
    if args.start < 0:
        raise SystemExit(f"--start must be >= 0, got {args.start}")
    setup, jobs, rows = plan(args.board, args.variant, args.member, changes, args.samples,
                             args.start)
    work = [(setup, arm, i) for arm, i in jobs]
    if args.workers > 1:
        with mp.get_context("spawn").Pool(args.workers) as pool:
            done = list(pool.imap_unordered(_job, work))
    else:
        done = [_job(w) for w in work]
    res = pd.DataFrame(done).sort_values(["arm", "sample_id"]).reset_index(drop=True)
    table = summarise(res, rows, args.member)
    from icpbench.harness.outputs import write_csv, write_json
    from icpbench.harness.runner import git_commit, package_versions

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_csv(args.out, res, index=False)
    write_json(args.out.with_suffix(".json"), {
        "command": "python scripts/member_ab.py " + " ".join(argv if argv is not None
                                                                else sys.argv[1:]),
        "board": str(args.board), "variant": args.variant, "member": args.member,
        "settings": setup["settings"], "budget": setup["budget"], "scans": len(rows),
        "workers": args.workers, "summary": table.reset_index().to_dict(orient="records"),
        "git": git_commit(), "versions": package_versions()})
    print(f"{args.member} on {args.variant}, {len(rows)} scans; B: {changes}")
    print(table.to_string(float_format=lambda x: f"{x:.3f}"))
    return table


if __name__ == "__main__":
    main()
