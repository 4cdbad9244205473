"""Attack ``generator``: the learned PointNet++ generator of Zhang et al. (ICRA 2025), "Ours".

Loads a checkpoint (a state dict + JSON config, ``torch.load(weights_only=True)``) and maps each
clean scan to its adversarial version in one forward pass. Its bound is *soft*: training penalises
displacement beyond lambda (SoftShrink reconstruction loss, eq. 4) but does not forbid it, so the
displacement audit of the base class matters here; run with ``--strict`` to project onto the
lambda-balls as well.

Checkpoint resolution: an explicit ``checkpoint=PATH``; otherwise the checkpoints shipped with the
package for the dataset, ``icpbench/checkpoints/<dataset>/``: ``generator-l<lambda>.pt`` (a model
for that budget) if present, else ``generator.pt`` (a model serving every budget: lambda-conditioned
or with the bounded output, where lambda scales the displacement).
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from icpbench.attacks.base import Attack, project_to_ball
from icpbench.core.errors import CheckpointError, InputError
from icpbench.core.iterated_sector import SectorIterSettings, surrogate_key
from icpbench.core.registry import Range
from icpbench.core.types import Batch
from icpbench.targets.base import Target


def shipped_checkpoint_dir(dataset: str) -> Path:
    """Folder of the checkpoints shipped for ``dataset`` (may not exist)."""
    return Path(str(resources.files("icpbench") / "checkpoints" / dataset))


def resolve_checkpoint(dataset: str | None, budget_m: float, checkpoint: str | None = None) -> Path:
    """The checkpoint to use for one budget (see the module docstring).

    Raises:
        CheckpointError: nothing suitable exists (the message lists what does).
    """
    if checkpoint is not None:
        return Path(checkpoint)
    if dataset is None:
        raise CheckpointError("the generator needs checkpoint=PATH (no dataset given to pick a "
                              "shipped checkpoint)")
    d = shipped_checkpoint_dir(dataset)
    per_budget = d / f"generator-l{budget_m:g}.pt"
    if per_budget.is_file():
        return per_budget
    if (d / "generator.pt").is_file():
        return d / "generator.pt"
    have = sorted(p.name for p in d.glob("*.pt")) if d.is_dir() else []
    raise CheckpointError(
        f"no shipped generator checkpoint for dataset {dataset!r} at budget {budget_m:g} "
        f"(have: {', '.join(have) or 'none'}); train one with `icpbench train` and pass "
        "--attack-param generator.checkpoint=PATH"
    )


class GeneratorAttack(Attack):
    """The paper's learned attack: a PointNet++ generator trained through differentiable ICP.

    Args:
        checkpoint: weights file (``.pt`` with its ``.json`` beside it); default: shipped.
        dataset: dataset name, used to find shipped checkpoints (the runner passes it).
        device: ``cpu`` or ``cuda``.
        refine_steps: beyond the paper: K steps of projected gradient ascent through the surrogate
            ICP (the PGD oracle's update, :meth:`icpbench.attacks.pgd.PGDAttack.refine`) starting
            from the generator's output; the best iterate is returned, so refinement never lowers
            the surrogate's objective. 0 (default) is the plain one-pass generator.
        refine_step_size: step length of the refinement as a fraction of the budget.
        refine_icp_iterations: iteration cap of the surrogate ICP inside the refinement.
        refine_backprop: gradient of that surrogate (``"unrolled"``, ``"implicit"``; None: the
            surrogate's own).
        sector_iter: for models with ``prior="sector-iter"``: settings of the iterated analytic
            attack that makes the prior channels
            (:class:`~icpbench.core.iterated_sector.SectorIterSettings` field names; missing ones
            keep their defaults, which are the ``sector-iter`` attack's, so that in one run the
            prior and the ``sector-iter`` row share the computation).

    Extras per sample: ``reused_s``, seconds per scan of work taken from the batch's memo (the
    prior computed for ``sector-iter``, or the generator's output for ``generator-refine``)
    instead of computed here; the row's attack time plus it is what the attack costs alone.
    """

    name: ClassVar[str] = "generator"
    description: ClassVar[str] = (
        "Learned PointNet++ generator trained through differentiable ICP (the paper's 'Ours')"
    )
    wants_context: ClassVar[bool] = True
    # the surrogate makes its iterated-sector prior and takes the refine steps: under
    # --surrogate self that is each evaluated target itself (or its replica)
    uses_surrogate: ClassVar[bool] = True

    param_ranges: ClassVar[dict[str, Range]] = {
        "refine_steps": Range(0, 100_000), "refine_step_size": Range(0.0, 2.0, lo_open=True),
        "refine_icp_iterations": Range(1, 1_000_000)}

    def __init__(self, *, strict: bool = False, checkpoint: str | None = None,
                 dataset: str | None = None, icp_preset: str | None = None,
                 device: str = "cpu", refine_steps: int = 0, refine_step_size: float = 0.1,
                 refine_icp_iterations: int = 25, refine_backprop: str | None = None,
                 sector_iter: dict[str, Any] | None = None, **params: Any) -> None:
        if int(refine_steps) < 0 or int(refine_icp_iterations) < 1 or not refine_step_size > 0:
            raise InputError(f"{self.name} needs refine_steps >= 0, refine_step_size > 0 and "
                             f"refine_icp_iterations >= 1; got {refine_steps}, {refine_step_size}, "
                             f"{refine_icp_iterations}")
        if refine_backprop not in (None, "unrolled", "implicit"):
            raise InputError(f"{self.name} refine_backprop must be 'unrolled', 'implicit' or None, "
                             f"got {refine_backprop!r}")
        self.prior_settings = SectorIterSettings.from_mapping(sector_iter, f"{self.name} sector_iter")
        super().__init__(strict=strict, checkpoint=checkpoint, dataset=dataset, device=device,
                         refine_steps=int(refine_steps), refine_step_size=float(refine_step_size),
                         refine_icp_iterations=int(refine_icp_iterations),
                         refine_backprop=refine_backprop,
                         sector_iter=self.prior_settings.as_dict(), **params)
        self.checkpoint, self.dataset, self.device = checkpoint, dataset, device
        self.refine_steps = int(refine_steps)
        self.refine_step_size = float(refine_step_size)
        self.refine_icp_iterations = int(refine_icp_iterations)
        self.refine_backprop = refine_backprop
        self._loaded: dict[Path, Any] = {}
        if checkpoint is not None:  # a missing or corrupt file is a user error: fail before the run
            self._model(0.0)

    def fingerprint(self, budgets: Sequence[float]) -> dict[str, str]:
        """SHA-256 (first 16 hex digits) of the weights and JSON of the checkpoint of each budget
        (keyed ``"<lambda>"``; ``"none"`` where no checkpoint resolves), so that resuming a run after a
        checkpoint changed is refused."""
        from icpbench.learning.checkpoint import config_path

        out = {}
        for lam in budgets:
            try:
                path = resolve_checkpoint(self.dataset, lam, self.checkpoint)
            except CheckpointError:  # reported per unit when the attack runs, as before
                out[f"{lam:g}"] = "none"
                continue
            h = hashlib.sha256()
            for f in (path, config_path(path)):
                if f.is_file():
                    h.update(f.read_bytes())
            out[f"{lam:g}"] = h.hexdigest()[:16]
        return out

    def _model(self, budget_m: float):
        from icpbench.learning.checkpoint import load_checkpoint

        path = resolve_checkpoint(self.dataset, budget_m, self.checkpoint)
        if path not in self._loaded:
            self._loaded[path] = load_checkpoint(path, map_location=self.device)
        return self._loaded[path]

    def settings(self) -> dict[str, Any]:
        out = super().settings()
        out["resolved"] = {str(p): lg.card for p, lg in self._loaded.items()}
        return out

    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator
                 ) -> tuple[torch.Tensor, dict[str, np.ndarray]]:
        key = ("generator", str(resolve_checkpoint(self.dataset, budget_m, self.checkpoint)),
               self.device, float(budget_m), self.prior_settings, *surrogate_key(surrogate))
        if key in batch.memo:  # e.g. generator-refine after generator: the network ran already
            adv, reused = batch.memo[key]
        else:
            t0 = time.perf_counter()
            adv, reused = self._forward(batch, budget_m, surrogate)
            # the memo keeps what the output costs alone: own time plus the prior taken from it
            batch.memo[key] = (adv, time.perf_counter() - t0 + reused)
        if self.refine_steps > 0:
            adv = self._refine(batch, adv, budget_m, surrogate)
        return adv, {"reused_s": np.full(len(batch), reused / len(batch))}

    @torch.no_grad()
    def _forward(self, batch: Batch, budget_m: float, surrogate: Target | None
                 ) -> tuple[torch.Tensor, float]:
        """The network's adversarial scans (B, N, 3) in the batch's dtype, and the seconds of
        prior computation taken from the batch's memo (0 when computed here)."""
        lg = self._model(budget_m)
        model = lg.model
        x = batch.scans.to(torch.float32).to(self.device)
        geo = model.precompute(batch.scans.to(torch.float32)).to(self.device)
        budget = (torch.full((x.shape[0],), float(budget_m), device=self.device)
                  if model.needs_budget else None)
        prior, reused = None, 0.0
        if model.needs_prior:  # analytic channels from the map and the true pose (prior models)
            from icpbench.core.iterated_sector import is_memoised, iterated_sector
            from icpbench.learning.prior import prior_channels

            icp = surrogate
            if icp is None and model.config.prior == "sector-iter":
                from icpbench.targets.p2plane import PointToPlaneICP

                icp = PointToPlaneICP()
            if model.config.prior == "sector-iter" and is_memoised(batch, budget_m, icp,
                                                                   self.prior_settings):
                reused = iterated_sector(batch, budget_m, icp, self.prior_settings).seconds
            lam = torch.full((x.shape[0],), float(budget_m), dtype=torch.float64)
            prior = prior_channels(model.config, batch, lam, icp, self.prior_settings).to(self.device)
        adv = model(x, geo, budget, prior)
        # the network runs in float32; add its displacement to the scans in their own precision, so
        # that rounding the input to float32 (~2e-6 m at 40 m) does not count as a displacement
        adv = batch.scans + (adv - x).to("cpu", batch.scans.dtype)
        if lg.card.get("strict_training") or lg.config.output in ("bounded", "ball"):
            # strict training: the model was trained behind this projection, so apply it here too;
            # bounded output: |displacement| < lambda already, the projection only removes float32
            # rounding at saturation (|u| = 1.0 in float32)
            adv = project_to_ball(batch.scans, adv, float(budget_m))
        return adv, reused

    def _refine(self, batch: Batch, adv: torch.Tensor, budget_m: float,
                surrogate: Target | None) -> torch.Tensor:
        """K projected gradient steps from the generator's output (see ``refine_steps``)."""
        from icpbench.attacks.pgd import PGDAttack

        if surrogate is None or not surrogate.differentiable:
            raise InputError(f"{self.name} with refine_steps > 0 needs a differentiable surrogate "
                             "target (--surrogate p2plane or p2point)")
        pgd = PGDAttack(steps=self.refine_steps, step_size=self.refine_step_size,
                        icp_iterations=self.refine_icp_iterations, init="clean",
                        backprop=self.refine_backprop)
        with torch.enable_grad():
            return pgd.refine(batch, adv, budget_m, surrogate=surrogate)


class GeneratorRefineAttack(GeneratorAttack):
    """"Ours + K steps": the generator followed by ``refine_steps`` (default 3) projected gradient
    steps through the surrogate run to the evaluation ICP's 100 iterations with the
    implicit-function gradient at its final pose (beyond the paper), so
    that its best-iterate rule compares evaluated errors and the row is never below the plain
    generator's on any scan. A preset of :class:`GeneratorAttack` (same settings), a separate
    attack so that Table 1 reports it as its own row; in one run it starts from the generator
    row's output (the batch's memo) rather than running the network again."""

    name: ClassVar[str] = "generator-refine"
    description: ClassVar[str] = (
        "The learned generator followed by K projected gradient steps through the surrogate "
        "(default K = 3; beyond the paper)"
    )
    preset: ClassVar[dict[str, Any]] = {"refine_steps": 3, "refine_icp_iterations": 100,
                                        "refine_backprop": "implicit"}
