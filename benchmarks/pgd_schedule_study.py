"""Choose PGD settings: mean target error and CPU time per scan on lidar-sim test scans.

Usage::

    python benchmarks/pgd_schedule_study.py 12 '{"old": {}, "cos20p4": {"steps": 20,
        "step_size": 0.5, "schedule": "cosine", "patience": 4}}' 1,4

For each named PGD setting (keyword arguments of ``PGDAttack``) and budget (metres): the attack
runs on each of the first N ``lidar-sim`` test scans alone (B = 1, seed 0, p2plane surrogate, lidar
preset), then our p2plane ICP (lidar preset) registers the adversarial scan; printed are the mean
horizontal translation error of that registration (m) and the attack's CPU time per scan (s,
``time.process_time``, 1 torch thread). Results in docs/performance.md.
"""

from __future__ import annotations

import json
import sys
import time

import torch

from icpbench.core import registry
from icpbench.core.se3 import pose_error_components
from icpbench.core.types import Batch
from icpbench.targets.p2plane import PointToPlaneICP


def main(n_scans: int, configs: dict[str, dict], budgets: list[float]) -> None:
    torch.set_num_threads(1)
    ds = registry.datasets.get("lidar-sim")(seed=0, split="test")
    samples = [ds[i] for i in range(n_scans)]
    surrogate, target = PointToPlaneICP("lidar"), PointToPlaneICP("lidar")
    for name, params in configs.items():
        pgd = registry.attacks.get("pgd")(**params)
        for lam in budgets:
            errs, secs = [], []
            for s in samples:
                batch = Batch.from_samples([s])
                t0 = time.process_time()
                adv = pgd.run(batch, lam, surrogate=surrogate, generator=0).scans
                secs.append(time.process_time() - t0)
                with torch.no_grad():
                    reg = target.register(adv.double(), batch.maps, batch.T_init)
                errs.append(float(pose_error_components(reg.T, batch.T_gt)["trans_err_xy"][0]))
            print(name, lam, json.dumps({"mean_err": sum(errs) / len(errs),
                                         "s_per_scan": sum(secs) / len(secs)}), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]), json.loads(sys.argv[2]), [float(b) for b in sys.argv[3].split(",")])
