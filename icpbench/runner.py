"""The evaluation grid: samples x attacks x targets x budgets x seeds.

Attacks that need gradients get a differentiable *surrogate* target (default ``p2plane``), while the
evaluated targets can be anything, including black boxes: this is how transfer is measured. Each
unit of work (one seed, one batch of samples, one budget, one attack) is attacked once and then
registered by every target; its rows are appended to the results store as soon as it finishes, so
an interrupted run resumes where it stopped. A plugin that raises inside a unit produces rows with
``status = "error"`` and the message, and the run goes on.

Where units are computed is the executor's business (:mod:`icpbench.executors`: ``local`` in this
process, ``ray`` on a Ray cluster); every executor yields the rows in grid order and only this
process writes them, so the results file is the same whatever the executor.
"""

from __future__ import annotations

import math
import platform
import subprocess
import time
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from functools import partial
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np
import torch

from icpbench import registry
from icpbench.attacks.base import STAT_COLUMNS, Attack, AttackOutput, validate_budget
from icpbench.errors import InputError
from icpbench.executors import WorkItem, check_executor, get_executor
from icpbench.progress import progress_bar
from icpbench.results import (
    MANIFEST_FILE,
    ResultsStore,
    read_manifest,
    row_key,
    write_json_atomic,
)
from icpbench.se3 import POSE_ERROR_COLUMNS, pose_error_components
from icpbench.targets.base import Target
from icpbench.types import Batch, Sample


@dataclass
class RunConfig:
    """Everything that determines a run's results (written to the manifest).

    Attributes:
        dataset: registered dataset name.
        dataset_params: constructor kwargs of the dataset (besides seed/split).
        split: dataset split to evaluate ("test" by default).
        dataset_seed: seed of the dataset itself.
        attacks, targets: registered names.
        budgets: perturbation budgets lambda (metres; normalised units for ``objects``).
        samples: number of samples (the first K of the split; None = all).
        seeds: attack seeds; each adds one row per (sample, attack, target, budget).
        surrogate: differentiable target that gradient-based attacks use.
        icp_preset: ICP settings preset for every target (default: the dataset's).
        batch_size: samples per batch.
        strict: project every attack's per-point displacement onto its budget ball.
        threads: torch intra-op threads (1 is fastest for these tensor sizes on small CPUs).
        attack_params, target_params: per-plugin constructor kwargs.
        executor: where units of work run (``local`` or ``ray``); results do not depend on it, so
            a run may be resumed with another executor.
    """

    dataset: str = "objects"
    attacks: list[str] = field(default_factory=lambda: ["none", "uniform", "normal"])
    targets: list[str] = field(default_factory=lambda: ["p2plane"])
    budgets: list[float] = field(default_factory=lambda: [1.0])
    samples: int | None = 20
    seeds: list[int] = field(default_factory=lambda: [0])
    surrogate: str = "p2plane"
    split: str = "test"
    dataset_seed: int = 0
    dataset_params: dict[str, Any] = field(default_factory=dict)
    icp_preset: str | None = None
    batch_size: int = 8
    strict: bool = False
    threads: int = 1
    attack_params: dict[str, dict[str, Any]] = field(default_factory=dict)
    target_params: dict[str, dict[str, Any]] = field(default_factory=dict)
    executor: str = "local"

    def validate(self) -> RunConfig:
        """Check names, budgets and sizes; raise InputError listing valid choices."""
        registry.datasets.get(self.dataset)
        self.attacks = registry.attacks.resolve(self.attacks)
        self.targets = registry.targets.resolve(self.targets)
        if self.surrogate not in registry.targets.names():
            registry.targets.get(self.surrogate)
        self.budgets = [validate_budget(b) for b in self.budgets]
        if self.samples is not None and self.samples < 1:
            raise InputError(f"--samples must be >= 1, got {self.samples}")
        if self.batch_size < 1:
            raise InputError(f"batch size must be >= 1, got {self.batch_size}")
        if not self.seeds:
            raise InputError("at least one seed is needed")
        check_executor(self.executor)
        return self


#: RunConfig fields that choose how a run is executed, not what it computes (ignored when a resumed
#: run's configuration is compared with the stored one).
EXECUTION_FIELDS = ("executor",)


def _same_config(a: dict[str, Any], b: dict[str, Any]) -> bool:
    def strip(c: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in c.items() if k not in EXECUTION_FIELDS}
    return strip(a) == strip(b)


def _stable_seed(*parts: Any) -> int:
    return zlib.crc32("|".join(str(p) for p in parts).encode())


def package_versions() -> dict[str, str]:
    """Versions of icpbench and the libraries that shape its numbers."""
    out = {"python": platform.python_version()}
    for pkg in ("icpbench", "torch", "numpy", "scipy", "open3d", "kiss-icp", "small_gicp",
                "pandas", "fpsample"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


#: Top-level folders that hold outputs, not inputs: changes there do not make a run "dirty".
OUTPUT_DIRS = ("results/", "runs/")


def git_commit() -> dict[str, Any]:
    """The source tree's commit and whether its code or config had uncommitted changes.

    ``dirty`` ignores changes under :data:`OUTPUT_DIRS` (other runs writing their results while this
    one starts must not mark it); ``dirty_paths`` lists up to 20 changed tracked paths, outputs
    included, so a reader can judge. ("unknown" outside git.)"""
    here = Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                                capture_output=True, text=True, timeout=10).stdout.splitlines()
        paths = [line[3:].strip() for line in status if line.strip()]
        dirty = any(not p.startswith(OUTPUT_DIRS) for p in paths)
        return {"commit": sha, "dirty": dirty, "dirty_paths": paths[:20]}
    except (OSError, subprocess.SubprocessError):
        return {"commit": "unknown", "dirty": None}


def build_target(name: str, preset: str, params: dict[str, Any] | None = None) -> Target:
    """Instantiate a registered target with an ICP preset and overrides."""
    cls = registry.targets.get(name)
    return cls(preset, **(params or {}))


def build_attack(name: str, strict: bool, params: dict[str, Any] | None = None) -> Attack:
    """Instantiate a registered attack."""
    cls = registry.attacks.get(name)
    return cls(strict=strict, **(params or {}))


def load_dataset(cfg: RunConfig):
    """Instantiate the configured dataset."""
    cls = registry.datasets.get(cfg.dataset)
    return cls(seed=cfg.dataset_seed, split=cfg.split, **cfg.dataset_params)


def _rows_for_unit(samples: Sequence[Sample], attack: str, target: str, budget: float, seed: int,
                   cfg: RunConfig) -> list[dict[str, Any]]:
    return [{"sample_id": s.id, "attack": attack, "target": target, "budget": budget,
             "seed": seed, "surrogate": cfg.surrogate, "strict": cfg.strict,
             "meta": dict(s.meta)} for s in samples]


class GridWorker:
    """Everything one process needs to compute units of work: the dataset, the targets, the
    surrogate, the attacks and the per-map caches, all built from a :class:`RunConfig`.

    The runner builds one in the driver (it also describes the run in the manifest); executors that
    compute elsewhere rebuild equivalent workers from :meth:`factory`.
    """

    def __init__(self, cfg: RunConfig) -> None:
        self.cfg = cfg
        torch.set_num_threads(cfg.threads)
        self.dataset = load_dataset(cfg)
        self.preset = cfg.icp_preset or self.dataset.icp_preset
        self.targets = {n: build_target(n, self.preset, cfg.target_params.get(n))
                        for n in cfg.targets}
        self.surrogate = (self.targets.get(cfg.surrogate) or
                          build_target(cfg.surrogate, self.preset,
                                       cfg.target_params.get(cfg.surrogate)))
        self.attacks = {n: build_attack(n, cfg.strict, {**_attack_context(n, cfg, self.dataset),
                                                        **cfg.attack_params.get(n, {})})
                        for n in cfg.attacks}
        self.prepared: dict[str, dict[str, Any]] = {t: {} for t in self.targets}

    def factory(self) -> Callable[[], GridWorker]:
        """A picklable callable that builds an equivalent worker (in another process or node)."""
        return partial(GridWorker, self.cfg)

    def run(self, item: WorkItem) -> Iterator[list[dict[str, Any]]]:
        """Attack and register one batch for each of ``item.units``; yield each unit's rows."""
        batch = Batch.from_samples([self.dataset[i].validate() for i in range(item.start, item.stop)])
        none_cache: dict[str, tuple] = {}
        for budget, aname in item.units:
            yield _run_unit(batch, self.attacks[aname], self.targets, self.surrogate, self.prepared,
                            budget, item.seed, self.cfg, none_cache)


def run(cfg: RunConfig, out_dir: str | Path, *, progress: bool = True,
        on_unit: Callable[[int], None] | None = None) -> ResultsStore:
    """Run (or resume) the grid of ``cfg`` into ``out_dir``; return the results store.

    Raises:
        InputError: invalid configuration, or ``out_dir`` holds a run with another configuration.
    """
    cfg.validate()
    torch.set_num_threads(cfg.threads)
    out_dir = Path(out_dir)
    worker = GridWorker(cfg)
    dataset, preset = worker.dataset, worker.preset
    manifest = {
        "config": asdict(cfg),
        "icp_preset": preset,
        "dataset": dataset.describe(),
        "versions": package_versions(),
        "git": git_commit(),
        "threads": {"torch": cfg.threads},
        "platform": {"machine": platform.machine(), "system": platform.system(),
                     "processor": platform.processor(), "cpu_count": _cpu_count()},
    }
    manifest["fingerprints"] = {n: a.fingerprint(cfg.budgets) for n, a in worker.attacks.items()}
    old = read_manifest(out_dir)
    if old is not None and not _same_config(old.get("config", {}), manifest["config"]):
        raise InputError(
            f"{out_dir} holds results of a different configuration; use a new --out "
            "(or the same command to resume)"
        )
    if old is not None and "fingerprints" in old:  # older manifests lack them: not checked
        changed = [n for n, fp in manifest["fingerprints"].items()
                   if fp and old["fingerprints"].get(n) != fp]
        if changed:
            raise InputError(
                f"{out_dir} holds results made with other files for attack(s) "
                f"{', '.join(changed)} (e.g. a changed checkpoint); use a new --out or delete it")
    out_dir.mkdir(parents=True, exist_ok=True)
    store = ResultsStore(out_dir)
    manifest["targets"] = {n: t.settings() for n, t in worker.targets.items()}
    manifest["surrogate_settings"] = worker.surrogate.settings()
    manifest["attacks"] = {n: a.settings() for n, a in worker.attacks.items()}
    manifest["created"] = (old or {}).get("created", time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    write_json_atomic(out_dir / MANIFEST_FILE, manifest)

    n = len(dataset) if cfg.samples is None else min(cfg.samples, len(dataset))
    if n == 0:
        raise InputError(f"dataset {cfg.dataset!r} split {cfg.split!r} has no samples")
    starts = list(range(0, n, cfg.batch_size))
    total = len(cfg.seeds) * len(starts) * len(cfg.budgets) * len(cfg.attacks)
    bar = progress_bar(total=total, desc="icpbench run", unit="cell", disable=not progress)
    items: list[WorkItem] = []
    for seed in cfg.seeds:
        for start in starts:
            ids = _ids(dataset, start, n, cfg.batch_size)
            units = tuple((budget, aname) for budget in cfg.budgets for aname in worker.attacks
                          if not all(store.has((sid, aname, t, float(budget), int(seed)))
                                     for sid in ids for t in worker.targets))
            if units:
                items.append(WorkItem(seed=seed, start=start,
                                      stop=min(start + cfg.batch_size, n), units=units))
    bar.update(total - sum(len(it.units) for it in items))  # units already in the store
    executor = get_executor(cfg.executor, threads=cfg.threads)
    done_units = 0
    for _item, _k, rows in executor.map(worker, items):
        store.append(rows)
        bar.update(1)
        done_units += 1
        if on_unit is not None:
            on_unit(done_units)
    bar.close()
    manifest["completed_rows"] = len(store)
    manifest["execution"] = executor.describe()
    write_json_atomic(out_dir / MANIFEST_FILE, manifest)
    return store


def _cpu_count() -> int:
    import os

    return os.cpu_count() or 0


def _ids(dataset, start: int, n: int, batch_size: int) -> list[str]:
    """Sample ids of one batch (datasets may expose a cheap ``sample_id(i)``)."""
    get_id = getattr(dataset, "sample_id", None)
    idx = range(start, min(start + batch_size, n))
    if get_id is not None:
        return [get_id(i) for i in idx]
    return [dataset[i].id for i in idx]


def _attack_context(name: str, cfg: RunConfig, dataset) -> dict[str, Any]:
    """Extra constructor kwargs an attack declares it wants (``wants_context``): dataset name and
    ICP preset, e.g. so the generator picks the shipped checkpoint of the dataset."""
    cls = registry.attacks.get(name)
    if getattr(cls, "wants_context", False):
        return {"dataset": cfg.dataset, "icp_preset": cfg.icp_preset or dataset.icp_preset}
    return {}


def _run_unit(batch: Batch, attack: Attack, targets: dict[str, Target], surrogate: Target,
              prepared: dict[str, dict[str, Any]], budget: float, seed: int, cfg: RunConfig,
              none_cache: dict[str, tuple]) -> list[dict[str, Any]]:
    """Attack one batch once and register it with every target; return the rows."""
    B = len(batch)
    gen = torch.Generator().manual_seed(_stable_seed(seed, attack.name, budget, batch.samples[0].id))
    t0 = time.perf_counter()
    try:
        out: AttackOutput = attack.run(batch, budget, surrogate=surrogate, generator=gen)
        attack_err = ""
    except Exception as exc:  # a crashing plugin becomes failed rows, the run goes on
        out, attack_err = None, f"{type(exc).__name__}: {exc}"
    attack_time = (time.perf_counter() - t0) / B
    rows: list[dict[str, Any]] = []
    for tname, target in targets.items():
        base = _rows_for_unit(batch.samples, attack.name, tname, budget, seed, cfg)
        if out is None:
            for r in base:
                r.update(status="error", converged=False, error=attack_err,
                         attack_time_s=attack_time)
            rows += base
            continue
        cache_key = tname
        t1 = time.perf_counter()
        try:
            if attack.name == "none" and cache_key in none_cache:
                reg_T, conv, iters, inl, status = none_cache[cache_key]
            else:
                maps = batch.maps if target.differentiable else _prepared(target, tname, batch,
                                                                         prepared)
                with torch.no_grad():
                    reg = target.register(out.scans, maps, batch.T_init)
                reg_T, conv, iters, inl, status = (reg.T.detach().to(torch.float64),
                                                   reg.converged, reg.iterations,
                                                   reg.inlier_fraction, reg.status)
                if attack.name == "none":
                    none_cache[cache_key] = (reg_T, conv, iters, inl, status)
            icp_err = ""
        except Exception as exc:
            icp_err = f"{type(exc).__name__}: {exc}"
        icp_time = (time.perf_counter() - t1) / B
        if icp_err:
            for r in base:
                r.update(status="error", converged=False, error=icp_err,
                         attack_time_s=attack_time, icp_time_s=icp_time)
            rows += base
            continue
        err = pose_error_components(reg_T, batch.T_gt)
        for b, r in enumerate(base):
            vals = {c: float(err[c][b]) for c in POSE_ERROR_COLUMNS}
            finite = all(math.isfinite(v) for v in vals.values())
            st = status[b] if finite else "nonfinite"
            r.update(vals)
            r.update({k: float(out.stats[k][b]) for k in (*STAT_COLUMNS, "disp_max_raw")})
            r.update(status=st, converged=bool(conv[b]) and st == "ok",
                     iterations=int(iters[b]), inlier_fraction=float(inl[b]),
                     attack_time_s=attack_time, icp_time_s=icp_time, error="",
                     extra={k: float(np.asarray(v)[b]) for k, v in out.extra.items()})
        rows += base
    return rows


def _prepared(target: Target, tname: str, batch: Batch, cache: dict[str, dict[str, Any]]) -> list:
    out = []
    for s in batch.samples:
        if s.id not in cache[tname]:
            cache[tname][s.id] = target.prepare(s.map, s.map_normals)
        out.append(cache[tname][s.id])
    return out


def completed_keys(store: ResultsStore) -> set[tuple]:
    """Keys of the rows already in a store (for tests)."""
    return {row_key(r) for r in store._read_rows()}
