"""Training the generator through the differentiable ICP (Zhang et al. 2025, §III-C and §IV).

Loss ``L = alpha * L_adv + beta * L_rec`` (eqs. 2-4): ``L_adv = -||w_1:3 rho|| - ||w_4:6 phi||``
of the pose error of the surrogate ICP run on the generator's output, ``L_rec`` the SoftShrink(lambda)
reconstruction loss. A pretraining phase (alpha = 0, beta = 1) is followed by the attack phase
(alpha = 1, beta = 10). AdamW, lr 1e-4, StepLR x0.7 every 7 (objects) / 5 (lidar) epochs; the ICP
is capped at 25 iterations. Everything the network indexes (FPS, kNN groups, 3-NN weights) is
computed once per training scan, outside autograd.

One epoch = one pass over ``train_samples`` samples. A checkpoint (weights + JSON) and the
optimiser/scheduler state are written after every epoch; calling :func:`train` again with the
same output directory resumes after the last finished epoch.

Several GPUs (or CPU processes): launch the same command with ``torchrun``; each process trains on
its shard of the training subset and DistributedDataParallel averages the gradients (see
:mod:`icpbench.learning.distributed`). Without torchrun the loop is the single-process one.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from icpbench.core import registry
from icpbench.core.errors import CheckpointError, InputError
from icpbench.core.iterated_sector import SectorIterSettings
from icpbench.core.projection import project_to_ball
from icpbench.core.se3 import pose_error, pose_error_components
from icpbench.core.types import Batch
from icpbench.harness.outputs import claim, write_file, write_json
from icpbench.harness.progress import progress_bar
from icpbench.harness.results import lock_results_dir
from icpbench.learning import distributed as ddp
from icpbench.learning.losses import adversarial_loss, reconstruction_loss, weights
from icpbench.learning.prior import prior_channels, sector_prior
from icpbench.targets.p2plane import PointToPlaneICP


@dataclass
class TrainConfig:
    """Everything that determines a training run (saved as ``train_config.json``).

    Attributes:
        dataset, dataset_params: training data (the ``train`` split; evaluation on ``test``).
        generator_preset, generator_overrides: network settings (see ``GeneratorConfig``).
        weights: pose-error weight preset (``xy``, ``x-only``, ``theta-only``) or 6 numbers.
        budgets: lambda values; more than one trains a lambda-conditioned model (one budget drawn
            per sample).
        train_samples, eval_samples: sizes of the training subset and the held-out evaluation.
        batch_size, pretrain_epochs, epochs, lr, lr_step_epochs, lr_gamma, alpha, beta: optimisation.
        icp_preset: surrogate ICP settings during training (25 iterations).
        soft_dmax: smooth max-distance gate in the surrogate during training.
        icp_backprop: how the surrogate's pose is differentiated: ``"unrolled"`` (dICP, the paper)
            or ``"implicit"`` (implicit function theorem at the final pose; beyond the paper: the
            surrogate can then run the evaluation's 100 iterations at the cost of a forward pass).
        seed, threads, device: reproducibility and hardware.
        max_minutes: stop after the epoch during which this wall time is exceeded (None = no limit).
        strict: beyond the paper: project every point's displacement onto its lambda-ball inside
            the training loop (differentiably), so the model learns attacks that respect the budget
            exactly; the generator attack then applies the same projection (recorded in the card).
        sector_iter: for ``prior="sector-iter"`` models: settings of the iterated analytic attack
            that makes the prior channels during training
            (:class:`~icpbench.core.iterated_sector.SectorIterSettings` field names; missing ones
            keep their defaults). Recorded in the model card; at run time the generator attack's
            own ``sector_iter`` applies.
        init_checkpoint: start from these weights (fine-tuning; the generator settings are taken
            from its JSON, ``generator_preset``/``generator_overrides`` are then ignored, except
            ``prior``, which adds the prior's zero-initialised inputs to a model trained without
            them, see :func:`~icpbench.learning.network.add_prior`).
        adv_per_budget: divide each sample's adversarial loss by its lambda, so that with several
            budgets the large ones (whose errors are larger) do not dominate the gradient.
    """

    dataset: str = "lidar-sim"
    dataset_params: dict[str, Any] = field(default_factory=dict)
    generator_preset: str = "lidar"
    generator_overrides: dict[str, Any] = field(default_factory=dict)
    weights: str | list[float] = "xy"
    budgets: list[float] = field(default_factory=lambda: [1.0, 2.0, 3.0, 4.0, 5.0])
    train_samples: int = 120
    eval_samples: int = 16
    batch_size: int = 2
    pretrain_epochs: int = 1
    epochs: int = 6
    lr: float = 1e-4
    lr_step_epochs: int = 5
    lr_gamma: float = 0.7
    alpha: float = 1.0
    beta: float = 10.0
    icp_preset: str = "lidar-train"
    soft_dmax: bool = False
    icp_backprop: str = "unrolled"
    seed: int = 0
    threads: int = 1
    device: str = "cpu"
    max_minutes: float | None = None
    strict: bool = False
    adv_per_budget: bool = False
    init_checkpoint: str | None = None
    sector_iter: dict[str, Any] = field(default_factory=dict)


#: Named presets: ``quick`` trains on 2 CPU cores within about an hour; ``paper`` uses the paper's
#: sizes (needs a GPU: pass device="cuda").
#:
#: ``quick-lidar`` is the recipe of the shipped lidar-sim ``generator.pt`` (scripts/train_lidar.sh):
#: bounded output (displacement < lambda by construction), one lambda-conditioned model for
#: lambda = 1..5 m, per-budget balanced loss, no pretraining (the zero-initialised residual already
#: reconstructs, and SoftShrink is 0 inside the ball), lr 1e-3 (the paper's 1e-4 barely moved the
#: model in an epoch on CPU; measured), 5 epochs of 144 training scans (~25 min on one core; the
#: loss plateaued after epoch 3-4). A ``prior="sector-iter"`` model trained with it sees the prior
#: made through the 25-iteration training surrogate on exact correspondences (``sector_iter``).
#: ``quick-lidar-soft`` is the same with the paper's soft bound (residual output, SoftShrink only).
#: ``paper-lidar`` has the paper's sizes and soft bound.
PRESETS: dict[str, TrainConfig] = {
    "quick-lidar": TrainConfig(generator_overrides={"output": "bounded"}, adv_per_budget=True,
                               lr=1e-3, pretrain_epochs=0, epochs=5, train_samples=144,
                               eval_samples=16,
                               sector_iter={"icp_iterations": 25, "icp_nn_reuse": 0.0}),
    "quick-lidar-soft": TrainConfig(lr=1e-3, train_samples=144, eval_samples=16),
    "paper-lidar": TrainConfig(train_samples=20_000, eval_samples=200, batch_size=6,
                               pretrain_epochs=3, epochs=10, budgets=[1.0], device="cuda"),
    "quick-objects": TrainConfig(dataset="objects", generator_preset="objects",
                                 budgets=[0.05], train_samples=256, eval_samples=32,
                                 batch_size=8, pretrain_epochs=1, epochs=8, lr=1e-3,
                                 lr_step_epochs=7, icp_preset="objects-train"),
    "paper-objects": TrainConfig(dataset="objects", generator_preset="objects", budgets=[0.05],
                                 train_samples=8_900, eval_samples=200, batch_size=32,
                                 pretrain_epochs=50, epochs=50, lr_step_epochs=7,
                                 icp_preset="objects-train", device="cuda"),
}


def train_config(preset: str = "quick-lidar", **overrides: Any) -> TrainConfig:
    """A preset plus overrides."""
    if preset not in PRESETS:
        raise InputError(f"unknown training preset {preset!r}; valid: {', '.join(PRESETS)}")
    return replace(PRESETS[preset], **overrides)


def _load_split(cfg: TrainConfig, split: str, k: int, ctx: ddp.DistContext | None = None):
    cls = registry.datasets.get(cfg.dataset)
    ds = cls.create(seed=0, split=split, **cfg.dataset_params)
    if len(ds) == 0:
        raise InputError(f"dataset {cfg.dataset!r} has no {split!r} samples")
    if ctx is None or not ctx.enabled:
        return ds.take(k)
    return [ds[i] for i in ddp.shard_indices(min(int(k), len(ds)), ctx)]  # this rank's shard


def _budgets(cfg: TrainConfig) -> torch.Tensor:
    from icpbench.attacks.base import validate_budget

    if not isinstance(cfg.budgets, list | tuple) or not cfg.budgets:
        raise InputError(f"budgets (--budgets) must be a non-empty list of numbers, got "
                         f"{cfg.budgets!r}")
    return torch.as_tensor([validate_budget(b) for b in cfg.budgets], dtype=torch.float64)


def check_train_config(cfg: TrainConfig) -> None:
    """Check every setting that can be checked without data, before anything is written.

    Raises:
        InputError: a setting out of range (the message names its flag), unknown generator
            settings (listing the valid ones), or an unknown dataset, ICP preset or weight preset.
    """
    from dataclasses import fields

    from icpbench.harness.options import TrainOptions
    from icpbench.learning.network import GeneratorConfig, generator_config

    TrainOptions.parse({k: getattr(cfg, k) for k in (  # the fields a flag sets, one model
        "epochs", "pretrain_epochs", "train_samples", "eval_samples", "batch_size", "threads",
        "lr", "alpha", "max_minutes", "budgets", "strict", "adv_per_budget", "icp_backprop")})
    if cfg.pretrain_epochs + cfg.epochs < 1:
        raise InputError(f"--epochs + --pretrain-epochs must be >= 1 (nothing would be trained), "
                         f"got {cfg.epochs} + {cfg.pretrain_epochs}")
    valid = sorted(f.name for f in fields(GeneratorConfig))
    unknown = sorted(set(cfg.generator_overrides) - set(valid))
    if unknown:
        raise InputError(f"unknown generator setting(s) {', '.join(map(repr, unknown))} "
                         f"(--generator-param); valid: {', '.join(valid)}")
    weights(cfg.weights)
    registry.datasets.check_params(cfg.dataset, cfg.dataset_params)
    generator_config(cfg.generator_preset, **cfg.generator_overrides)
    PointToPlaneICP(cfg.icp_preset, soft_dmax=cfg.soft_dmax, backprop=cfg.icp_backprop)


def train(cfg: TrainConfig, out_dir: str | Path, *, progress: bool = True,
          log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Train (or resume) a generator into ``out_dir``; return the model card.

    Files: ``generator.pt`` + ``generator.json`` (the checkpoint, with the model card),
    ``train_state.pt`` (optimiser, scheduler, epoch), ``train_config.json``, ``history.csv``.
    """
    torch.set_num_threads(cfg.threads)
    from icpbench.learning.allocator import retain_for_training

    retain_for_training()  # keep freed memory: faster steps (docs/performance.md, section 3)
    ctx, device = ddp.setup(cfg.device)  # torchrun: process group + this rank's device
    try:
        return _train(cfg, Path(out_dir), ctx, device, progress=progress and ctx.is_main,
                      log=log if ctx.is_main else None)
    finally:
        ddp.cleanup(ctx)


def _train(cfg: TrainConfig, out: Path, ctx: ddp.DistContext, device: str, *, progress: bool,
           log: Callable[[str], None] | None) -> dict[str, Any]:
    """Check, lock ``out``, train; a run that fails before its first checkpoint removes the
    files it created (so the corrected command is not refused as another configuration)."""
    check_train_config(cfg)  # before anything is written: a refused command leaves no trace
    cfg_path = out / "train_config.json"
    if cfg_path.exists() and json.loads(cfg_path.read_text()) != asdict(cfg):
        raise InputError(f"{out} holds a training run with another configuration; use a new --out")
    if not cfg_path.exists() and any((out / f).exists() for f in ("generator.pt", "generator.json")):
        raise InputError(f"{out} already holds a generator.pt/.json that no training run in this "
                         "folder wrote; training would overwrite it: use a new --out")
    if ctx.is_main:
        claim(out, "train")
    else:
        out.mkdir(parents=True, exist_ok=True)
    with lock_results_dir(out) if ctx.is_main else nullcontext():
        if cfg_path.exists() and json.loads(cfg_path.read_text()) != asdict(cfg):  # again, locked
            raise InputError(f"{out} holds a training run with another configuration; use a new "
                             "--out")
        fresh = not cfg_path.exists()
        try:
            return _train_locked(cfg, out, ctx, device, progress=progress, log=log)
        except BaseException:
            if fresh and ctx.is_main and not (out / "generator.pt").exists():
                for f in ("train_config.json", "history.csv"):
                    (out / f).unlink(missing_ok=True)
            raise


def _train_locked(cfg: TrainConfig, out: Path, ctx: ddp.DistContext, device: str, *,
                  progress: bool, log: Callable[[str], None] | None) -> dict[str, Any]:
    """:func:`_train` once the configuration is checked and ``out`` is locked."""
    from icpbench.learning.checkpoint import load_checkpoint, save_checkpoint
    from icpbench.learning.network import Generator, add_prior, generator_config

    cfg_path = out / "train_config.json"
    if ctx.is_main:
        write_json(cfg_path, asdict(cfg))
    w = weights(cfg.weights)
    budgets = _budgets(cfg)
    # validates the ICP settings before any data is loaded
    surrogate = PointToPlaneICP(cfg.icp_preset, soft_dmax=cfg.soft_dmax, backprop=cfg.icp_backprop)
    conditioned = budgets.numel() > 1
    gcfg = generator_config(cfg.generator_preset,
                            **{"conditioned": conditioned, **cfg.generator_overrides})
    torch.manual_seed(cfg.seed)
    if cfg.init_checkpoint is not None:  # fine-tuning: the checkpoint's own config wins
        model = load_checkpoint(cfg.init_checkpoint, map_location=device).model.train()
        if cfg.generator_overrides.get("prior", "none") != "none" and not model.needs_prior:
            model = add_prior(model, cfg.generator_overrides["prior"],
                              float(cfg.generator_overrides.get("prior_gain", 2.0)),
                              float(cfg.generator_overrides.get("prior_dmax", 5.0)))
    else:
        model = Generator(gcfg).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.lr_step_epochs, gamma=cfg.lr_gamma)
    state_path, ckpt = out / "train_state.pt", out / "generator.pt"
    start_epoch, wall_before = 0, 0.0
    if state_path.exists() and ckpt.exists():
        model = load_checkpoint(ckpt, map_location=device).model.train()
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
        sched = torch.optim.lr_scheduler.StepLR(opt, step_size=cfg.lr_step_epochs,
                                                gamma=cfg.lr_gamma)
        try:
            st = torch.load(state_path, weights_only=True, map_location="cpu")
        except Exception as exc:  # truncated or corrupt: torch says "Invalid argument" or similar
            raise CheckpointError(f"{state_path} is truncated or corrupt ({type(exc).__name__}); "
                                  "delete it (and generator.pt) to train from scratch") from exc
        opt.load_state_dict(st["optimizer"])
        sched.load_state_dict(st["scheduler"])
        start_epoch, wall_before = int(st["epoch"]), float(st["wall_s"])
    total_epochs = cfg.pretrain_epochs + cfg.epochs
    net = ddp.wrap_model(model, ctx, device)  # DDP averages gradients over ranks in backward()

    t_data = time.perf_counter()
    train_set = _load_split(cfg, "train", cfg.train_samples, ctx)
    geos = [model.precompute(torch.as_tensor(s.scan[None], dtype=torch.float32))
            for s in train_set]
    priors = [_prior(model, s) for s in train_set]
    iter_priors: dict[tuple[int, float], torch.Tensor] = {}  # prior="sector-iter": per (scan, λ)
    prior_icp = PointToPlaneICP(cfg.icp_preset)  # forward only: the plain preset, as at run time
    prior_settings = SectorIterSettings.from_mapping(cfg.sector_iter, "training sector_iter")
    data_s = time.perf_counter() - t_data
    n_train = len({i for ids in ddp.all_gather([s.id for s in train_set], ctx) for i in ids})
    rng = np.random.default_rng(cfg.seed)
    for _ in range(start_epoch):  # keep the shuffling stream aligned on resume
        rng.permutation(len(train_set))
        rng.random(len(train_set))
    history_path = out / "history.csv"
    if ctx.is_main and not history_path.exists():
        write_file(history_path, "epoch,phase,loss,l_adv,l_rec,trans_err_xy,lr,wall_s\n")
    t0 = time.perf_counter()
    from icpbench.learning.geometry import Geometry

    for epoch in range(start_epoch, total_epochs):
        pretrain = epoch < cfg.pretrain_epochs
        alpha, beta = (0.0, 1.0) if pretrain else (cfg.alpha, cfg.beta)
        order = rng.permutation(len(train_set))
        u = rng.random(len(train_set))
        model.train()
        sums = {"loss": 0.0, "l_adv": 0.0, "l_rec": 0.0, "err": 0.0, "n": 0}
        steps = range(0, len(order), cfg.batch_size)
        bar = progress_bar(total=len(steps), disable=not progress,
                           desc=f"epoch {epoch + 1}/{total_epochs} ({'pretrain' if pretrain else 'attack'})")
        for s in steps:
            idx = order[s:s + cfg.batch_size]
            batch = Batch.from_samples([train_set[i] for i in idx])
            x = batch.scans.to(torch.float32).to(device)
            geo = Geometry.stack([geos[i] for i in idx]).to(device)
            lam = budgets[np.minimum((u[idx] * budgets.numel()).astype(int), budgets.numel() - 1)]
            if model.config.prior == "sector-iter":  # depends on lambda: per (scan, λ)
                prior = torch.cat([_iterated_prior(model, train_set[i], float(v), prior_icp,
                                                   prior_settings, iter_priors, int(i))
                                   for i, v in zip(idx, lam.tolist(), strict=True)]).to(device)
            else:
                prior = None if priors[0] is None else torch.cat([priors[i] for i in idx]).to(device)
            x_adv = net(x, geo, lam.to(torch.float32).to(device) if model.needs_budget else None,
                        prior)
            if cfg.strict:
                x_adv = project_to_ball(x, x_adv, lam.to(x.dtype).to(device))
            l_rec = reconstruction_loss(x.double(), x_adv.double(), lam.to(device)).mean()
            if alpha > 0:
                reg = surrogate.register(x_adv.double().cpu(), batch.maps, batch.T_init)
                xi = pose_error(reg.T, batch.T_gt)
                l_adv = adversarial_loss(xi, w)
                if cfg.adv_per_budget:  # errors grow ~linearly with lambda: balance the budgets
                    l_adv = l_adv / lam.to(l_adv.dtype)
                l_adv = l_adv.mean()
                err = float(torch.linalg.norm(xi[:, :2].detach(), dim=-1).mean())
            else:
                l_adv, err = torch.zeros((), dtype=torch.float64), float("nan")
            loss = alpha * l_adv + beta * l_rec
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            sums["loss"] += float(loss.detach())
            sums["l_adv"] += float(l_adv.detach())
            sums["l_rec"] += float(l_rec.detach())
            sums["err"] += 0.0 if math.isnan(err) else err
            sums["n"] += 1
            bar.set_postfix(loss=f"{sums['loss'] / sums['n']:.4f}",
                            rec=f"{sums['l_rec'] / sums['n']:.4f}",
                            err_xy=f"{sums['err'] / sums['n']:.3f}" if not pretrain else "-")
            bar.update(1)
        bar.close()
        sched.step()
        wall = wall_before + time.perf_counter() - t0
        sums = ddp.all_reduce_sums(sums, ctx)  # epoch statistics over every rank's steps
        n = max(sums["n"], 1)
        bad = _nonfinite(model, sums)
        if bad:
            raise InputError(f"training diverged in epoch {epoch + 1} ({bad}); this epoch was not "
                             f"saved; lower --lr (now {cfg.lr:g})")
        if not ctx.is_main:  # rank 0 writes the files; the others wait for them
            ddp.barrier(ctx)
            if ddp.broadcast(None, ctx):
                break
            continue
        with open(history_path, "a") as f:
            f.write(f"{epoch + 1},{'pretrain' if pretrain else 'attack'},{sums['loss'] / n:.6g},"
                    f"{sums['l_adv'] / n:.6g},{sums['l_rec'] / n:.6g},"
                    f"{(sums['err'] / n) if not pretrain else float('nan'):.6g},"
                    f"{opt.param_groups[0]['lr']:.3g},{wall:.1f}\n")
        card = _card(cfg, epoch + 1, wall, data_s, n_train)
        if ctx.enabled:
            card["distributed"] = ddp.describe(ctx, cfg.batch_size)
        save_checkpoint(model, ckpt, card)
        tmp_state = state_path.with_name(state_path.name + ".tmp")
        torch.save({"optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                    "epoch": epoch + 1, "wall_s": wall}, tmp_state)
        os.replace(tmp_state, state_path)  # atomic: a killed run leaves the old state or the new
        if log is not None:
            log(f"epoch {epoch + 1}: loss {sums['loss'] / n:.4f} err_xy "
                f"{sums['err'] / n:.3f} m ({wall / 60:.1f} min)")
        stop = cfg.max_minutes is not None and wall > 60 * cfg.max_minutes
        ddp.barrier(ctx)
        if ddp.broadcast(stop, ctx):
            break
    card = evaluate(cfg, ckpt, progress=progress) if ctx.is_main else None
    if ctx.is_main:
        save_checkpoint(load_checkpoint(ckpt).model, ckpt, card)
    ddp.barrier(ctx)
    return ddp.broadcast(card, ctx)


def _nonfinite(model: torch.nn.Module, sums: dict[str, float]) -> str:
    """What is not finite after an epoch (the mean loss or some weights), or ``""``."""
    if not math.isfinite(sums["loss"]):
        return f"the loss is {sums['loss']}"
    for name, p in model.state_dict().items():
        if p.is_floating_point() and not bool(torch.isfinite(p).all()):
            return f"weights {name} are NaN or Inf"
    return ""


def _prior(model: torch.nn.Module, sample: Any) -> torch.Tensor | None:
    """Prior channels (1, N, 8) of one training sample for prior models (else None); computed
    once per scan, like the index precompute."""
    if not model.needs_prior or model.config.prior == "sector-iter":
        return None
    from icpbench.core.mapindex import MapIndex

    return torch.as_tensor(sector_prior(sample.scan, sample.T_gt,
                                        MapIndex(sample.map, sample.map_normals),
                                        model.config.prior_dmax))[None]


def _iterated_prior(model: torch.nn.Module, sample: Any, budget_m: float, icp: Any,
                    settings: SectorIterSettings, cache: dict[tuple[int, float], torch.Tensor],
                    key: int) -> torch.Tensor:
    """Prior channels (1, N, 8) of ``prior="sector-iter"`` for one training scan at one budget
    (metres), computed on first use with the training surrogate ``icp`` and the iterated attack's
    ``settings``, and kept in ``cache``."""
    k = (key, budget_m)
    if k not in cache:
        cache[k] = prior_channels(model.config, Batch.from_samples([sample]),
                                  torch.tensor([budget_m]), icp, settings)
    return cache[k]


def _card(cfg: TrainConfig, epochs_done: int, wall_s: float, data_s: float,
          n_train: int) -> dict[str, Any]:
    """The model card; a fine-tuned model also carries the card of the checkpoint it started from
    (``init_card``, with that one's own lineage) and ``train_wall_s_total``, the wall time summed
    along the chain (seconds)."""
    card = _own_card(cfg, epochs_done, wall_s, data_s, n_train)
    if cfg.init_checkpoint is not None:
        from icpbench.learning.checkpoint import read_checkpoint_meta

        parent = read_checkpoint_meta(cfg.init_checkpoint)[1]["card"]
        card["init_card"] = parent
        card["train_wall_s_total"] = round(
            wall_s + float(parent.get("train_wall_s_total", parent.get("train_wall_s", 0.0))), 1)
    return card


def _own_card(cfg: TrainConfig, epochs_done: int, wall_s: float, data_s: float,
              n_train: int) -> dict[str, Any]:
    return {
        "data": {"dataset": cfg.dataset, "params": cfg.dataset_params, "split": "train",
                 "samples": n_train},
        "budgets_m": list(cfg.budgets), "weights": cfg.weights,
        "epochs_done": epochs_done, "pretrain_epochs": cfg.pretrain_epochs,
        "epochs_planned": cfg.pretrain_epochs + cfg.epochs,
        "train_wall_s": round(wall_s, 1), "data_prep_s": round(data_s, 1),
        "hardware": {"device": cfg.device, "threads": cfg.threads,
                     "machine": platform.machine(), "processor": platform.processor()},
        "optimiser": {"lr": cfg.lr, "step_epochs": cfg.lr_step_epochs, "gamma": cfg.lr_gamma,
                      "alpha": cfg.alpha, "beta": cfg.beta, "batch_size": cfg.batch_size},
        "icp_preset": cfg.icp_preset,
        "icp_backprop": cfg.icp_backprop,
        "strict_training": cfg.strict,
        "adv_per_budget": cfg.adv_per_budget,
        "init_checkpoint": cfg.init_checkpoint,
        "sector_iter": (SectorIterSettings.from_mapping(cfg.sector_iter).as_dict()
                        if cfg.sector_iter else None),
    }


def evaluate(cfg: TrainConfig, ckpt: Path, *, progress: bool = False) -> dict[str, Any]:
    """Held-out evaluation (test split, test ICP settings) written into the model card."""
    from icpbench.learning.checkpoint import load_checkpoint

    lg = load_checkpoint(ckpt, map_location=cfg.device)
    card = dict(lg.card)
    test = _load_split(cfg, "test", cfg.eval_samples)
    target = PointToPlaneICP(cfg.icp_preset.replace("-train", ""))
    res = {}
    for lam in cfg.budgets:
        errs, disp = [], []
        for i in range(0, len(test), 4):
            batch = Batch.from_samples(test[i:i + 4])
            x = batch.scans.to(torch.float32)
            with torch.no_grad():
                geo = lg.model.precompute(x)
                prior = prior_channels(lg.model.config, batch, torch.full((len(batch),), float(lam)),
                                       PointToPlaneICP(cfg.icp_preset),
                                       SectorIterSettings.from_mapping(cfg.sector_iter))
                prior = None if prior is None else prior.to(cfg.device)
                adv = lg.model(x.to(cfg.device), geo.to(cfg.device),
                               torch.full((len(batch),), float(lam)) if lg.model.needs_budget
                               else None, prior).cpu().double()
                reg = target.register(adv, batch.maps, batch.T_init)
            e = pose_error_components(reg.T, batch.T_gt)
            errs += [float(v) for v, c in zip(e["trans_err_xy"], reg.converged, strict=True) if c]
            disp += [float(v) for v in torch.linalg.norm(adv - batch.scans, dim=-1).max(1).values]
        res[f"{lam:g}"] = {"trans_err_xy_mean": float(np.mean(errs)) if errs else None,
                           "converged": len(errs), "samples": len(test),
                           "disp_max_mean": float(np.mean(disp))}
    card["heldout_eval"] = res
    return card
