"""A resumable on-disk cache of PGD oracle solutions for training scans (learning from the oracle).

Beyond the paper. The generator of Zhang et al. (ICRA 2025) learns only from the adversarial loss
through the surrogate ICP; here it can also imitate the per-scan optimum that projected gradient
ascent finds (Madry et al., ICLR 2018), a form of amortised optimisation / policy distillation
(docs/methods.md, "Learning from the oracle"). This module computes those optima once per training
scan and budget and stores them as files, so that training can be stopped and resumed and several
runs can share one cache.

Layout: ``ROOT/spec.json`` (the oracle's settings; a cache made with other settings is refused)
and one ``<sample id with / replaced by __>@<lambda>.npz`` per scan and budget holding

* ``disp``: (N, 3) float32, the oracle's displacement ``x_adv - x`` in the sensor frame (metres,
  every row's norm <= lambda);
* ``objective``, ``start_objective``: the surrogate's weighted pose error (m) of the oracle's
  answer and of its starting point (the sector attack's output with ``init="sector"``).
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.se3 import pose_error
from icpbench.core.types import Batch, Sample
from icpbench.learning.losses import weighted_pose_error, weights
from icpbench.targets.base import Target


@dataclass(frozen=True)
class OracleSpec:
    """Settings of the oracle whose answers are cached (see :class:`icpbench.attacks.pgd.PGDAttack`).

    Attributes:
        steps: projected gradient steps.
        init: ``"sector"`` (warm start from the analytic attack, default), ``"random"`` or ``"clean"``.
        step_size: step as a fraction of lambda.
        icp_iterations: iteration cap of the surrogate ICP inside the oracle.
        weights: pose-error weight preset.
        seed: attack seed (only used by a random start).
    """

    steps: int = 10
    init: str = "sector"
    step_size: float = 0.1
    icp_iterations: int = 25
    weights: str = "xy"
    seed: int = 0


def assigned_budget(sample_id: str, budgets: Sequence[float]) -> float:
    """The one budget (metres) at which a training scan's oracle answer is cached and imitated:
    a fixed, well-spread choice from the sample id (CRC32), independent of sharding and order."""
    if not budgets:
        raise InputError("assigned_budget needs at least one budget")
    return float(budgets[zlib.crc32(sample_id.encode()) % len(budgets)])


class OracleCache:
    """Files of oracle displacements under ``root`` for one :class:`OracleSpec`."""

    def __init__(self, root: str | Path, spec: OracleSpec) -> None:
        self.root, self.spec = Path(root), spec
        self.root.mkdir(parents=True, exist_ok=True)
        spec_path = self.root / "spec.json"
        if spec_path.exists():
            found = json.loads(spec_path.read_text())
            if found != asdict(spec):
                raise InputError(f"{self.root} caches an oracle with other settings ({found}); "
                                 f"use another folder for {asdict(spec)}")
        else:
            spec_path.write_text(json.dumps(asdict(spec), indent=1))

    def path(self, sample_id: str, budget_m: float) -> Path:
        """File of one scan's answer at one budget."""
        return self.root / f"{sample_id.replace('/', '__')}@{budget_m:g}.npz"

    def load(self, sample_id: str, budget_m: float) -> np.ndarray:
        """Cached displacement (N, 3) float32; raises if it was never computed."""
        p = self.path(sample_id, budget_m)
        if not p.exists():
            raise InputError(f"no oracle answer cached for {sample_id!r} at λ={budget_m:g} in "
                             f"{self.root}")
        with np.load(p) as f:
            return f["disp"].astype(np.float32)

    def ensure(self, samples: Sequence[Sample], budgets_m: Sequence[float], surrogate: Target,
               *, batch_size: int = 4,
               progress: Callable[[int, int], None] | None = None) -> list[np.ndarray]:
        """Compute the missing answers (resumable: finished files are kept) and return all.

        Args:
            samples: training scans (equal N within a batch of the same budget).
            budgets_m: one budget per sample (metres).
            surrogate: differentiable ICP the oracle ascends through (its iteration cap is set
                from the spec).
            batch_size: scans attacked together.
            progress: called with (done, total) after every batch.

        Returns:
            One (N, 3) float32 displacement per sample, in the order given.
        """
        from icpbench.attacks.pgd import PGDAttack

        if len(samples) != len(budgets_m):
            raise InputError("ensure needs one budget per sample")
        s = self.spec
        pgd = PGDAttack(steps=s.steps, init=s.init, step_size=s.step_size,
                        icp_iterations=s.icp_iterations, weights=s.weights)
        icp = surrogate.with_max_iterations(s.icp_iterations)
        w = weights(s.weights)
        todo: dict[float, list[int]] = {}
        for i, (smp, lam) in enumerate(zip(samples, budgets_m, strict=True)):
            if not self.path(smp.id, lam).exists():
                todo.setdefault(float(lam), []).append(i)
        total, done = sum(len(v) for v in todo.values()), 0
        for lam, idx in todo.items():
            for k in range(0, len(idx), batch_size):
                chunk = idx[k:k + batch_size]
                batch = Batch.from_samples([samples[i] for i in chunk])
                out = pgd.run(batch, lam, surrogate=icp, generator=s.seed)
                clean = batch.scans.to(torch.float64)
                with torch.no_grad():
                    objective = _objective(icp, batch, out.scans.to(torch.float64), w)
                    start = (pgd.sector_start(batch, lam, icp) if s.init == "sector" else clean)
                    start_obj = _objective(icp, batch, start.to(torch.float64), w)
                disp = (out.scans.to(torch.float64) - clean).numpy().astype(np.float32)
                for j, i in enumerate(chunk):
                    _save_atomic(self.path(samples[i].id, lam), disp=disp[j],
                                 objective=float(objective[j]), start_objective=float(start_obj[j]))
                done += len(chunk)
                if progress is not None:
                    progress(done, total)
        return [self.load(smp.id, lam) for smp, lam in zip(samples, budgets_m, strict=True)]


def _objective(icp: Target, batch: Batch, adv: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Surrogate weighted pose error (B,) of adversarial scans adv (B, N, 3)."""
    reg = icp.register(adv, batch.maps, batch.T_init)
    return weighted_pose_error(pose_error(reg.T, batch.T_gt.to(adv.dtype)), w)


def _save_atomic(path: Path, **arrays: float | np.ndarray) -> None:
    """Write an .npz through a temporary file and a rename (an interrupted write leaves no file)."""
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **{k: np.asarray(v) for k, v in arrays.items()})
    os.replace(tmp, path)
