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
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any, ClassVar

import torch

from icpbench.attacks.base import Attack, project_to_ball
from icpbench.errors import CheckpointError
from icpbench.types import Batch


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
    """

    name: ClassVar[str] = "generator"
    description: ClassVar[str] = (
        "Learned PointNet++ generator trained through differentiable ICP (the paper's 'Ours')"
    )
    wants_context: ClassVar[bool] = True

    def __init__(self, *, strict: bool = False, checkpoint: str | None = None,
                 dataset: str | None = None, icp_preset: str | None = None,
                 device: str = "cpu", **params: Any) -> None:
        super().__init__(strict=strict, checkpoint=checkpoint, dataset=dataset, device=device,
                         **params)
        self.checkpoint, self.dataset, self.device = checkpoint, dataset, device
        self._loaded: dict[Path, Any] = {}
        if checkpoint is not None:  # a missing or corrupt file is a user error: fail before the run
            self._model(0.0)

    def fingerprint(self, budgets: Sequence[float]) -> dict[str, str]:
        """SHA-256 (first 16 hex digits) of the weights and JSON of the checkpoint of each budget
        (keyed ``"<lambda>"``; ``"none"`` where no checkpoint resolves), so that resuming a run after a
        checkpoint changed is refused."""
        from icpbench.generator.checkpoint import config_path

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
        from icpbench.generator.checkpoint import load_checkpoint

        path = resolve_checkpoint(self.dataset, budget_m, self.checkpoint)
        if path not in self._loaded:
            self._loaded[path] = load_checkpoint(path, map_location=self.device)
        return self._loaded[path]

    def settings(self) -> dict[str, Any]:
        out = super().settings()
        out["resolved"] = {str(p): lg.card for p, lg in self._loaded.items()}
        return out

    @torch.no_grad()
    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        lg = self._model(budget_m)
        model = lg.model
        x = batch.scans.to(torch.float32).to(self.device)
        geo = model.precompute(batch.scans.to(torch.float32)).to(self.device)
        budget = (torch.full((x.shape[0],), float(budget_m), device=self.device)
                  if model.needs_budget else None)
        prior = None
        if model.needs_prior:  # analytic channels from the map and the true pose (sector model)
            from icpbench.generator.prior import sector_prior_batch

            prior = sector_prior_batch(batch.scans, batch.T_gt, batch.maps).to(self.device)
        adv = model(x, geo, budget, prior)
        # the network runs in float32; add its displacement to the scans in their own precision, so
        # that rounding the input to float32 (~2e-6 m at 40 m) does not count as a displacement
        adv = batch.scans + (adv - x).to("cpu", batch.scans.dtype)
        if lg.card.get("strict_training") or lg.config.output == "bounded":
            # strict training: the model was trained behind this projection, so apply it here too;
            # bounded output: |displacement| < lambda already, the projection only removes float32
            # rounding at saturation (|u| = 1.0 in float32)
            adv = project_to_ball(batch.scans, adv, float(budget_m))
        return adv
