"""The evaluation grid: samples x attacks x targets x budgets x seeds.

Attacks that need gradients get a differentiable *surrogate* target (default ``p2plane``), while the
evaluated targets can be anything, including black boxes: this is how transfer is measured. Each
unit of work (one seed, one batch of samples, one budget, one attack) is attacked once and then
registered by every target; its rows are appended to the results store as soon as it finishes, so
an interrupted run resumes where it stopped. A plugin that raises inside a unit produces rows with
``status = "error"`` and the message, and the run goes on; so does a sample whose input file is bad
(one warning, ``error`` rows, retried on the next run; ``strict_files`` stops instead). Every sample
gets its own random stream from (seed, attack, budget, sample id), so rows do not depend on the
batch size or the executor. The results folder is locked while a run writes to it.

Where units are computed is the executor's business (:mod:`icpbench.harness.executors`: ``local`` in this
process, ``ray`` on a Ray cluster); every executor yields the rows in grid order and only this
process writes them, so the results file is the same whatever the executor.
"""

from __future__ import annotations

import copy
import json
import math
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from functools import partial
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np
import torch

from icpbench.attacks.base import STAT_COLUMNS, Attack, AttackOutput
from icpbench.core import registry
from icpbench.core.errors import CheckpointError, InputError
from icpbench.core.se3 import POSE_ERROR_COLUMNS, pose_error_components
from icpbench.core.types import Batch, Sample
from icpbench.corruptions.base import SEVERITIES
from icpbench.datasets.base import Dataset
from icpbench.harness.corruption_units import build_corruption_attacks, check_corruptions, grid_units
from icpbench.harness.executors import WorkItem, check_executor, get_executor
from icpbench.harness.options import RunOptions
from icpbench.harness.outputs import claim, write_json
from icpbench.harness.progress import RunProgress
from icpbench.harness.results import (
    BAD_INPUT,
    MANIFEST_FILE,
    NOT_RUN,
    PROVENANCE_FIELDS,
    RESULTS_FILE,
    ResultsStore,
    count_rows,
    drop_attack_rows,
    lock_results_dir,
    merge_provenance,
    read_manifest,
)
from icpbench.harness.run_monitors import (
    calibrate_run,
    calibrated_monitors,
    monitor_extra,
    thresholds_of,
    undetected_output,
)
from icpbench.harness.settings import check_list_field, config_file
from icpbench.monitors.base import Monitor
from icpbench.monitors.oracle import MonitoredOracle
from icpbench.targets.base import Target
from icpbench.targets.oracle import QueryOracle
from icpbench.targets.self_surrogate import self_surrogate

#: ``RunConfig.surrogate`` value that attacks each target through itself (or its replica).
SELF = "self"


@dataclass
class RunConfig:
    """Everything that determines a run's results (written to the manifest), and the one source of
    the defaults of ``icpbench run``.

    Attributes:
        dataset: registered dataset name.
        dataset_params: constructor settings of the dataset (besides seed/split).
        split: dataset split to evaluate ("test" by default).
        dataset_seed: seed of the dataset itself.
        attacks: registered attack names; ``["all"]`` = every attack that loads.
        targets: registered target names.
        budgets: perturbation budgets lambda (metres; normalised units for ``objects``); None =
            the dataset's ``default_budgets``.
        samples: number of samples (the first K of the split; None = all).
        seeds: attack seeds; each adds one row per (sample, attack, target, budget).
        surrogate: differentiable target that gradient-based attacks use; ``"self"``: each
            target itself, or its differentiable replica, at its own converged pose (the
            gradient attacks then run once per target, adaptively).
        icp_preset: ICP settings preset for every target (default: the dataset's).
        batch_size: samples per batch (results do not depend on it).
        strict: project every attack's per-point displacement onto its budget ball.
        threads: torch intra-op threads (1 is fastest for these tensor sizes on small CPUs).
        attack_params, target_params: per-plugin settings, ``{name: {key: value}}``.
        executor: where units of work run (``local`` or ``ray``); results do not depend on it, so
            a run may be resumed with another executor.
        strict_files: stop the run at the first sample whose input file is bad, instead of
            skipping it with a warning and ``error`` rows.
        replica_queries: a target's exact replica (``Target.exact_replica``, e.g. KISS-ICP's)
            answers the queries of the query attacks in its place; every row is still the
            target's own registration, so the rows do not depend on it.
        corruptions: realistic corruptions run beside the attacks (``["all"]`` = every one that
            loads; default none), each at every level of ``severities`` (1..5), the severity in the
            budget column (:mod:`icpbench.harness.corruption_units`).
        monitors: integrity monitors (``["all"]`` = every one that loads; default none) whose
            score and alarm every row records (:mod:`icpbench.harness.run_monitors`), each
            calibrated per target for ``false_alarm_rate`` (0..0.5) on the clean registrations of
            ``calibration_samples`` scans of the ``calibration_split``.
        calibration_split: ``"train"`` (the first scans of the dataset's train split) or
            ``"heldout"`` (the scans of the evaluated split after its first ``samples``: the same
            data, never evaluated; needs ``samples``).
        monitor_params: per-monitor settings, ``{name: {key: value}}``.
        monitor_aware: the query attacks maximise the *undetected* error (candidates a monitor
            flags count as failures), instead of ignoring the monitors.

    :meth:`validate` resolves ``all`` and the default budgets and checks every setting, so the
    manifest records exactly what ran; :meth:`from_file` reads such a record back.
    """

    dataset: str = "lidar-sim"
    attacks: list[str] = field(default_factory=lambda: ["all"])
    targets: list[str] = field(default_factory=lambda: ["p2plane"])
    budgets: list[float] | None = None
    samples: int | None = None
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
    strict_files: bool = False
    replica_queries: bool = True
    corruptions: list[str] = field(default_factory=list)
    severities: list[int] = field(default_factory=lambda: list(SEVERITIES))
    monitors: list[str] = field(default_factory=list)
    monitor_params: dict[str, dict[str, Any]] = field(default_factory=dict)
    false_alarm_rate: float = 0.01
    calibration_samples: int = 100
    calibration_split: str = "train"
    monitor_aware: bool = False

    def validate(self) -> RunConfig:
        """Check names, budgets, sizes and every plugin setting; resolve ``all`` and the default
        budgets. Raises InputError naming the setting and listing valid choices."""
        checked = RunOptions.parse({f.name: getattr(self, f.name) for f in fields(self)})
        for key in self.field_names():  # one model for every field, whoever set it
            setattr(self, key, getattr(checked, key))
        ds_cls = registry.datasets.get(self.dataset)
        everything = list(self.attacks) == ["all"]
        self.attacks = registry.attacks.resolve(self.attacks)
        if everything:  # cheapest first, the ensemble last (Attack.cost_class)
            self.attacks.sort(key=lambda n: (registry.attacks.get(n).cost_class, n))
        self.targets = registry.targets.resolve(self.targets)
        needs = [a for a in self.attacks if registry.attacks.get(a).needs_surrogate]
        if self.surrogate != SELF and needs and \
                not registry.targets.get(self.surrogate).differentiable:
            raise InputError(f"attack(s) {', '.join(needs)} need a differentiable surrogate; "
                             f"{self.surrogate!r} is a black box (use --surrogate p2plane or p2point)")
        if self.budgets is None:
            self.budgets = check_list_field("budgets", list(ds_cls.default_budgets))
        self._check_params()
        self._check_monitors()
        check_corruptions(self)
        check_executor(self.executor)
        return self

    def _check_params(self) -> None:
        """Plugin settings: only for plugins in the run, only keys they declare, typed values."""
        for what, given, allowed in (("attack", self.attack_params, self.attacks),
                                     ("target", self.target_params,
                                      [*self.targets, *([self.surrogate]
                                                        if self.surrogate != SELF else [])])):
            stray = sorted(set(given) - set(allowed))
            if stray:
                raise InputError(f"settings given for {what}(s) {', '.join(map(repr, stray))} that "
                                 f"are not in this run ({', '.join(dict.fromkeys(allowed))})")
        self.attack_params = {n: registry.attacks.check_params(n, p)
                              for n, p in self.attack_params.items()}
        self.target_params = {n: registry.targets.check_params(n, p)
                              for n, p in self.target_params.items()}
        self.dataset_params = registry.datasets.check_params(self.dataset, self.dataset_params)

    def _check_monitors(self) -> None:
        """Monitor names resolved, settings only for monitors in the run, typed and in range."""
        self.monitors = registry.monitors.resolve(self.monitors) if self.monitors else []
        stray = sorted(set(self.monitor_params) - set(self.monitors))
        if stray:
            raise InputError(f"settings given for monitor(s) {', '.join(map(repr, stray))} that "
                             f"are not in this run ({', '.join(self.monitors) or 'no monitors'})")
        self.monitor_params = {n: registry.monitors.check_params(n, p)
                               for n, p in self.monitor_params.items()}
        if self.monitor_aware and not self.monitors:
            raise InputError("--monitor-aware needs --monitors (the monitors the attacks evade)")

    @classmethod
    def field_names(cls) -> list[str]:
        """The configuration keys (what a config file may set)."""
        return [f.name for f in fields(cls)]

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], source: str = "configuration") -> RunConfig:
        """A config from a mapping of its fields (unknown keys are refused, listing the valid ones)."""
        if not isinstance(data, Mapping):
            raise InputError(f"{source} must be a mapping of settings, got {type(data).__name__}")
        unknown = sorted(set(data) - set(cls.field_names()))
        if unknown:
            raise InputError(f"{source}: unknown setting(s) {', '.join(map(repr, unknown))}; valid: "
                             f"{', '.join(cls.field_names())}")
        checked = RunOptions.parse(data, source)
        return cls(**{k: copy.deepcopy(getattr(checked, k)) for k in data})

    @classmethod
    def from_file(cls, path: str | Path) -> RunConfig:
        """Read a run configuration: a YAML file of :class:`RunConfig` fields, or the
        ``manifest.json`` of a previous run (its ``config``: re-running it repeats that run)."""
        import yaml

        p = config_file(path)
        try:
            data = yaml.safe_load(p.read_text())  # JSON is YAML
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise InputError(f"config file {p} is not valid YAML or JSON ({exc})") from exc
        if data is None:  # an empty file must not start the default run
            raise InputError(f"config file {p} is empty; give at least one setting (valid: "
                             f"{', '.join(cls.field_names())})")
        if isinstance(data, Mapping) and "config" in data and "versions" in data:  # a manifest
            data = data["config"]
        return cls.from_mapping(data, f"config file {p}")


#: RunConfig fields that choose how a run is executed, not what it computes (ignored when a resumed
#: run's configuration is compared with the stored one).
EXECUTION_FIELDS = ("executor", "strict_files", "replica_queries")


def _grows(stored: int | None, now: int | None) -> bool:
    """Whether a sample count ``now`` extends ``stored`` (None: the whole split)."""
    return now is None or (stored is not None and now >= stored)


def config_differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """The settings (``key: stored X, now Y``) in which two recorded configurations differ,
    execution fields aside; a key an older manifest lacks counts as its current default.

    A larger ``samples`` (or None, the whole split) is not a difference: a run covers the first
    K samples of the split and stores its rows by sample id, so resuming with more samples only
    adds the rows of the new ones (the old rows are what a fresh run would compute again). A
    smaller one is, since the store would hold rows outside the run; so is any other with a
    held-out calibration, whose scans are those after the first ``samples``.

    Likewise, more ``attacks`` (the stored ones kept, with their settings unchanged) are not a
    difference: rows are stored by attack, so resuming only adds the new attacks' rows.
    """
    defaults = asdict(RunConfig())
    old_attacks = old.get("attacks", defaults["attacks"]) or []
    new_attacks = new.get("attacks", defaults["attacks"]) or []
    added = set(new_attacks) - set(old_attacks) if set(old_attacks) <= set(new_attacks) else set()
    out = []
    for k in sorted(set(old) | set(new)):
        if k in EXECUTION_FIELDS:
            continue
        a, b = old.get(k, defaults.get(k)), new.get(k, defaults.get(k))
        if k == "samples" and _grows(a, b) and not (
                a != b and new.get("calibration_split") == "heldout"):
            continue  # (held-out calibration scans follow the evaluated ones: more would overlap)
        if k == "attacks" and added and set(a) <= set(b):
            continue
        if k == "attack_params" and added and isinstance(a, Mapping) and isinstance(b, Mapping) \
                and {n: p for n, p in b.items() if n not in added} == dict(a):
            continue
        if a != b:
            out.append(f"{k}: stored {a!r}, now {b!r}")
    return out


def settings_differences(stored: Mapping[str, Any] | None, now: Mapping[str, Any],
                         attacks: Mapping[str, Attack] | None = None,
                         targets: Mapping[str, Any] | None = None) -> list[str]:
    """The settings (``attack.key: stored X, now Y``) of attacks recorded in both ``stored`` and
    ``now`` (attack name -> its resolved ``settings()``, defaults included) that differ: rows of
    one attack made with two settings must not mix, even when the command line is the same and
    only a default of the code changed.

    Given the run's ``attacks`` (name -> instance) and ``targets`` (name -> instance), settings
    are compared as they act on each target (:meth:`Attack.settings_on`): a changed setting that
    computes the same rows against every target of the run is not a difference, and one that
    does not is named with the target (``attack.key on TARGET: ...``)."""
    out: list[str] = []
    for name, new in (now or {}).items():
        old = (stored or {}).get(name)
        if old is None:
            continue
        new = json.loads(json.dumps(new, sort_keys=True, default=str))  # as a manifest stores it
        pairs: list[tuple[str, Mapping[str, Any], Mapping[str, Any]]] = [("", old, new)]
        if attacks is not None and targets and name in attacks:
            act = attacks[name].settings_on
            pairs = [(f" on {tn}", act(old, t), act(new, t)) for tn, t in targets.items()]
        for where, o, n in pairs:
            for k in sorted(set(o) | set(n)):
                line = f"{name}.{k}{where}: stored {o.get(k)!r}, now {n.get(k)!r}"
                if o.get(k) != n.get(k) and line not in out:
                    out.append(line)
    return out


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


def software() -> dict[str, Any]:
    """What makes the rows a process writes: package ``versions``, the source tree's ``git`` state
    and the ``platform`` (the fields of :data:`icpbench.harness.results.PROVENANCE_FIELDS`)."""
    return {"versions": package_versions(), "git": git_commit(),
            "platform": {"machine": platform.machine(), "system": platform.system(),
                         "processor": platform.processor(), "cpu_count": _cpu_count()}}


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
    """Instantiate a registered target by its constructor contract ``cls(preset, **settings)``
    (settings checked against the target's ``param_types``)."""
    cls = registry.targets.get(name)
    return cls(preset, **registry.targets.check_params(name, params))


def build_attack(name: str, strict: bool, params: dict[str, Any] | None = None) -> Attack:
    """Instantiate a registered attack as ``cls(strict=..., **settings)`` (settings checked)."""
    cls = registry.attacks.get(name)
    return cls(strict=strict, **registry.attacks.check_params(name, params))


def load_dataset(cfg: RunConfig) -> Dataset:
    """Build the configured dataset with ``cls.create(seed=..., split=..., **settings)``."""
    cls = registry.datasets.get(cfg.dataset)
    return cls.create(seed=cfg.dataset_seed, split=cfg.split,
                      **registry.datasets.check_params(cfg.dataset, cfg.dataset_params))


def sample_id(dataset: Dataset, i: int) -> str:
    """The id of sample ``i``; a sample whose id cannot be read (its file is bad) is named by its
    index, ``"<dataset>/#<i>"``, in the driver and in every worker alike."""
    try:
        return dataset.sample_id(i)
    except InputError:
        return f"{dataset.name}/#{i}"


def _base_rows(ids: Sequence[str], metas: Sequence[Mapping[str, Any]], attack: str, target: str,
               budget: float, seed: int, cfg: RunConfig) -> list[dict[str, Any]]:
    return [{"sample_id": sid, "attack": attack, "target": target, "budget": budget,
             "seed": seed, "surrogate": cfg.surrogate, "strict": cfg.strict, "meta": dict(meta)}
            for sid, meta in zip(ids, metas, strict=True)]


class GridWorker:
    """Everything one process needs to compute units of work: the dataset, the targets, the
    surrogate, the attacks and the per-map caches, all built from a :class:`RunConfig`.

    The runner builds one in the driver (it also describes the run in the manifest); executors that
    compute elsewhere rebuild equivalent workers from :meth:`factory`.
    """

    def __init__(self, cfg: RunConfig,
                 thresholds: Mapping[str, Mapping[str, float]] | None = None) -> None:
        self.cfg = cfg
        torch.set_num_threads(cfg.threads)
        self.dataset = load_dataset(cfg)
        self.preset = cfg.icp_preset or self.dataset.icp_preset
        self.targets = {n: build_target(n, self.preset, cfg.target_params.get(n))
                        for n in cfg.targets}
        self.self_surrogates: dict[str, Target | None] | None = None
        if cfg.surrogate == SELF:
            self.surrogate: Target | None = None
            self.self_surrogates = {n: self_surrogate(t) for n, t in self.targets.items()}
            blind = [n for n, s in self.self_surrogates.items() if s is None]
            needs = [a for a in cfg.attacks if registry.attacks.get(a).needs_surrogate]
            if blind and needs:
                raise InputError(
                    f"attack(s) {', '.join(needs)} need gradients, and target(s) "
                    f"{', '.join(blind)} have neither gradients nor a differentiable replica: "
                    f"attack them with query-only attacks (e.g. sector-adaptive, search, "
                    f"ensemble) or use --surrogate p2plane")
        else:
            self.surrogate = (self.targets.get(cfg.surrogate) or
                              build_target(cfg.surrogate, self.preset,
                                           cfg.target_params.get(cfg.surrogate)))
        self.attacks = {n: build_attack(n, cfg.strict, {**_attack_context(n, cfg, self.dataset),
                                                        **cfg.attack_params.get(n, {})})
                        for n in cfg.attacks}
        self.attacks.update(build_corruption_attacks(cfg))
        self.prepared: dict[str, dict[str, Any]] = {t: {} for t in self.targets}
        #: per target, the exact replica that answers its queries (None: the target itself)
        self.answerers: dict[str, Target | None] = {
            n: t.exact_replica() if cfg.replica_queries else None for n, t in self.targets.items()}
        self.set_thresholds(thresholds)

    def set_thresholds(self, thresholds: Mapping[str, Mapping[str, float]] | None) -> None:
        """Give the run's monitors their calibrated thresholds, ``{target: {monitor: value}}``
        (None: no monitors, or not yet calibrated)."""
        self.thresholds = None if thresholds is None else {t: dict(v) for t, v in
                                                           thresholds.items()}
        self.monitors: dict[str, list[Monitor]] | None = None if thresholds is None else {
            t: calibrated_monitors(self.cfg, thresholds[t]) for t in self.targets}

    def prepared_maps(self, target: Target, batch: Batch) -> list:
        """``batch``'s maps in the form ``target.register`` takes."""
        name = next(n for n, t in self.targets.items() if t is target)
        return batch.maps if target.differentiable else _prepared(target, name, batch,
                                                                  self.prepared)

    def factory(self) -> Callable[[], GridWorker]:
        """A picklable callable that builds an equivalent worker (in another process or node)."""
        return partial(GridWorker, self.cfg, self.thresholds)

    def _load(self, item: WorkItem) -> tuple[list[Sample], dict[str, str]]:
        """The batch's samples, and ``{sample id: message}`` of those whose input is bad (skipped;
        with ``strict_files`` the error is raised instead)."""
        good, bad = [], {}
        for i in range(item.start, item.stop):
            try:
                good.append(self.dataset[i].validate())
            except InputError as exc:
                if self.cfg.strict_files:
                    raise
                bad[sample_id(self.dataset, i)] = str(exc)
        return good, bad

    def run(self, item: WorkItem) -> Iterator[list[dict[str, Any]]]:
        """Attack and register one batch for each of ``item.units``; yield each unit's rows."""
        good, bad = self._load(item)
        batch = Batch.from_samples(good) if good else None
        invariant_cache: dict[tuple[str, str], tuple] = {}
        for budget, aname in item.units:
            rows = [] if batch is None else _run_unit(
                batch, self.attacks[aname], self.targets, self.surrogate, self.prepared, budget,
                item.seed, self.cfg, invariant_cache, self.self_surrogates, self.monitors,
                self.answerers)
            for tname in self.targets:
                for r in _base_rows(list(bad), [{}] * len(bad), aname, tname, budget, item.seed,
                                    self.cfg):
                    r.update(status="error", converged=False, error=BAD_INPUT + bad[r["sample_id"]])
                    rows.append(r)
            yield rows



def run_manifest_head(cfg: RunConfig, worker: GridWorker) -> dict[str, Any]:
    """What a run's manifest records of ``cfg`` before any row: the configuration, the ICP
    preset, the dataset, the software and the attacks' file fingerprints."""
    return {
        "config": asdict(cfg),
        "icp_preset": worker.preset,
        "dataset": worker.dataset.describe(),
        **software(),
        "threads": {"torch": cfg.threads},
        "fingerprints": {n: a.fingerprint(cfg.budgets) for n, a in worker.attacks.items()},
    }


def check_resume(out_dir: Path, old: Mapping[str, Any], manifest: Mapping[str, Any],
                 worker: GridWorker, redo: Sequence[str] = ()) -> None:
    """Refuse to add rows to the run of ``out_dir`` (its stored manifest ``old``) under the
    manifest ``manifest`` (:func:`run_manifest_head`) of ``worker``'s configuration unless the
    stored rows are rows this configuration would compute again: the same configuration (more
    samples or attacks aside, :func:`config_differences`), the same files of each attack, and
    the same settings of each attack as they act on each target (:func:`settings_differences`);
    the attacks in ``redo`` are computed again, so only their files and settings may differ.

    Raises:
        InputError: what differs, and what to do about it.
    """
    diff = config_differences(old.get("config", {}), manifest["config"])
    if diff:
        raise InputError(
            f"{out_dir} holds results of a different configuration ({'; '.join(diff)}); "
            "use a new --out (or the same command to resume)")
    # a manifest older than the fingerprints cannot show which files made its rows: an attack
    # that has files (a generator checkpoint) is then refused too, or the rewritten manifest
    # would label the old rows with the new checkpoint and commit
    old_fp = old.get("fingerprints")
    changed = [n for n, fp in manifest["fingerprints"].items()
               if fp and n not in redo and (old_fp is None or old_fp.get(n) != fp)]
    if changed:
        raise InputError(
            f"{out_dir} holds results made with other files for attack(s) "
            f"{', '.join(changed)} (e.g. a changed checkpoint); use a new --out or delete it")
    kept = {n: v for n, v in (old.get("attacks") or {}).items() if n not in redo}
    diff = settings_differences(kept, {n: a.settings() for n, a in worker.attacks.items()},
                                worker.attacks, worker.targets)
    if diff:
        raise InputError(
            f"{out_dir} holds results of attacks with other settings ({'; '.join(diff)}), "
            "e.g. made before a default changed; use a new --out, or --redo ATTACK to "
            "compute that attack's rows again")


def run(cfg: RunConfig, out_dir: str | Path, *, progress: bool = True,
        on_unit: Callable[[int], None] | None = None, redo: Sequence[str] = ()) -> ResultsStore:
    """Run (or resume) the grid of ``cfg`` into ``out_dir``; return the results store.

    While it runs, ``out_dir`` is locked: a second run with the same ``out_dir`` is refused.
    A sample whose input file is bad is skipped with one warning (logger ``icpbench``) and
    ``error`` rows, unless ``cfg.strict_files``.

    ``redo`` names attacks of ``cfg`` whose stored rows are removed first and computed again with
    their current settings and files (e.g. after a default changed); every other attack must
    still match what the folder holds. The manifest's ``provenance`` entry of this run lists them
    under ``redone``.

    Raises:
        InputError: invalid configuration; ``out_dir`` holds a run with another configuration,
            results without a manifest, or is in use by another run; ``redo`` names an attack the
            run does not have.
    """
    cfg.validate()
    unknown = [a for a in redo if a not in cfg.attacks]
    if unknown:
        raise InputError(f"--redo {', '.join(unknown)}: not among the run's attacks "
                         f"({', '.join(cfg.attacks)})")
    redo = list(dict.fromkeys(redo))
    torch.set_num_threads(cfg.threads)
    out_dir = Path(out_dir)
    if str(out_dir) == "":
        raise InputError("the results folder is empty ('')")
    _check_out_dir(out_dir)
    claim(out_dir, "run")
    worker = GridWorker(cfg)
    manifest = run_manifest_head(cfg, worker)
    with lock_results_dir(out_dir):
        _check_out_dir(out_dir)  # again, now that no other run can be writing
        old = read_manifest(out_dir)
        if old is not None:
            check_resume(out_dir, old, manifest, worker, redo)
            if redo:
                old = {**old, "provenance": drop_attack_rows(
                    out_dir, redo, old.get("provenance") or [
                        {"rows_from": 0, "started": old.get("created"),
                         **{k: old.get(k) for k in PROVENANCE_FIELDS}}])}
        store = ResultsStore(out_dir)
        rows_before = count_rows(out_dir)
        manifest.update(merge_provenance(old, manifest, rows_before))
        if redo:
            manifest["provenance"][-1]["redone"] = redo
        manifest["finished"] = False
        manifest["targets"] = {n: t.settings() for n, t in worker.targets.items()}
        manifest["surrogate_settings"] = (
            worker.surrogate.settings() if worker.self_surrogates is None else
            {n: (None if s is None else s.settings()) for n, s in worker.self_surrogates.items()})
        manifest["attacks"] = {n: a.settings() for n, a in worker.attacks.items()}
        if cfg.monitors:
            _calibrate_monitors(cfg, worker, manifest, old, progress)
        manifest["created"] = (old or {}).get("created", time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        write_json(out_dir / MANIFEST_FILE, manifest)
        def untouched() -> bool:
            """A resume that appended nothing: the folder's manifest stays as it was (its
            execution settings and provenance describe the runs that made the rows)."""
            return old is not None and not redo and count_rows(out_dir) == rows_before

        try:
            _run_items(cfg, worker, store, manifest, progress=progress, on_unit=on_unit)
        except BaseException:
            if old is None and len(store) == 0:  # refused before any row: leave no manifest
                (out_dir / MANIFEST_FILE).unlink(missing_ok=True)
                raise
            manifest["completed_rows"] = len(store)
            write_json(out_dir / MANIFEST_FILE, old if untouched() else manifest)
            raise
        if untouched() and old.get("finished", True):
            write_json(out_dir / MANIFEST_FILE, old)
            return store
        manifest["completed_rows"] = len(store)
        manifest["finished"] = True
        write_json(out_dir / MANIFEST_FILE, manifest)
    return store


def _calibrate_monitors(cfg: RunConfig, worker: GridWorker, manifest: dict[str, Any],
                        old: Mapping[str, Any] | None, progress: bool) -> None:
    """Calibrate the run's monitors per target (or take the calibration a resumed run stored:
    same configuration, same clean scans, same thresholds), record it in ``manifest`` and give
    the thresholds to ``worker``."""
    cal = (old or {}).get("monitors")
    if not cal or set(cal) != set(worker.targets):
        say = (lambda line: print(f"icpbench run: {line}", file=sys.stderr)) if progress else None
        cal = {t: {m: c.as_dict() for m, c in per.items()}
               for t, per in calibrate_run(cfg, worker.targets, worker.prepared_maps, say).items()}
    manifest["monitors"] = cal
    worker.set_thresholds(thresholds_of(cal))


def _check_out_dir(out_dir: Path) -> None:
    """Refuse a results folder that holds rows but no manifest (nothing says what made them)."""
    if (out_dir / RESULTS_FILE).is_file() and (out_dir / RESULTS_FILE).stat().st_size > 0 and \
            not (out_dir / MANIFEST_FILE).is_file():
        raise InputError(f"{out_dir} holds a {RESULTS_FILE} but no {MANIFEST_FILE}, so what made "
                         "those rows is unknown and they cannot be resumed; use a new --out")


def _run_items(cfg: RunConfig, worker: GridWorker, store: ResultsStore, manifest: dict[str, Any],
               *, progress: bool, on_unit: Callable[[int], None] | None) -> None:
    """Compute the units the store lacks, append their rows, warn once per skipped sample."""
    dataset = worker.dataset
    n = len(dataset) if cfg.samples is None else min(cfg.samples, len(dataset))
    if n == 0:
        raise InputError(f"dataset {cfg.dataset!r} split {cfg.split!r} has no samples")
    starts = list(range(0, n, cfg.batch_size))
    grid = grid_units(cfg, list(worker.attacks))
    total = len(cfg.seeds) * len(starts) * len(grid)
    items: list[WorkItem] = []
    for seed in cfg.seeds:
        for start in starts:
            ids = [sample_id(dataset, i) for i in range(start, min(start + cfg.batch_size, n))]
            units = tuple((budget, aname) for budget, aname in grid
                          if not all(store.has((sid, aname, t, float(budget), int(seed)))
                                     for sid in ids for t in worker.targets))
            if units:
                items.append(WorkItem(seed=seed, start=start,
                                      stop=min(start + cfg.batch_size, n), units=units))
    todo = sum(len(it.units) for it in items)
    workers = max(1, _cpu_count()) if cfg.executor != "local" else 1
    # time left once about one item per worker is done: units differ in cost, items do not
    per_item = max((len(it.units) for it in items), default=1)
    bar = RunProgress(total=total, done=total - todo, desc="icpbench run", unit="unit",
                      enabled=progress, warmup=per_item * min(workers, max(len(items), 1)))
    executor = get_executor(cfg.executor, threads=cfg.threads)
    skipped: dict[str, str] = {}
    done_units = 0
    try:
        for _item, _k, rows in executor.map(worker, items):
            store.append(rows)
            for r in rows:
                err = str(r.get("error") or "")
                if err.startswith(BAD_INPUT) and r["sample_id"] not in skipped:
                    skipped[r["sample_id"]] = err[len(BAD_INPUT):]
                    bar.write(f"warning: skipped sample {r['sample_id']}: {skipped[r['sample_id']]}")
            bar.update(1)
            done_units += 1
            if on_unit is not None:
                on_unit(done_units)
    finally:
        bar.close()
    manifest["completed_rows"] = len(store)
    manifest["skipped_samples"] = skipped
    manifest["execution"] = executor.describe()
    if skipped and len(skipped) == n:
        first = next(iter(skipped.items()))
        raise InputError(f"no sample of dataset {cfg.dataset!r} could be read ({len(skipped)} "
                         f"skipped); the first, {first[0]}: {first[1]}")


def _cpu_count() -> int:
    import os

    return os.cpu_count() or 0


def _attack_context(name: str, cfg: RunConfig, dataset: Dataset) -> dict[str, Any]:
    """Extra constructor kwargs an attack declares it wants (``Attack.wants_context``): dataset
    name and ICP preset, e.g. so the generator picks the shipped checkpoint of the dataset."""
    if registry.attacks.get(name).wants_context:
        return {"dataset": cfg.dataset, "icp_preset": cfg.icp_preset or dataset.icp_preset}
    return {}


def _run_unit(batch: Batch, attack: Attack, targets: dict[str, Target], surrogate: Target | None,
              prepared: dict[str, dict[str, Any]], budget: float, seed: int, cfg: RunConfig,
              invariant_cache: dict[tuple[str, str], tuple],
              self_surrogates: Mapping[str, Target | None] | None = None,
              monitors: Mapping[str, list[Monitor]] | None = None,
              answerers: Mapping[str, Target | None] | None = None) -> list[dict[str, Any]]:
    """Attack one batch and register it with every target; return the rows.

    A non-adaptive attack runs once and every target registers its output (transfer). An adaptive
    one (:meth:`Attack.adaptive`: it queries the evaluated target, or follows gradients while the
    run's surrogate is ``self``) runs once per target, against that target: with a
    :class:`~icpbench.targets.oracle.QueryOracle` of it and, under ``--surrogate self``, with the
    target itself or its replica as surrogate (``self_surrogates``).

    Each sample's random stream comes from (seed, attack, budget, sample id), so the rows do not
    depend on the batch. An attack that is ``budget_invariant`` is registered once per batch.
    With ``monitors`` (``{target: calibrated monitors}``) every row records their alarms, and with
    ``cfg.monitor_aware`` a query attack sees a :class:`MonitoredOracle` of its target. Without
    monitors the oracle's queries go to the target's exact replica where ``answerers`` names one
    (a monitor reads the target's own registration)."""
    if attack.adaptive(self_surrogates is not None):
        groups = [[t] for t in targets]
    else:
        groups = [list(targets)]
    rows: list[dict[str, Any]] = []
    for names in groups:
        sur = surrogate if self_surrogates is None else (
            self_surrogates[names[0]] if len(names) == 1 else None)
        oracle = None
        if attack.needs_oracle:
            target = targets[names[0]]
            maps = batch.maps if target.differentiable else _prepared(target, names[0], batch,
                                                                      prepared)
            oracle = (MonitoredOracle(target, batch, maps, monitors[names[0]])
                      if cfg.monitor_aware and monitors else
                      QueryOracle(target, batch, maps, (answerers or {}).get(names[0])))
        t0 = time.perf_counter()
        try:
            out: AttackOutput | None = attack.run(batch, budget, surrogate=sur,
                                                  generator=int(seed), oracle=oracle)
            if isinstance(oracle, MonitoredOracle):  # report the best undetected scan
                out = undetected_output(oracle, out, batch, budget)
            attack_err = ""
        except Exception as exc:  # a crashing plugin becomes failed rows, the run goes on
            out, attack_err = None, f"{type(exc).__name__}: {exc}"
            if isinstance(exc, CheckpointError):  # the user can fix it: retried by the next run
                attack_err = NOT_RUN + attack_err
        attack_time = (time.perf_counter() - t0) / len(batch)
        for tname in names:
            rows += _target_rows(batch, attack, tname, targets[tname], out, attack_err,
                                 attack_time, prepared, budget, seed, cfg, invariant_cache,
                                 None if monitors is None else monitors[tname])
    return rows


def _target_rows(batch: Batch, attack: Attack, tname: str, target: Target,
                 out: AttackOutput | None, attack_err: str, attack_time: float,
                 prepared: dict[str, dict[str, Any]], budget: float, seed: int, cfg: RunConfig,
                 invariant_cache: dict[tuple[str, str], tuple],
                 monitors: list[Monitor] | None = None) -> list[dict[str, Any]]:
    """Register an attack's output (or record its failure) with one target; the rows (with the
    monitors' scores and alarms in ``extra``, where there are monitors)."""
    B = len(batch)
    ids = [s.id for s in batch.samples]
    metas = [s.meta for s in batch.samples]
    base = _base_rows(ids, metas, attack.name, tname, budget, seed, cfg)
    if out is None:
        for r in base:
            r.update(status="error", converged=False, error=attack_err, attack_time_s=attack_time)
        return base
    cache_key = (attack.name, tname)
    t1 = time.perf_counter()
    try:
        if attack.budget_invariant and cache_key in invariant_cache:
            reg_T, conv, iters, inl, status, alarms = invariant_cache[cache_key]
        else:
            maps = batch.maps if target.differentiable else _prepared(target, tname, batch,
                                                                     prepared)
            with torch.no_grad():
                reg = target.register(out.scans, maps, batch.T_init)
            reg_T, conv, iters, inl, status = (reg.T.detach().to(torch.float64),
                                               reg.converged, reg.iterations,
                                               reg.inlier_fraction, reg.status)
            alarms = ([{}] * B if not monitors else
                      monitor_extra(monitors, batch, out.scans, reg))
            if attack.budget_invariant:
                invariant_cache[cache_key] = (reg_T, conv, iters, inl, status, alarms)
        icp_err = ""
    except Exception as exc:
        icp_err = f"{type(exc).__name__}: {exc}"
    icp_time = (time.perf_counter() - t1) / B
    if icp_err:
        for r in base:
            r.update(status="error", converged=False, error=icp_err,
                     attack_time_s=attack_time, icp_time_s=icp_time)
        return base
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
                 extra={**{k: float(np.asarray(v)[b]) for k, v in out.extra.items()},
                        **alarms[b]})
    return base


def _prepared(target: Target, tname: str, batch: Batch, cache: dict[str, dict[str, Any]]) -> list:
    out = []
    for s in batch.samples:
        if s.id not in cache[tname]:
            cache[tname][s.id] = target.prepare(s.map, s.map_normals)
        out.append(cache[tname][s.id])
    return out
