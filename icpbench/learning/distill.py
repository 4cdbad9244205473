"""Amortising the iterated analytic attack: the generator learns the expensive attack's output.

Beyond the paper. The iterated sector attack (:mod:`icpbench.core.iterated_sector`) finds more the
more re-linearisation steps it takes, at about one surrogate ICP per step and scan. The generator
runs on the cheap setting (2 steps, the ``sector-iter`` attack's default, whose computation Table 1
shares with that row). Here the network is taught to map what it is given at run time (the scan,
the cheap attack's displacement and the one-step channels of :mod:`icpbench.learning.prior`) to
the displacement of the expensive setting (8 steps): a per-point direction inside the lambda-ball,
learned by regression, with no ICP in the training loop. This is the amortisation of an
optimisation into one forward pass that Zhang et al. (ICRA 2025) motivate the generator with, and
of learned-optimiser distillation generally (e.g. Xiao et al., "Generating adversarial examples
with adversarial networks", IJCAI 2018, train a generator to replace an optimisation attack).

Two steps, each resumable:

1. :func:`make_targets` runs both settings on training scans for every budget and writes shards
   (``chunk_<first>.npz``) into a folder with the settings recorded (``targets.json``).
2. :func:`train_distilled` fits a ``prior="sector-iter"``, ``output="ball"``, budget-conditioned
   generator to them (mean squared error between unit displacements) and writes a checkpoint the
   ``generator`` attack loads. Its zero-initialised head with prior gain 1 starts as the cheap
   attack exactly; the validation line reports the share of the cheap-to-expensive squared gap the
   model closes on held-out scans.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import platform
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from icpbench.core.errors import InputError
from icpbench.core.iterated_sector import SectorIterSettings, iterated_sector
from icpbench.core.types import Batch

#: Budgets of the shipped lidar-sim models (metres).
DEFAULT_BUDGETS = (1.0, 2.0, 3.0, 4.0, 5.0)
#: Keys of one shard (see :func:`make_targets`).
SHARD_KEYS = ("ids", "scan", "fps", "stat", "cheap", "target", "cheap_err", "target_err", "budgets")
#: Unit displacements are stored as int8 in steps of 1/QUANT (|error| <= 0.4% of lambda).
QUANT = 127.0
#: Training losses of :func:`train_distilled` (see :class:`DistillConfig`).
LOSSES = ("mse", "align")


@dataclass(frozen=True)
class TargetSpec:
    """What :func:`make_targets` computes (saved as ``targets.json``; a folder holds one spec).

    Attributes:
        dataset, dataset_params, split: the scans (a registered dataset).
        samples: the first ``samples`` scans of the split.
        budgets: lambda values (metres).
        cheap, target: settings of the iterated sector attack the model is given / learns
            (:class:`SectorIterSettings` field names; missing ones keep their defaults).
        icp_preset: the surrogate point-to-plane ICP of both (the evaluation ICP's preset).
        chunk: scans per shard (and per surrogate batch).
    """

    dataset: str = "lidar-sim"
    dataset_params: dict[str, Any] = field(default_factory=dict)
    split: str = "train"
    samples: int = 128
    budgets: tuple[float, ...] = DEFAULT_BUDGETS
    cheap: dict[str, Any] = field(default_factory=dict)
    target: dict[str, Any] = field(default_factory=lambda: {"iterations": 8})
    icp_preset: str = "lidar"
    chunk: int = 4

    def check(self) -> tuple[SectorIterSettings, SectorIterSettings]:
        """The two settings, checked.

        Raises:
            InputError: a bad setting (the message names it).
        """
        if int(self.samples) < 1 or int(self.chunk) < 1:
            raise InputError(f"samples and chunk must be >= 1, got {self.samples}, {self.chunk}")
        if not self.budgets or not all(math.isfinite(b) and b > 0 for b in self.budgets):
            raise InputError(f"budgets must be finite numbers > 0 (metres), got {self.budgets}")
        return (SectorIterSettings.from_mapping(self.cheap, "cheap sector-iter settings"),
                SectorIterSettings.from_mapping(self.target, "target sector-iter settings"))

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["budgets"] = [float(b) for b in self.budgets]
        return d


def make_targets(spec: TargetSpec, out_dir: str | Path, *, shards: Sequence[int] | None = None,
                 log: Callable[[str], None] | None = None) -> list[Path]:
    """Write the training pairs of ``spec`` into ``out_dir``; return the shard paths written now.

    Each shard ``chunk_<first scan index>.npz`` (compressed) holds, for ``B`` scans of ``N`` points
    and ``L`` budgets: ``ids`` (B,), ``scan`` (B, N, 3) float32 sensor frame [m], ``fps`` (B, n2)
    int32 (the network's level indices, :func:`~icpbench.learning.geometry.nested_fps_levels`,
    so that training needs no Open3D), ``stat`` (B, N, 5) float16 (the one-step channels 3:8 of
    :func:`~icpbench.learning.prior.sector_prior`), ``cheap`` and ``target`` (B, L, N, 3) int8
    (each attack's displacement divided by lambda, |.| <= 1, times :data:`QUANT`),
    ``cheap_err`` and ``target_err`` (B, L) (each attack's surrogate horizontal error [m]) and
    ``budgets`` (L,). Shards already present are skipped (resumable); ``shards`` restricts the work
    to those shard indices (to split it over processes).

    Raises:
        InputError: ``out_dir`` holds targets of another spec, or a bad setting.
    """
    from icpbench.core import registry
    from icpbench.harness.outputs import write_json
    from icpbench.learning.geometry import nested_fps_levels
    from icpbench.learning.prior import sector_prior_batch
    from icpbench.targets.p2plane import PointToPlaneICP

    cheap, target = spec.check()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = out / "targets.json"
    if meta.exists():
        if json.loads(meta.read_text()) != spec.as_dict():
            raise InputError(f"{out} holds targets of another spec; use a new folder")
    else:
        write_json(meta, spec.as_dict())
    ds = registry.datasets.get(spec.dataset).create(seed=0, split=spec.split, **spec.dataset_params)
    n = min(int(spec.samples), len(ds))
    icp = PointToPlaneICP(spec.icp_preset)
    geo_cfg = distilled_model().config.geometry
    starts = list(range(0, n, spec.chunk))
    todo = [starts[i] for i in (shards if shards is not None else range(len(starts)))]
    written = []
    for first in todo:
        path = out / f"chunk_{first:05d}.npz"
        if path.exists():
            continue
        t0 = time.perf_counter()
        samples = [ds[j] for j in range(first, min(first + spec.chunk, n))]
        b = Batch.from_samples(samples)
        stat = sector_prior_batch(b.scans, b.T_gt, b.maps).numpy()[..., 3:8]
        cols: dict[str, list[np.ndarray]] = {"cheap": [], "target": [], "cheap_err": [],
                                             "target_err": []}
        clean = b.scans.numpy()
        for lam in spec.budgets:
            bb = Batch.from_samples(samples, maps=b.maps)  # fresh memo per budget
            for name, s in (("cheap", cheap), ("target", target)):
                r = iterated_sector(bb, float(lam), icp, s)
                cols[name].append((r.scans - clean) / float(lam))
                cols[f"{name}_err"].append(r.surrogate_xy)
        sizes = geo_cfg.level_sizes(clean.shape[1])[1:]
        arrays = {"ids": np.array([s.id for s in samples]), "scan": clean.astype(np.float32),
                  "fps": np.stack([nested_fps_levels(c, sizes) for c in clean]).astype(np.int32),
                  "stat": stat.astype(np.float16),
                  **{k: quantise(np.stack(v, 1)) for k, v in cols.items() if not k.endswith("err")},
                  **{k: np.stack(v, 1) for k, v in cols.items() if k.endswith("err")},
                  "budgets": np.asarray(spec.budgets, dtype=np.float64)}
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)  # atomic: a killed run leaves no half shard
        written.append(path)
        if log is not None:
            log(f"{path.name}: {len(samples)} scans in {time.perf_counter() - t0:.0f} s; mean "
                f"surrogate error cheap {np.nanmean(arrays['cheap_err']):.2f} m, target "
                f"{np.nanmean(arrays['target_err']):.2f} m")
    return written


def quantise(unit: np.ndarray) -> np.ndarray:
    """Unit displacements (|.| <= 1) as int8 in steps of 1 / :data:`QUANT`."""
    return np.clip(np.round(np.asarray(unit, dtype=np.float64) * QUANT), -QUANT, QUANT).astype(np.int8)


@dataclass
class TargetSet:
    """Every shard of a targets folder, concatenated (shapes as in :func:`make_targets`, S scans;
    ``cheap`` and ``target`` still int8, see :data:`QUANT`)."""

    ids: np.ndarray
    scan: np.ndarray
    fps: np.ndarray
    stat: np.ndarray
    cheap: np.ndarray
    target: np.ndarray
    cheap_err: np.ndarray
    target_err: np.ndarray
    budgets: np.ndarray

    def __len__(self) -> int:
        return int(self.scan.shape[0])


def load_targets(folder: str | Path) -> TargetSet:
    """Read every ``chunk_*.npz`` of ``folder`` in scan order.

    Raises:
        InputError: no shard, a shard without the expected keys, or shards of different budgets.
    """
    paths = sorted(Path(folder).glob("chunk_*.npz"))
    paths = [p for p in paths if not p.name.endswith(".tmp.npz")]
    if not paths:
        raise InputError(f"{folder} holds no target shards (chunk_*.npz); run make_targets first")
    parts = []
    for p in paths:
        with np.load(p) as z:
            missing = [k for k in SHARD_KEYS if k not in z.files]
            if missing:
                raise InputError(f"{p} lacks {missing}: not a target shard")
            parts.append({k: z[k] for k in SHARD_KEYS})
    if any(not np.array_equal(q["budgets"], parts[0]["budgets"]) for q in parts):
        raise InputError(f"the shards of {folder} have different budgets")
    return TargetSet(budgets=parts[0]["budgets"], **{
        k: np.concatenate([q[k] for q in parts]) for k in SHARD_KEYS if k != "budgets"})


@dataclass
class DistillConfig:
    """Optimisation of :func:`train_distilled` (saved in the model card).

    Attributes:
        epochs: passes over every (scan, budget) pair of the training scans (at most).
        batch_size: pairs per step.
        lr: AdamW learning rate, decayed to 5% along a cosine over the epochs, or over
            ``max_minutes`` of wall time when that is set (so that a run of fixed length ends its
            schedule on any hardware).
        loss: ``"mse"``: squared distance to the target's unit displacement; ``"align"``: minus
            the dot product with it, which with the ball output commits every point to the full
            budget in the target's expected direction rather than shrinking uncertain points.
        val_scans: the last ``val_scans`` scans of the folder are held out for the validation line.
        seed: shuffling and initialisation.
        device: ``cpu`` or ``cuda``.
        max_minutes: stop once this wall time (training, not the index precompute) is passed.
        workers: processes of the index precompute (FPS and neighbour groups, on the CPU).
    """

    epochs: int = 40
    batch_size: int = 16
    lr: float = 1e-3
    val_scans: int = 8
    seed: int = 0
    device: str = "cpu"
    max_minutes: float | None = None
    workers: int = 1
    loss: str = "mse"


def _precompute(args: tuple[Any, np.ndarray, np.ndarray]) -> Any:
    geo_cfg, scan, fps = args
    from icpbench.learning.geometry import compute_geometry

    torch.set_num_threads(1)
    return compute_geometry(scan, geo_cfg, fps=fps)


def distilled_model(prior_gain: float = 1.0):
    """A fresh generator for distillation: lidar preset, ``prior="sector-iter"``, ``output="ball"``,
    budget-conditioned; with its zero head it returns the cheap attack's displacement exactly."""
    from icpbench.learning.network import Generator, generator_config

    return Generator(generator_config("lidar", prior="sector-iter", output="ball",
                                      prior_gain=float(prior_gain), conditioned=True))


def unit_displacement(model: Any, x: torch.Tensor, geo: Any, lam: torch.Tensor,
                      prior: torch.Tensor) -> torch.Tensor:
    """The model's displacement divided by the budget, (B, N, 3) with |.| <= 1."""
    return (model(x, geo, lam, prior) - x) / lam[:, None, None]


def train_distilled(data_dir: str | Path, out_dir: str | Path, cfg: DistillConfig | None = None,
                    *, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Fit a generator to the targets in ``data_dir``; write ``generator.pt``/``.json`` and
    ``history.csv`` into ``out_dir`` after every epoch; return the model card.

    Raises:
        InputError: bad settings, or no scan left for training.
    """
    from icpbench.learning.checkpoint import save_checkpoint
    from icpbench.learning.geometry import Geometry

    cfg = cfg or DistillConfig()
    if cfg.epochs < 1 or cfg.batch_size < 1 or not cfg.lr > 0 or cfg.val_scans < 0:
        raise InputError(f"need epochs >= 1, batch_size >= 1, lr > 0, val_scans >= 0; got {cfg}")
    if cfg.loss not in LOSSES:
        raise InputError(f"loss must be one of {LOSSES}, got {cfg.loss!r}")
    data = load_targets(data_dir)
    spec = json.loads((Path(data_dir) / "targets.json").read_text())
    S, L = len(data), len(data.budgets)
    n_train = S - cfg.val_scans
    if n_train < 1:
        raise InputError(f"{S} scans leave none for training with val_scans={cfg.val_scans}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    model = distilled_model()
    t_prep = time.perf_counter()
    jobs = [(model.config.geometry, data.scan[i], data.fps[i]) for i in range(S)]
    if cfg.workers > 1:
        # spawned, not forked: a fork of a process whose torch runtime already started threads
        # can hang (measured here: the forked pool never returned)
        with ProcessPoolExecutor(cfg.workers, mp_context=mp.get_context("spawn")) as pool:
            geos = list(pool.map(_precompute, jobs, chunksize=2))
    else:
        geos = [_precompute(j) for j in jobs]
    prep_s = time.perf_counter() - t_prep
    dev = torch.device(cfg.device)
    model = model.to(dev).train()
    scans = torch.as_tensor(data.scan, device=dev)
    stat = torch.as_tensor(data.stat.astype(np.float32), device=dev)
    cheap = torch.as_tensor(data.cheap, device=dev).float() / QUANT
    target = torch.as_tensor(data.target, device=dev).float() / QUANT
    lams = torch.as_tensor(data.budgets, dtype=torch.float32, device=dev)
    geos = [g.to(dev) for g in geos]

    def run(pairs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        i, j = torch.as_tensor(pairs[:, 0], device=dev), torch.as_tensor(pairs[:, 1], device=dev)
        geo = Geometry.stack([geos[k] for k in pairs[:, 0].tolist()])
        prior = torch.cat([cheap[i, j], stat[i]], -1)
        return unit_displacement(model, scans[i], geo, lams[j], prior), target[i, j]

    def per_sample(u: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mse, alignment) per sample: mean over points of |u - t|^2 and of u . t."""
        return ((u - t) ** 2).sum(-1).mean(-1), (u * t).sum(-1).mean(-1)

    train_pairs = np.array([(i, j) for i in range(n_train) for j in range(L)])
    val_pairs = np.array([(i, j) for i in range(n_train, S) for j in range(L)]).reshape(-1, 2)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    steps_per_epoch = math.ceil(len(train_pairs) / cfg.batch_size)
    rng = np.random.default_rng(cfg.seed)
    (out / "history.csv").write_text("epoch,train_loss,val_mse,val_align,val_cheap_mse,"
                                     "val_cheap_align,val_gap_closed,lr,wall_s\n")
    if len(val_pairs):
        vi, vj = val_pairs[:, 0], val_pairs[:, 1]
        cm, ca = per_sample(cheap[vi, vj], target[vi, vj])
        val_cheap, val_cheap_align = float(cm.mean()), float(ca.mean())
    else:
        val_cheap = val_cheap_align = float("nan")
    t0 = time.perf_counter()
    card: dict[str, Any] = {}
    step = 0
    for epoch in range(cfg.epochs):
        order = train_pairs[rng.permutation(len(train_pairs))]
        tot, cnt = 0.0, 0
        for s in range(0, len(order), cfg.batch_size):
            if cfg.max_minutes is not None:
                progress = (time.perf_counter() - t0) / (60.0 * cfg.max_minutes)
            else:
                progress = step / (cfg.epochs * steps_per_epoch)
            for g in opt.param_groups:  # cosine from lr to 5% of it
                g["lr"] = cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0))))
            mse, align = per_sample(*run(order[s:s + cfg.batch_size]))
            loss = (mse if cfg.loss == "mse" else -align).mean()
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            step += 1
            tot, cnt = tot + float(loss.detach()) * len(mse), cnt + len(mse)
        if not math.isfinite(tot):
            raise InputError(f"training diverged in epoch {epoch + 1}; lower the learning rate")
        model.eval()
        with torch.no_grad():
            parts = [per_sample(*run(val_pairs[s:s + cfg.batch_size]))
                     for s in range(0, len(val_pairs), cfg.batch_size)]
        model.train()
        val = float(torch.cat([m for m, _ in parts]).mean()) if parts else float("nan")
        val_align = float(torch.cat([a for _, a in parts]).mean()) if parts else float("nan")
        wall = time.perf_counter() - t0
        closed = 1.0 - val / val_cheap if val_cheap > 0 else float("nan")
        lr_now = opt.param_groups[0]["lr"]
        with open(out / "history.csv", "a") as f:
            f.write(f"{epoch + 1},{tot / cnt:.6g},{val:.6g},{val_align:.6g},{val_cheap:.6g},"
                    f"{val_cheap_align:.6g},{closed:.4f},{lr_now:.3g},{wall:.1f}\n")
        card = {
            "objective": f"distilled ({cfg.loss}) towards the target attack's unit displacement "
                         "(icpbench.learning.distill); no ICP in the loss",
            "data": {"dataset": spec["dataset"], "params": spec["dataset_params"],
                     "split": spec["split"], "samples": n_train, "held_out": S - n_train},
            "budgets_m": [float(b) for b in data.budgets], "weights": "none",
            "epochs_done": epoch + 1, "pretrain_epochs": 0, "epochs_planned": cfg.epochs,
            "optimiser": {"lr": cfg.lr, "schedule": "cosine to 5%"
                          + (f" over {cfg.max_minutes} min" if cfg.max_minutes else ""),
                          "batch_size": cfg.batch_size, "loss": cfg.loss},
            "icp_preset": "none", "icp_backprop": "none",
            "train_wall_s": round(wall, 1), "data_prep_s": round(prep_s, 1),
            "hardware": {"device": cfg.device, "machine": platform.machine(),
                         "gpu": torch.cuda.get_device_name(0) if dev.type == "cuda" else None},
            "sector_iter": SectorIterSettings.from_mapping(spec["cheap"]).as_dict(),
            "distill_target": SectorIterSettings.from_mapping(spec["target"]).as_dict(),
            "validation": None if not len(val_pairs) else {
                "scans": S - n_train, "mse": round(val, 6), "cheap_mse": round(val_cheap, 6),
                "align": round(val_align, 6), "cheap_align": round(val_cheap_align, 6),
                "gap_closed": round(closed, 4)},
        }
        save_checkpoint(model.cpu() if dev.type != "cpu" else model, out / "generator.pt", card)
        model.to(dev)
        if log is not None:
            log(f"epoch {epoch + 1}: train loss {tot / cnt:.4f}; val mse {val:.4f} (cheap "
                f"{val_cheap:.4f}: {100 * closed:.1f}% of the gap closed), align {val_align:.4f} "
                f"(cheap {val_cheap_align:.4f}); lr {lr_now:.2g}; {wall:.0f} s")
        if cfg.max_minutes is not None and wall > 60 * cfg.max_minutes:
            break
    return card
