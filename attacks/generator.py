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

from icpbench.attacks.base import Attack, project_to_ball, reuse_radius
from icpbench.core.errors import CheckpointError, InputError
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
        keep_prior: beyond the paper, for models with ``prior="sector-iter"``: run the surrogate
            ICP (capped at the model's ``prior_icp_iterations``) on the prior's own attack and on
            the corrected output and return, per scan, the one with the larger horizontal error
            (before any refinement). Two more surrogate ICPs per scan; with a prior capped at the
            evaluation ICP's iterations the result is never below the prior on that ICP.
        prior_icp_nn_reuse: beyond the paper, for models with ``prior="sector-iter"``: overrides
            the checkpoint's ``prior_icp_nn_reuse`` (metres): the prior's surrogate ICPs keep a
            point's correspondence while it moves less than this (``ICPConfig.nn_reuse_m``,
            approximate nearest neighbours; docs/performance.md section 12). None: the
            checkpoint's value.
    """

    name: ClassVar[str] = "generator"
    description: ClassVar[str] = (
        "Learned PointNet++ generator trained through differentiable ICP (the paper's 'Ours')"
    )
    wants_context: ClassVar[bool] = True

    def __init__(self, *, strict: bool = False, checkpoint: str | None = None,
                 dataset: str | None = None, icp_preset: str | None = None,
                 device: str = "cpu", refine_steps: int = 0, refine_step_size: float = 0.1,
                 refine_icp_iterations: int = 25, keep_prior: bool = False,
                 prior_icp_nn_reuse: float | None = None, **params: Any) -> None:
        if not isinstance(keep_prior, bool):
            raise InputError(f"{self.name} keep_prior must be true or false, got {keep_prior!r}")
        if int(refine_steps) < 0 or int(refine_icp_iterations) < 1 or not refine_step_size > 0:
            raise InputError(f"{self.name} needs refine_steps >= 0, refine_step_size > 0 and "
                             f"refine_icp_iterations >= 1; got {refine_steps}, {refine_step_size}, "
                             f"{refine_icp_iterations}")
        super().__init__(strict=strict, checkpoint=checkpoint, dataset=dataset, device=device,
                         refine_steps=int(refine_steps), refine_step_size=float(refine_step_size),
                         refine_icp_iterations=int(refine_icp_iterations), **params)
        if keep_prior:  # recorded only when set, so that older runs' settings stay comparable
            self.params["keep_prior"] = True
        self.keep_prior = keep_prior
        self.prior_icp_nn_reuse = (None if prior_icp_nn_reuse is None else
                                   reuse_radius(self.name, "prior_icp_nn_reuse", prior_icp_nn_reuse))
        if self.prior_icp_nn_reuse is not None:  # recorded only when set, as keep_prior
            self.params["prior_icp_nn_reuse"] = self.prior_icp_nn_reuse
        self.checkpoint, self.dataset, self.device = checkpoint, dataset, device
        self.refine_steps = int(refine_steps)
        self.refine_step_size = float(refine_step_size)
        self.refine_icp_iterations = int(refine_icp_iterations)
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

    @torch.no_grad()
    def _perturb(self, batch: Batch, budget_m: float, *, surrogate, generator) -> torch.Tensor:
        lg = self._model(budget_m)
        model = lg.model
        x = batch.scans.to(torch.float32).to(self.device)
        geo = model.precompute(batch.scans.to(torch.float32)).to(self.device)
        budget = (torch.full((x.shape[0],), float(budget_m), device=self.device)
                  if model.needs_budget else None)
        prior, icp = None, surrogate
        if model.needs_prior:  # analytic channels from the map and the true pose (prior models)
            from icpbench.learning.prior import prior_channels

            icp = surrogate
            if icp is None and model.config.prior == "sector-iter":
                from icpbench.targets.p2plane import PointToPlaneICP

                icp = PointToPlaneICP()
            cfg = model.config
            if self.prior_icp_nn_reuse is not None:
                if cfg.prior != "sector-iter":
                    raise InputError(f"{self.name} prior_icp_nn_reuse needs a model with "
                                     "prior='sector-iter'")
                cfg = cfg.with_(prior_icp_nn_reuse=self.prior_icp_nn_reuse)
            prior = prior_channels(cfg, batch, torch.full((x.shape[0],), float(budget_m)), icp)
            prior = prior.to(self.device)
        adv = model(x, geo, budget, prior)
        # the network runs in float32; add its displacement to the scans in their own precision, so
        # that rounding the input to float32 (~2e-6 m at 40 m) does not count as a displacement
        adv = batch.scans + (adv - x).to("cpu", batch.scans.dtype)
        if lg.card.get("strict_training") or lg.config.output in ("bounded", "sphere", "ball"):
            # strict training: the model was trained behind this projection, so apply it here too;
            # bounded output: |displacement| < lambda already, the projection only removes float32
            # rounding at saturation (|u| = 1.0 in float32)
            adv = project_to_ball(batch.scans, adv, float(budget_m))
        if self.keep_prior:
            adv = self._keep_prior(batch, adv, prior, budget_m, model.config, icp)
        if self.refine_steps > 0:
            adv = self._refine(batch, adv, budget_m, surrogate)
        return adv

    def _keep_prior(self, batch: Batch, adv: torch.Tensor, prior: torch.Tensor | None,
                    budget_m: float, config: Any, icp) -> torch.Tensor:
        """Per scan, the prior's attack where it beats the corrected output ``adv`` (B, N, 3) on
        the surrogate (see ``keep_prior``); ``prior`` (B, N, 8) holds the prior's displacement
        divided by the budget in channels 0-2."""
        from icpbench.core.se3 import pose_error
        from icpbench.learning.losses import weighted_pose_error, weights

        if prior is None or config.prior != "sector-iter":
            raise InputError(f"{self.name} keep_prior needs a model with prior='sector-iter'")
        own = project_to_ball(batch.scans, batch.scans + (prior[..., 0:3].to(
            "cpu", batch.scans.dtype) * float(budget_m)), float(budget_m))
        cap = icp.with_max_iterations(config.prior_icp_iterations)
        err = []
        for scans in (adv, own):
            reg = cap.register(scans.to(torch.float64), batch.maps, batch.T_init.to(torch.float64))
            err.append(weighted_pose_error(pose_error(reg.T, batch.T_gt.to(torch.float64)),
                                           weights("xy")))
        use_prior = (err[1] > err[0]).reshape(-1, 1, 1)
        return torch.where(use_prior, own, adv)

    def _refine(self, batch: Batch, adv: torch.Tensor, budget_m: float,
                surrogate: Target | None) -> torch.Tensor:
        """K projected gradient steps from the generator's output (see ``refine_steps``)."""
        from icpbench.attacks.pgd import PGDAttack

        if surrogate is None or not surrogate.differentiable:
            raise InputError(f"{self.name} with refine_steps > 0 needs a differentiable surrogate "
                             "target (--surrogate p2plane or p2point)")
        pgd = PGDAttack(steps=self.refine_steps, step_size=self.refine_step_size,
                        icp_iterations=self.refine_icp_iterations, random_start=False)
        with torch.enable_grad():
            return pgd.refine(batch, adv, budget_m, surrogate=surrogate)


class GeneratorRefineAttack(GeneratorAttack):
    """"Ours + K steps": the generator followed by ``refine_steps`` (default 3) projected gradient
    steps through the surrogate (beyond the paper), a separate attack so that Table 1 can report
    it as its own row next to the plain generator. Same settings as :class:`GeneratorAttack`."""

    name: ClassVar[str] = "generator-refine"
    description: ClassVar[str] = (
        "The learned generator followed by K projected gradient steps through the surrogate "
        "(default K = 3; beyond the paper)"
    )

    def __init__(self, *, strict: bool = False, checkpoint: str | None = None,
                 dataset: str | None = None, icp_preset: str | None = None,
                 device: str = "cpu", refine_steps: int = 3, refine_step_size: float = 0.1,
                 refine_icp_iterations: int = 25) -> None:
        super().__init__(strict=strict, checkpoint=checkpoint, dataset=dataset,
                         icp_preset=icp_preset, device=device, refine_steps=refine_steps,
                         refine_step_size=refine_step_size,
                         refine_icp_iterations=refine_icp_iterations)
