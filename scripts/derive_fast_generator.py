"""Re-save the trained lidar-sim weights with another iterated prior (nothing is trained).

The lidar-sim generator takes the iterated sector attack (``prior="sector-iter"``) as input
channels, and that prior is most of its cost and much of its strength. The weights trained in
session 7 live in ``icpbench/checkpoints/lidar-sim-icp25/`` with the prior they were trained with
(8 re-linearisations, i.e. 9 surrogate ICPs per scan, each capped at 25 iterations). This script
re-saves *the same weights* with changed prior settings; the card says so (``derived_from``:
source file, its SHA-256 prefix and the changed settings) and the source card's held-out numbers,
which belong to the source's prior, are dropped.

    # the default lidar-sim checkpoint (session 12): prior ICPs run to the evaluation cap, 100
    python scripts/derive_fast_generator.py --prior-iterations 8 --prior-icp-iterations 100 \
        --out icpbench/checkpoints/lidar-sim \
        --title "the default lidar-sim generator: the trained weights, prior ICPs to 100 iterations"
    # lidar-sim-fast (session 10): a 4-iteration prior
    python scripts/derive_fast_generator.py            # -> icpbench/checkpoints/lidar-sim-fast/
    python scripts/derive_fast_generator.py --prior-iterations 5 --out runs/fast5

``--prior-icp-iterations`` changes the cap of the surrogate ICP the prior runs on each iterate (the
source's 25 is the training surrogate's cap; the lidar evaluation ICP's is 100);
``--prior-icp-stride`` lets those ICPs register every k-th point only; ``--prior-icp-nn-reuse R``
lets them keep a point's correspondence while it moves less than R metres (approximate).

Use a result with ``--attack-param generator.checkpoint=<out>/generator.pt`` (the default
``icpbench/checkpoints/lidar-sim/`` is used without it).
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

from icpbench.learning.checkpoint import load_checkpoint, save_checkpoint

ROOT = Path(__file__).resolve().parents[1]
#: the trained session-7 weights (prior ICPs capped at 25 iterations); the default ``lidar-sim``
#: checkpoint is derived from them (prior ICPs to 100, see the module docstring)
SOURCE = ROOT / "icpbench" / "checkpoints" / "lidar-sim-icp25" / "generator.pt"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", type=Path, default=SOURCE, help="weights to re-save")
    ap.add_argument("--prior-iterations", type=int, default=4,
                    help="re-linearisations of the iterated prior (the source has its own)")
    ap.add_argument("--prior-icp-iterations", type=int, default=None,
                    help="cap of the prior's surrogate ICPs (default: the source's)")
    ap.add_argument("--prior-icp-stride", type=int, default=None,
                    help="the prior's surrogate ICPs register every N-th point (default: the source's)")
    ap.add_argument("--prior-icp-nn-reuse", type=float, default=None,
                    help="the prior's surrogate ICPs keep a point's correspondence while it moves "
                         "less than this many metres (approximate; default: the source's)")
    ap.add_argument("--title", default=None, help="title of the written MODEL_CARD.md")
    ap.add_argument("--out", type=Path, default=ROOT / "icpbench" / "checkpoints" / "lidar-sim-fast")
    args = ap.parse_args()
    loaded = load_checkpoint(args.source)
    model = loaded.model
    if model.config.prior != "sector-iter":
        raise SystemExit(f"{args.source} has prior={model.config.prior!r}; only sector-iter models "
                         "have prior iterations")
    old = model.config.prior_iterations
    changed = {"prior_iterations": [old, args.prior_iterations]}
    model.config = model.config.with_(prior_iterations=args.prior_iterations)
    if args.prior_icp_iterations is not None:
        changed["prior_icp_iterations"] = [model.config.prior_icp_iterations,
                                           args.prior_icp_iterations]
        model.config = model.config.with_(prior_icp_iterations=args.prior_icp_iterations)
    if args.prior_icp_stride is not None:
        changed["prior_icp_stride"] = [model.config.prior_icp_stride, args.prior_icp_stride]
        model.config = model.config.with_(prior_icp_stride=args.prior_icp_stride)
    if args.prior_icp_nn_reuse is not None:
        changed["prior_icp_nn_reuse"] = [model.config.prior_icp_nn_reuse, args.prior_icp_nn_reuse]
        model.config = model.config.with_(prior_icp_nn_reuse=args.prior_icp_nn_reuse)
    card = dict(loaded.card)
    card.pop("heldout_eval", None)
    card["derived_from"] = {
        "checkpoint": str(args.source.relative_to(ROOT) if args.source.is_relative_to(ROOT)
                          else args.source),
        "sha256_16": hashlib.sha256(args.source.read_bytes()).hexdigest()[:16],
        "changed": changed,
        "note": "same weights, not retrained; held-out numbers of the source dropped",
    }
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out.resolve()
    use = out.relative_to(ROOT) if out.is_relative_to(ROOT) else out
    dest = save_checkpoint(model, args.out / "generator.pt", card)
    icp_line = ("" if "prior_icp_iterations" not in changed else
                f"- changed: `prior_icp_iterations` {changed['prior_icp_iterations'][0]} -> "
                f"{changed['prior_icp_iterations'][1]} (the cap of every surrogate ICP the "
                "iterated prior runs)\n")
    stride_line = ("" if "prior_icp_stride" not in changed else
                   f"- changed: `prior_icp_stride` {changed['prior_icp_stride'][0]} -> "
                   f"{changed['prior_icp_stride'][1]} (those surrogate ICPs register every "
                   f"{changed['prior_icp_stride'][1]}-th scan point)\n")
    reuse_line = ("" if "prior_icp_nn_reuse" not in changed else
                  f"- changed: `prior_icp_nn_reuse` {changed['prior_icp_nn_reuse'][0]:g} -> "
                  f"{changed['prior_icp_nn_reuse'][1]:g} m (those surrogate ICPs keep a point's "
                  "correspondence while it moves less than this: approximate nearest neighbours)\n")
    shorter_only = (args.prior_icp_iterations is None and args.prior_icp_stride is None
                    and args.prior_icp_nn_reuse is None)
    title = args.title or ("the trained lidar-sim weights with a shorter prior" if shorter_only
                           else "the trained lidar-sim weights with a changed prior")
    iter_line = ("" if old == args.prior_iterations else
                 f"- changed: `prior_iterations` {old} -> {args.prior_iterations} (the iterated "
                 f"sector prior runs {args.prior_iterations + 1} surrogate ICPs per scan instead "
                 f"of {old + 1})\n")
    measured = ("- measured: `results/frontier/idle-timing/` (row `generator-fast`) and "
                "`results/lidar-sim-test-full-fast/` (see `docs/status.md`, session 10)\n"
                if shorter_only else "- measured: see `docs/status.md`\n")
    (args.out / "MODEL_CARD.md").write_text(
        f"# `{args.out.name}`: {title}\n\n"
        "Written by `python scripts/derive_fast_generator.py` (nothing here is typed by hand).\n\n"
        f"- weights: those of `{card['derived_from']['checkpoint']}` (SHA-256 "
        f"{card['derived_from']['sha256_16']}...), not retrained\n"
        f"{iter_line}"
        f"{icp_line}"
        f"{stride_line}"
        f"{reuse_line}"
        f"- training of the weights: see `{Path(card['derived_from']['checkpoint']).parent}/MODEL_CARD.md`\n"
        f"{measured}"
        f"- use: `--attack-param generator.checkpoint={use}/generator.pt`\n")
    print(f"wrote {dest} (prior_iterations {old} -> {args.prior_iterations})")


if __name__ == "__main__":
    main()
