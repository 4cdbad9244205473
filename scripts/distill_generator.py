"""Train the distilled lidar-sim generator (icpbench.learning.distill): targets, then training.

    python scripts/distill_generator.py targets --out runs/distill-targets --samples 128 --workers 2
    python scripts/distill_generator.py train --data runs/distill-targets --out runs/distill \
        --epochs 40 --device cuda --workers 16

``targets`` runs the 2-step and the 8-step iterated sector attack through the lidar evaluation ICP
on the first ``--samples`` training scans at λ = 1..5 m (resumable; ``--workers`` processes, each
on its own shards; about 27 s per scan on one core). ``train`` fits the generator to them and
writes ``generator.pt``/``.json`` and ``history.csv`` into ``--out`` after every epoch; copy the
two checkpoint files to ``icpbench/checkpoints/lidar-sim/`` to ship them, then regenerate Table 1
(``make run``) and the model card (``python scripts/model_card.py``).
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from functools import partial

from icpbench.core.errors import IcpbenchError
from icpbench.learning.distill import DistillConfig, TargetSpec, make_targets, train_distilled


def _targets_worker(rank: int, world: int, spec: TargetSpec, out: str) -> int:
    import torch

    torch.set_num_threads(1)
    n_shards = -(-min(spec.samples, 10**9) // spec.chunk)
    mine = [k for k in range(n_shards) if k % world == rank]
    return len(make_targets(spec, out, shards=mine,
                            log=lambda m: print(f"[{rank}] {m}", flush=True)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("targets", help="compute the cheap and target attacks on training scans")
    t.add_argument("--out", required=True)
    t.add_argument("--samples", type=int, default=128)
    t.add_argument("--workers", type=int, default=1)
    t.add_argument("--target-iterations", type=int, default=8)
    r = sub.add_parser("train", help="fit the generator to a targets folder")
    r.add_argument("--data", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--epochs", type=int, default=40)
    r.add_argument("--batch-size", type=int, default=16)
    r.add_argument("--lr", type=float, default=1e-3)
    r.add_argument("--val-scans", type=int, default=8)
    r.add_argument("--device", default="cpu")
    r.add_argument("--max-minutes", type=float, default=None)
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--loss", choices=("mse", "align"), default="mse")
    a = p.parse_args(argv)
    try:
        if a.cmd == "targets":
            spec = TargetSpec(samples=a.samples, target={"iterations": a.target_iterations})
            spec.check()
            if a.workers > 1:
                with ProcessPoolExecutor(a.workers) as pool:
                    n = sum(pool.map(partial(_targets_worker, world=a.workers, spec=spec,
                                             out=a.out), range(a.workers)))
            else:
                n = _targets_worker(0, 1, spec, a.out)
            print(f"{n} shard(s) written to {a.out}")
        else:
            cfg = DistillConfig(epochs=a.epochs, batch_size=a.batch_size, lr=a.lr,
                                val_scans=a.val_scans, device=a.device, loss=a.loss,
                                max_minutes=a.max_minutes, workers=a.workers)
            card = train_distilled(a.data, a.out, cfg, log=lambda m: print(m, flush=True))
            print(f"validation: {card['validation']}")
    except IcpbenchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
