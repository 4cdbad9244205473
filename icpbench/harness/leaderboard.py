"""The leaderboard: ICP variants ranked by the worst case the ``ensemble`` finds against each.

RobustBench (Croce et al., NeurIPS 2021 datasets and benchmarks track) ranks image classifiers by the
accuracy left under AutoAttack, a fixed ensemble of adaptive attacks; this is the ICP version. Each
variant (a target plugin with its settings) is attacked *adaptively*: ``ensemble`` with
``--surrogate self`` (every gradient member through the target itself or its differentiable replica,
every query member against the target's own output), at each budget lambda. A variant's row reports

* its clean error (attack ``none``),
* the ensemble's mean and median worst-case ``trans_err_xy`` (metres),
* the amplification: worst-case error / lambda (a rigid translation of the scan by lambda gives
  about 1), and the share of scans whose amplification stays <= :data:`SAFE_AMPLIFICATION`,
* the ensemble over ``uniform`` (how much worse than translating the whole scan),
* attack time per scan and queries per scan, and which member won how often.

RobustBench keeps the lowest robust figure *anyone* found; so does this board: further attacks
(``extra_attacks``, e.g. ``spoof``, or a user's own attack plugin) run on the same scans, and a
scan's worst case is the largest error over the ensemble and them (a scan an attack moved beyond
lambda does not count for it, :func:`summarise`). The ensemble alone is reported beside it, and the
winner counts name the extra attacks too. Adding an attack to a finished board only computes that
attack's rows.

Only what was measured is ranked: a scan whose rows are errors (a plugin raised) is left out of
a variant's numbers and counted, a variant that measured no finite worst case is not ranked, and
an extra attack that did not run on a variant is said not to have run, with the reason each time
(:func:`summarise`); the board lists them beside the ranking.

Rows are ranked by the mean amplification at the middle budget, most robust first. Every variant
is an ordinary results folder (``<out>/runs/<variant>/``), so the board resumes where it stopped and
each number can be traced to its rows. A user's own ICP joins as a target plugin
(``extra_targets``): README, "Put your ICP on the leaderboard".
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from icpbench.attacks.ensemble import MEMBERS, column, seconds_column
from icpbench.attacks.sector_adaptive import score
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.harness.board_figures import board_figure, domain_figure, ranking_rows
from icpbench.harness.board_stats import (
    bootstrap_ranks,
    kendall_agreement,
    kendall_interval,
    paired_ratios,
)
from icpbench.harness.carry_over import carry_over
from icpbench.harness.outputs import claim, write_csv, write_file, write_json
from icpbench.harness.protocol import (
    STANDARD_DOMAINS,
    Protocol,
    custom_protocol,
    protocol_differences,
    standard_protocol,
)
from icpbench.harness.results import (
    NOT_RUN,
    RESULTS_FILE,
    commits_of,
    load_results,
    read_manifest,
    row_makers,
)
from icpbench.harness.runner import SELF, RunConfig, build_target, git_commit, package_versions
from icpbench.harness.runner import run as run_grid
from icpbench.targets.self_surrogate import self_surrogate

#: The row column of a run with monitors that says whether any fired.
_ALARM = "extra.monitor_alarm.any"

#: The figure of this board against the one it is compared with (``--compare-with``).
COMPARISON_FIGURE = "comparison.png"

#: A scan counts as "held" when its worst-case error stays within this multiple of lambda.
SAFE_AMPLIFICATION = 1.5


@dataclass(frozen=True)
class Variant:
    """One row of the board: a target plugin with settings.

    Attributes:
        label: the row's name (also its results folder, made file-name safe).
        target: the target's registry name.
        params: its settings (``--target-param`` keys).
    """

    label: str
    target: str
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def slug(self) -> str:
        """A file-name-safe folder name for the label."""
        return re.sub(r"[^A-Za-z0-9._-]+", "-", self.label).strip("-.") or "variant"


#: The standard board (the ICP variants the harness ships or wraps).
STANDARD_VARIANTS: tuple[Variant, ...] = (
    Variant("p2plane (Cauchy)", "p2plane"),
    Variant("p2plane (no kernel)", "p2plane", {"cauchy_c": None}),
    Variant("p2plane (Huber)", "p2plane", {"kernel": "huber"}),
    Variant("p2plane (d_max 2 m)", "p2plane", {"d_max": 2.0}),
    Variant("p2plane (d_max 1 m)", "p2plane", {"d_max": 1.0}),
    Variant("p2point", "p2point"),
    Variant("open3d p2plane", "open3d"),
    Variant("open3d p2point", "open3d", {"mode": "point", "cauchy_c": None}),
    Variant("kiss-icp", "kiss-icp"),
    Variant("small-gicp GICP", "small-gicp"),
    Variant("small-gicp plane ICP", "small-gicp", {"registration_type": "PLANE_ICP"}),
)


def split_variant_labels(text: str, known: Sequence[str] | None = None) -> list[str]:
    """The variant labels of a comma-separated list (``--variants``).

    A label may itself contain commas only if it is a known one (``known``, default the labels
    of :data:`STANDARD_VARIANTS`): the longest run of comma-separated pieces that spells a known
    label is taken as one label, and any other piece is a label of its own, so that
    ``"p2point,bogus"`` gives ``["p2point", "bogus"]`` and :meth:`LeaderboardConfig.resolve`
    names ``bogus`` alone. Empty pieces are dropped."""
    labels = set(known if known is not None else (v.label for v in STANDARD_VARIANTS))
    pieces = text.split(",")
    out: list[str] = []
    i = 0
    while i < len(pieces):
        j = next((j for j in range(len(pieces), i, -1)
                  if ",".join(pieces[i:j]).strip() in labels), i + 1)
        label = ",".join(pieces[i:j]).strip()
        if label:
            out.append(label)
        i = j
    return out


#: Attacks the standard board runs beside the ensemble: none, since every attack that found a
#: board's worst case is an ensemble member (``extra_attacks`` is for a user's own attack).
STANDARD_EXTRA_ATTACKS: tuple[str, ...] = ()


@dataclass
class LeaderboardConfig:
    """What a board is computed from (recorded in its manifest).

    The protocol fields (dataset, dataset_params, split, samples, budgets, seed, ensemble) default
    to the standard protocol's ``town`` domain (:mod:`icpbench.harness.protocol`);
    :meth:`for_domain` gives another domain's, and :meth:`protocol` says which protocol a
    configuration is under.

    Attributes:
        dataset, dataset_params, split: the data (default: the simulated lidar test route).
        samples: scans per variant (the first K of the split).
        budgets: lambda values (metres).
        variants: labels of :data:`STANDARD_VARIANTS` to include (None: all).
        extra_targets: registry names of further target plugins, each a row with its defaults.
        ensemble: settings of the ``ensemble`` attack (``pgd_steps``, ``queries``, ...).
        extra_attacks: registry names of further attacks run on every variant with their
            defaults; a scan's worst case is the largest over the ensemble and them (default
            :data:`STANDARD_EXTRA_ATTACKS`).
        seed: attack seed.
        batch_size: scans per batch.
        executor: ``local`` or ``ray`` (see ``icpbench run --executor``).
    """

    dataset: str = STANDARD_DOMAINS["town"].dataset
    dataset_params: dict[str, Any] = field(
        default_factory=lambda: dict(STANDARD_DOMAINS["town"].dataset_params))
    split: str = STANDARD_DOMAINS["town"].split
    samples: int | None = STANDARD_DOMAINS["town"].samples
    budgets: list[float] = field(default_factory=lambda: list(STANDARD_DOMAINS["town"].budgets))
    variants: list[str] | None = None
    extra_targets: list[str] = field(default_factory=list)
    ensemble: dict[str, Any] = field(default_factory=dict)
    extra_attacks: list[str] = field(default_factory=lambda: list(STANDARD_EXTRA_ATTACKS))
    seed: int = 0
    batch_size: int = 4
    executor: str = "local"
    monitors: list[str] = field(default_factory=list)
    monitor_aware: bool = False

    @classmethod
    def for_domain(cls, domain: str, **fields: Any) -> LeaderboardConfig:
        """The standard protocol of ``domain`` (``town``, ``unseen``), with further ``fields``
        (variants, executor, ...; a protocol field given here makes the protocol custom).

        Raises:
            InputError: an unknown domain.
        """
        p = standard_protocol(domain)
        base = dict(dataset=p.dataset, dataset_params=dict(p.dataset_params), split=p.split,
                    samples=p.samples, budgets=list(p.budgets), seed=p.seed,
                    ensemble=dict(p.ensemble))
        return cls(**{**base, **fields})

    def protocol(self) -> Protocol:
        """The standard protocol of a domain if every protocol field is that domain's, else a
        custom protocol of these fields."""
        mine = custom_protocol(self.dataset, self.dataset_params, self.split,
                               -1 if self.samples is None else self.samples,
                               tuple(sorted(self.budgets)), self.seed, self.ensemble)
        for p in STANDARD_DOMAINS.values():
            fields = ("dataset", "dataset_params", "split", "samples", "budgets", "seed",
                      "ensemble")
            if all(getattr(p, f) == getattr(mine, f) for f in fields):
                return p
        return mine

    def resolve(self) -> list[Variant]:
        """The variants of this board, checked.

        Raises:
            InputError: an unknown variant label or target name, or no variant at all.
        """
        by_label = {v.label: v for v in STANDARD_VARIANTS}
        if self.variants is None:
            chosen = list(STANDARD_VARIANTS)
        else:
            unknown = [v for v in self.variants if v not in by_label]
            if unknown:
                raise InputError(f"unknown leaderboard variant(s) {', '.join(map(repr, unknown))}; "
                                 f"valid: {', '.join(by_label)}")
            chosen = [by_label[v] for v in self.variants]
        for t in self.extra_targets:
            registry.targets.get(t)  # raises, listing the valid names
            chosen.append(Variant(t, t))
        if not chosen:
            raise InputError("the leaderboard has no variant to rank")
        for a in self.extra_attacks:
            registry.attacks.get(a)  # raises, listing the valid names
            if a in ("none", "ensemble"):
                raise InputError(f"{a!r} is always on the board; name other attacks to add")
        if len(set(self.extra_attacks)) != len(self.extra_attacks):
            raise InputError(f"an extra attack is named twice: {self.extra_attacks}")
        slugs = [v.slug for v in chosen]
        if len(set(slugs)) != len(slugs):
            raise InputError(f"two variants share a folder name: {slugs}")
        return chosen

    def missing_standard(self) -> list[str]:
        """Labels of :data:`STANDARD_VARIANTS` this board leaves out (``variants`` names a subset),
        in their standard order; empty for a board of every standard variant."""
        if self.variants is None:
            return []
        return [v.label for v in STANDARD_VARIANTS if v.label not in self.variants]

    def run_config(self, v: Variant) -> RunConfig:
        """The ``icpbench run`` configuration of one variant."""
        return RunConfig(dataset=self.dataset, dataset_params=dict(self.dataset_params),
                         split=self.split, attacks=["none", "ensemble", *self.extra_attacks],
                         targets=[v.target],
                         budgets=list(self.budgets), samples=self.samples, seeds=[self.seed],
                         surrogate=SELF, batch_size=self.batch_size, executor=self.executor,
                         attack_params={"ensemble": dict(self.ensemble)} if self.ensemble else {},
                         target_params={v.target: dict(v.params)} if v.params else {},
                         monitors=list(self.monitors), monitor_aware=self.monitor_aware)


def run_leaderboard(cfg: LeaderboardConfig, out_dir: str | Path, *, progress: bool = True,
                    on_variant: Callable[[Variant, str], None] | None = None,
                    compare_with: str | Path | None = None,
                    carry_over_from: str | Path | None = None) -> pd.DataFrame:
    """Compute (or resume) every variant's run under ``out_dir/runs`` and write the board.

    A variant whose settings its target refuses (e.g. a kernel it does not have), or whose target
    cannot take a gradient extra attack (:func:`gradient_blind_reason`), is skipped; a variant
    that measured nothing is not ranked (:func:`summarise`). Both are named with the reason in
    the board, its manifest and ``board.attrs["not_ranked"]`` (label -> reason; the skipped ones
    also in ``board.attrs["skipped"]``). ``on_variant(variant, status)`` is called as each one
    starts (``"running (k of n)"``), ends (its wall time) or is skipped (the reason); the run's
    own progress bar shows the time left within a variant.

    ``carry_over_from`` (a board of an earlier version of the same protocol) first copies each of
    its runs whose rows this protocol would compute again (:func:`~icpbench.harness.carry_over.
    carry_over`); the board's manifest records them (``carried_over``) and its Markdown names them.

    Returns:
        The board (one row per ranked variant and budget), also written as ``leaderboard.csv``.

    Raises:
        InputError: no variant could be ranked (each one's reason is in the message).
    """
    out = Path(out_dir)
    variants = cfg.resolve()
    check_board_folder(out, cfg)
    claim(out, BOARD_KIND)
    if read_manifest(out) is None:  # claim the folder for this protocol before any row exists
        write_json(out / "manifest.json", {
            "kind": BOARD_KIND, "protocol": cfg.protocol().as_dict(), "config": asdict(cfg),
            "finished": False, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    carried = dict((read_manifest(out) or {}).get("carried_over") or {})
    if carry_over_from is not None:
        by_label = {v.label: v for v in variants}
        source = Path(carry_over_from)
        news = carry_over({v.label: (cfg.run_config(v), v.slug) for v in variants},
                          cfg.protocol().as_dict(), out, source)
        source_protocol = (read_manifest(source) or {}).get("protocol")
        for label, what in news.items():
            if what.startswith("carried over"):
                carried[label] = {"from": str(source / "runs" / by_label[label].slug),
                                  "protocol": source_protocol}
            if on_variant:
                on_variant(by_label[label], what)
        write_json(out / "manifest.json", {**(read_manifest(out) or {}), "carried_over": carried})
    runs: dict[str, Path] = {}
    skipped: dict[str, str] = {}
    for k, v in enumerate(variants, 1):
        if not still_carried(carried.get(v.label), out / "runs" / v.slug):
            carried.pop(v.label, None)  # computed here (now or by an earlier command)
        rc = cfg.run_config(v)
        try:
            rc.validate()
            why = gradient_blind_reason(rc)
        except InputError as exc:
            why = f"its target refused the settings: {exc}"
        if why is not None:
            skipped[v.label] = why
            if on_variant:
                on_variant(v, f"skipped: {why}")
            continue
        if on_variant:
            on_variant(v, f"running ({k} of {len(variants)})")
        t0 = time.perf_counter()
        run_grid(rc, out / "runs" / v.slug, progress=progress)
        runs[v.label] = out / "runs" / v.slug
        if on_variant:
            on_variant(v, f"done in {time.perf_counter() - t0:.0f} s")
    try:
        board = summarise(runs, cfg.budgets, cfg.extra_attacks) if runs else None
    except InputError as exc:
        if not skipped:
            raise
        raise InputError(f"{exc}; skipped: " + "; ".join(
            f"{k}: {v}" for k, v in skipped.items())) from None
    if board is None:
        raise InputError("no variant could be ranked: " + "; ".join(
            f"{k}: {v}" for k, v in skipped.items()))
    board.attrs["skipped"] = dict(skipped)
    board.attrs["not_ranked"] = {**skipped, **board.attrs.get("not_ranked", {})}
    board.attrs["runs"] = {k: str(v) for k, v in runs.items()}
    board.attrs["carried_over"] = {k: v for k, v in carried.items() if k in runs}
    board.attrs["carried_record"] = carried  # also of variants this command did not rank
    write_board(board, out, cfg, board.attrs["not_ranked"], compare_with=compare_with)
    return board


def still_carried(entry: Mapping[str, Any] | None, run_dir: Path) -> bool:
    """Whether the run in ``run_dir`` is still the one a board carried over (``entry``: its
    ``carried_over`` record, ``from`` the source run's folder): it exists and its ``provenance``
    (the commits and start times of the commands that made its rows) is the source run's. A run
    deleted and computed again, by this command or an earlier one, is not. A source that is no
    longer there cannot be compared; the record is kept."""
    if entry is None or not run_dir.exists():
        return False
    source = read_manifest(Path(entry.get("from", "")))
    if source is None:
        return True
    return (read_manifest(run_dir) or {}).get("provenance") == source.get("provenance")


def gradient_blind_reason(rc: RunConfig) -> str | None:
    """Why a variant's run cannot attack its target: an extra attack that needs gradients
    (``needs_surrogate``) on a target with neither gradients nor a differentiable replica (on a
    board every attack runs through the target itself, ``--surrogate self``); None if it can.

    The ensemble is not such an attack: it skips its gradient member on these targets."""
    needs = [a for a in rc.attacks if registry.attacks.get(a).needs_surrogate]
    if not needs:
        return None
    preset = rc.icp_preset or registry.datasets.get(rc.dataset).icp_preset
    blind = [t for t in rc.targets
             if self_surrogate(build_target(t, preset, rc.target_params.get(t))) is None]
    if not blind:
        return None
    return (f"extra attack(s) {', '.join(needs)} need gradients, and target {', '.join(blind)} "
            "has neither gradients nor a differentiable replica; rank it without them (leave "
            "them out of --extra-attacks: the ensemble skips its own gradient member on such a "
            "target), or rank a target that has a replica")


#: The ``kind`` a board's ``manifest.json`` records (a run folder's manifest has none).
BOARD_KIND = "leaderboard"


def check_board_folder(out: Path, cfg: LeaderboardConfig) -> None:
    """Refuse an ``out`` that is not a board folder, or a board of another protocol.

    A board writes only into a new folder or into a board of the same protocol (resuming it, or
    adding variants or extra attacks to it).

    Raises:
        InputError: ``out`` is a file, a results folder of ``icpbench run`` or another folder
            with a manifest, or a board made under a protocol that differs (the message names
            each differing field).
    """
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file; a board needs a folder")
    if not out.is_dir():
        return
    old = read_manifest(out)
    is_board = old is not None and (old.get("kind") == BOARD_KIND or "variants" in old)
    if not is_board and ((out / RESULTS_FILE).exists()
                         or "targets" in ((old or {}).get("config") or {})):
        raise InputError(f"--out {out} holds the results of an `icpbench run` (its "
                         "manifest.json); a board writes only into a new folder or a board of "
                         "its own")
    if old is None:
        return
    if not is_board:
        raise InputError(f"--out {out} holds the manifest of something else than a board "
                         f"({out / 'manifest.json'}); a board writes only into a new folder or a "
                         "board of its own")
    diff = protocol_differences(old.get("protocol"), cfg.protocol().as_dict())
    if diff:
        raise InputError(f"--out {out} is a board of another protocol ({'; '.join(diff)}); "
                         "use a new --out, or the same settings to resume it")


def _first_error(rows: pd.DataFrame) -> str:
    """The first non-empty ``error`` message of ``rows`` (without the retry prefix), or ``""``."""
    errs = rows.get("error", pd.Series(dtype=object)).dropna().astype(str)
    errs = errs[errs.str.strip() != ""]
    return errs.iloc[0].removeprefix(NOT_RUN) if len(errs) else ""


def _failed(rows: pd.DataFrame) -> np.ndarray:
    """Rows that measured nothing: a plugin raised (``status`` error)."""
    return (rows.status == "error").to_numpy()


def unmeasured_reason(df: pd.DataFrame, lam: float) -> str:
    """Why a variant's results measured no finite worst case at budget ``lam`` (every
    registration failed, the ensemble failed on every scan, or every pose was non-finite),
    naming the first error message; the budget is named when other budgets measured some."""
    e = df[(df.attack == "ensemble") & np.isclose(df.budget, lam)]
    clean = df[df.attack == "none"]
    failed = _failed(e)
    if len(e) and failed.all():
        if len(clean) and _failed(clean).all():
            why = f"every registration failed: {_first_error(clean) or _first_error(e)}"
        else:
            why = f"the ensemble failed on every scan: {_first_error(e)}"
    elif len(e) and not failed.any():
        why = f"every registration gave a non-finite pose ({len(e)} scan(s))"
    else:
        why = (f"no registration gave a finite pose: {int(failed.sum())} scan(s) failed (first: "
               f"{_first_error(e[failed])}), {int((~failed).sum())} non-finite")
    ens = df[df.attack == "ensemble"]
    others = ens[~np.isclose(ens.budget, lam)]
    if len(others) and np.isfinite(others.trans_err_xy.to_numpy(dtype=float)).any():
        why = f"nothing measured at λ={lam:g} m, the ranking budget: {why}"
    return why


def attack_not_run_reason(rows: pd.DataFrame) -> str | None:
    """Why an extra attack's rows of one variant measured nothing (absent, or every row an error;
    the first error message), or None when some row was measured."""
    if rows.empty:
        return "no rows (it was not run)"
    if _failed(rows).all():
        why = _first_error(rows) or "every row is an error"
        errs = rows.error.fillna("").astype(str)
        return why + ("; the same command tries it again" if errs.str.startswith(NOT_RUN).all()
                      else "")
    return None


def summarise(runs: dict[str, Path], budgets: Sequence[float],
              extra_attacks: Sequence[str] = ()) -> pd.DataFrame:
    """The board (one row per ranked variant and budget) from the variants' results folders.

    A scan's worst case is the ensemble's error, or an extra attack's where it is larger (a
    diverged estimate never wins; an extra attack's scan with points moved beyond lambda,
    ``frac_over_budget`` > 0, is not counted and is reported as ``over_budget_<attack>``). With
    extra attacks the ensemble's own mean is kept as ``ensemble_mean``.

    Only what was measured is ranked. A scan whose rows are errors (a plugin raised) measured
    nothing: it is left out of the means and shares and counted in ``failed``; a scan whose
    worst-case pose is non-finite counts as ``diverged`` (not held). A variant with no finite
    worst case at the ranking (middle) budget is not ranked at all: it has no row, and
    ``board.attrs["not_ranked"]`` maps its label to the reason (e.g. ``every registration failed:
    <first error>``). An extra attack none of whose rows of a variant was measured is not
    counted as losing every scan: ``board.attrs["extra_not_run"]`` maps ``attack -> {label:
    reason}`` and its ``ran_extra_<attack>`` is false.

    Raises:
        InputError: no variant could be ranked (the message gives each one's reason).
    """
    rows = []
    per_scan: dict[float, dict[str, pd.Series]] = {}  # budget -> variant -> worst case per scan
    mid = sorted(budgets)[len(budgets) // 2]
    not_ranked: dict[str, str] = {}
    extra_not_run: dict[str, dict[str, str]] = {}
    for label, path in runs.items():
        df = load_results(path)
        e_mid = df[(df.attack == "ensemble") & np.isclose(df.budget, mid)]
        if not e_mid.empty and not _worst_errors(df, e_mid, mid, extra_attacks)[0].any():
            not_ranked[label] = unmeasured_reason(df, mid)
            continue
        for a in extra_attacks:
            why = attack_not_run_reason(df[df.attack == a])
            if why is not None:
                extra_not_run.setdefault(a, {})[label] = why
        clean = df[df.attack == "none"]
        clean_err = clean.drop_duplicates("sample_id").trans_err_xy
        for lam in budgets:
            e = df[(df.attack == "ensemble") & np.isclose(df.budget, lam)]
            if e.empty:
                continue
            ok, err, ens_err, from_ensemble, won_extra, over, xs = _worst_errors(
                df, e, lam, extra_attacks)
            failed = _failed(e) & ~ok  # nothing measured (an extra attack may have measured it)
            counted = ~failed
            per_scan.setdefault(float(lam), {})[label] = pd.Series(
                np.where(ok, err, np.nan), index=e.sample_id.to_numpy())
            amp = err / lam
            uni = e.get(f"extra.{column('uniform')}", pd.Series(np.nan, index=e.index))
            win = e.get("extra.winner", pd.Series(np.nan, index=e.index))[from_ensemble]
            win = win.dropna().astype(int)
            row = {
                "variant": label, "budget": float(lam), "scans": int(len(e)),
                "failed": int(failed.sum()),
                "clean_mean": float(clean_err.mean()), "clean_median": float(clean_err.median()),
                "worst_mean": float(np.mean(err[ok])) if ok.any() else math.nan,
                "worst_median": float(np.median(err[ok])) if ok.any() else math.nan,
                "amplification": float(np.mean(amp[ok])) if ok.any() else math.nan,
                "held_share": float(np.mean((ok & (amp <= SAFE_AMPLIFICATION))[counted]))
                if counted.any() else math.nan,
                "diverged": int((~ok & counted).sum()),
                "uniform_mean": float(np.nanmean(uni)) if uni.notna().any() else math.nan,
                "attack_s": float(e.attack_time_s.mean()),
                "queries": float(e.get("extra.queries", pd.Series(np.nan)).mean()),
                "weak_gradient": float(e.get("extra.weak_gradient", pd.Series(0.0)).mean()),
            }
            if _ALARM in e:  # monitors: what of the worst case reaches the planner unannounced
                alarms = [e[_ALARM].to_numpy(dtype=float)] + [
                    x.set_index("sample_id").reindex(e.sample_id.to_numpy())[_ALARM]
                    .to_numpy(dtype=float) for x in xs.values() if _ALARM in x]
                errs = [ens_err] + [x.set_index("sample_id").reindex(e.sample_id.to_numpy())
                                    .trans_err_xy.to_numpy(dtype=float)
                                    for x in xs.values() if _ALARM in x]
                und = np.nanmax(np.column_stack([np.where((a > 0) | ~np.isfinite(x), 0.0, x)
                                                 for a, x in zip(alarms, errs, strict=True)]),
                                axis=1)
                row["detected_share"] = float(np.mean(alarms[0][counted] > 0)) \
                    if counted.any() else math.nan
                row["undetected_mean"] = float(np.mean(und[counted])) if counted.any() \
                    else math.nan
            row["over_uniform"] = row["worst_mean"] / row["uniform_mean"] \
                if row["uniform_mean"] and math.isfinite(row["uniform_mean"]) else math.nan
            if extra_attacks:
                fin = np.isfinite(ens_err)
                row["ensemble_mean"] = float(np.mean(ens_err[fin])) if fin.any() else math.nan
                for x in xs.values():
                    row["attack_s"] += float(x.attack_time_s.mean()) if len(x) else 0.0
                    q = x.get("extra.queries")  # an attack that queries nothing adds none
                    row["queries"] += 0.0 if q is None else float(q.fillna(0.0).mean())
            for i, m in enumerate(MEMBERS):
                row[f"won_{m}"] = int((win == i).sum())
                ran = e.get(f"extra.{column(m)}")
                row[f"ran_{m}"] = ran is not None and bool(ran.notna().any())
                sec = e.get(f"extra.{seconds_column(m)}")
                row[f"sec_{m}"] = float(sec.mean()) if sec is not None and sec.notna().any() \
                    else math.nan
            for a in extra_attacks:  # an attack that did not run won nothing, lost nothing
                ran = label not in extra_not_run.get(a, {})
                row[f"won_extra_{a}"] = int(won_extra[a].sum()) if ran else math.nan
                row[f"over_budget_{a}"] = over[a] if ran else math.nan
            rows.append(row)
    board = pd.DataFrame(rows)
    if board.empty:
        if not_ranked:
            raise InputError("no variant could be ranked: " + "; ".join(
                f"{k}: {v}" for k, v in not_ranked.items()))
        raise InputError("no variant produced ensemble rows: nothing to rank")
    board = board.join(_intervals(per_scan), on=["budget", "variant"])
    rank = board[np.isclose(board.budget, mid)].set_index("variant").amplification
    board["rank_key"] = board.variant.map(rank).fillna(np.inf)
    board = board.sort_values(["rank_key", "variant", "budget"]).drop(columns="rank_key") \
        .reset_index(drop=True)
    board.attrs["not_ranked"] = not_ranked
    board.attrs["extra_not_run"] = extra_not_run
    board.attrs["per_scan"] = {lam: pd.DataFrame(series) for lam, series in per_scan.items()}
    return board


def _worst_errors(df: pd.DataFrame, e: pd.DataFrame, lam: float, extra_attacks: Sequence[str]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                             dict[str, np.ndarray], dict[str, int], dict[str, pd.DataFrame]]:
    """Each scan's worst case at budget ``lam``: the ensemble's rows ``e``, raised by the extra
    attacks' where larger (within lambda, finite).

    Returns:
        ``(ok, err, ens_err, from_ensemble, won_extra, over, xs)``: finite worst case per scan,
        the worst-case errors, the ensemble's own, the scans the ensemble won, the scans each
        extra attack won, the scans each moved beyond lambda, and each extra attack's rows.
    """
    err = e.trans_err_xy.to_numpy(dtype=float)
    xs = {a: df[(df.attack == a) & np.isclose(df.budget, lam)] for a in extra_attacks}
    won_extra: dict[str, np.ndarray] = {}
    over: dict[str, int] = {}
    ens_err = err.copy()
    from_ensemble = np.ones(len(e), dtype=bool)
    for a, x in xs.items():
        x = x.set_index("sample_id").reindex(e.sample_id.to_numpy())
        bad = x.frac_over_budget.to_numpy(dtype=float) > 0
        xe = np.where(bad, np.nan, x.trans_err_xy.to_numpy(dtype=float))
        better = score(xe) > score(err)
        err = np.where(better, xe, err)
        from_ensemble &= ~better
        for b in won_extra:  # a scan has one winner: the last attack that raised it
            won_extra[b] &= ~better
        won_extra[a] = better
        over[a] = int(bad.sum())
    return np.isfinite(err), err, ens_err, from_ensemble, won_extra, over, xs


def _intervals(per_scan: dict[float, dict[str, pd.Series]]) -> pd.DataFrame:
    """Bootstrap 95 % intervals over the scans (:func:`~icpbench.analysis.board_stats.
    bootstrap_ranks`, one paired resample for all variants) of each variant's mean worst case
    (``worst_lo``, ``worst_hi``) and rank (``rank``, ``rank_lo``, ``rank_hi``; 1 = most robust),
    indexed by (budget, variant)."""
    parts = []
    for lam, series in per_scan.items():
        errors = pd.DataFrame(series)  # scans x variants, aligned by sample id
        ci = bootstrap_ranks(errors).rename(columns={"mean_lo": "worst_lo", "mean_hi": "worst_hi"})
        parts.append(ci.drop(columns="mean").assign(budget=lam).rename_axis("variant"))
    return pd.concat(parts).reset_index().set_index(["budget", "variant"])


def _wins_and_seconds(rows: pd.DataFrame, member: str) -> str:
    """A member's cell of the cost table: its wins over a variant's ``rows`` (one per budget) and,
    where the runs recorded it, its mean seconds per scan, e.g. ``16 (28.6 s)``."""
    wins = str(int(rows[f"won_{member}"].sum()))
    sec = rows.get(f"sec_{member}")
    if sec is None or not sec.notna().any():  # a board written before the times were kept
        return wins
    return f"{wins} ({float(sec.mean()):.1f} s)"


def _rank_range(lo: float, hi: float) -> str:
    """A rank interval as text: ``3`` or ``2-5`` (bounds rounded to whole ranks)."""
    a, b = int(math.floor(lo)), int(math.ceil(hi))
    return str(a) if a == b else f"{a}-{b}"


def _fmt(x: float, nd: int = 2) -> str:
    return "-" if x is None or not math.isfinite(float(x)) else f"{float(x):.{nd}f}"


def ran_members(board: pd.DataFrame) -> list[str]:
    """The ensemble members the board's rows ran (on some scan of some row)."""
    return [m for m in MEMBERS if f"ran_{m}" not in board or board[f"ran_{m}"].any()]


def board_markdown(board: pd.DataFrame, cfg: LeaderboardConfig, skipped: dict[str, str]) -> str:
    """The board as Markdown: the ranking, then time/queries and the members' wins, then what was
    not measured: extra attacks that did not run (``board.attrs["extra_not_run"]``), scans that
    failed or diverged, and the variants not ranked (``skipped``: label -> reason)."""
    budgets = sorted(board.budget.unique())
    order = list(dict.fromkeys(board.variant))
    members = ran_members(board)
    extras = list(cfg.extra_attacks)
    also = (f" and, per scan, the larger error of the extra attack(s) "
            f"{', '.join(f'`{a}`' for a in extras)} (*ensemble [m]*: the ensemble alone)"
            if extras else "")
    lines = [
        "# ICP leaderboard: worst case under the attack ensemble",
        "",
        f"Data: `{cfg.dataset}` {cfg.split} split, {int(board.scans.max())} scans per variant; "
        f"attack: `ensemble` (members {', '.join(members)}) with `--surrogate self`{also}; "
        f"errors are `trans_err_xy` in metres. Amplification = worst-case error / λ (a rigid "
        f"translation of the scan by λ gives about 1); *held* = share of scans with amplification "
        f"<= {SAFE_AMPLIFICATION:g}. Ranked by mean amplification at λ = "
        f"{budgets[len(budgets) // 2]:g} m, most robust first.",
        "",
    ]
    missing = cfg.missing_standard()
    if missing:
        lines += [f"**Not every standard variant:** this board ranks {len(order)} variant(s) "
                  f"(`--variants`); {len(missing)} of the {len(STANDARD_VARIANTS)} standard "
                  f"ones are not on it: {', '.join(f'`{m}`' for m in missing)}. Ranks, their "
                  "intervals and any agreement below hold among the variants on this board only.",
                  ""]
    mid = budgets[len(budgets) // 2]
    monitored = "undetected_mean" in board
    head = ["#", f"rank 95% CI (λ={mid:g})", "variant", "clean mean [m]"]
    for lam in budgets:
        head += [f"λ={lam:g}: mean [m]", "95% CI [m]", "median [m]", "ampl.", "held",
                 "× uniform"]
        head += ["ensemble [m]"] if extras else []
        head += ["detected", "undetected [m]"] if monitored else []
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k, v in enumerate(order, 1):
        r = board[board.variant == v].set_index("budget")
        rk = r.loc[mid] if mid in r.index else None
        cells = [str(k), "-" if rk is None else _rank_range(rk.rank_lo, rk.rank_hi), v,
                 _fmt(r.clean_mean.iloc[0], 3)]
        for lam in budgets:
            if lam not in r.index:
                cells += ["-"] * (6 + bool(extras) + 2 * monitored)
                continue
            x = r.loc[lam]
            cells += [_fmt(x.worst_mean), f"{_fmt(x.worst_lo)}-{_fmt(x.worst_hi)}",
                      _fmt(x.worst_median), _fmt(x.amplification),
                      f"{100 * x.held_share:.0f}%", _fmt(x.over_uniform, 1)]
            cells += [_fmt(x.ensemble_mean)] if extras else []
            cells += [f"{100 * x.detected_share:.0f}%", _fmt(x.undetected_mean)] \
                if monitored else []
        lines.append("| " + " | ".join(cells) + " |")
    if monitored:
        lines += ["", f"Monitors: {', '.join(f'`{m}`' for m in cfg.monitors)}, calibrated per "
                  "variant on clean train-split scans (each variant's manifest.json, `monitors`); "
                  "the attacks " + ("maximise the undetected error (`--monitor-aware`)"
                                    if cfg.monitor_aware else "ignore them") +
                  ". *detected*: share of scans whose ensemble result raised an alarm; "
                  "*undetected*: mean over scans of the largest error that raised none (0 where "
                  "every attack's result was flagged)."]
    lines += ["", "Intervals: bootstrap over the scans (1000 resamples, the same for every "
              "variant), 2.5-97.5 %; rank 1 is the most robust. Variants whose rank intervals "
              "overlap are not told apart by these scans."]
    lines += ["", "Attack cost per scan (seconds, queries) and the member that found each scan's "
              "worst case (counts over all budgets), with, in brackets, the member's own mean "
              "seconds per scan (its queries, plans and gradients; over all budgets):", ""]
    head = ["variant", *[f"λ={lam:g}: s / queries" for lam in budgets], *members,
            *[f"+ {a}" for a in extras]]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for v in order:
        r = board[board.variant == v].set_index("budget")
        cells = [v] + [f"{_fmt(r.loc[lam].attack_s, 1)} / {_fmt(r.loc[lam].queries, 0)}"
                       if lam in r.index else "-" for lam in budgets]
        cells += [_wins_and_seconds(r, m) for m in members]
        cells += ["did not run" if r[f"won_extra_{a}"].isna().all() else
                  str(int(r[f"won_extra_{a}"].sum())) for a in extras]
        lines.append("| " + " | ".join(cells) + " |")
    weak = board[board.weak_gradient > 0]
    if not weak.empty:
        lines += ["", "Weak gradient (the query search still raised the gradient member's error by "
                  "more than 10%) on a share of scans: " + ", ".join(
                      f"{r.variant} λ={r.budget:g}: {100 * r.weak_gradient:.0f}%"
                      for r in weak.itertuples()) + "."]
    over = {a: int(board[f"over_budget_{a}"].sum()) for a in extras}
    if any(over.values()):
        lines += ["", "Not counted (points moved beyond λ): " + ", ".join(
            f"`{a}` on {n} scan(s)" for a, n in over.items() if n) + "."]
    for a, where in board.attrs.get("extra_not_run", {}).items():
        lines += ["", f"`{a}` did not run (its wins are not counted) on " + "; ".join(
            f"{v}: {why}" for v, why in where.items())]
    lost = board[(board.failed > 0) | (board.diverged > 0)]
    if not lost.empty:
        lines += ["", "Scans not measured (a plugin raised: *failed*, left out of every number) "
                  "and diverged (non-finite pose: counted as not held): " + ", ".join(
                      f"{r.variant} λ={r.budget:g}: {r.failed} failed, {r.diverged} diverged of "
                      f"{r.scans}" for r in lost.itertuples()) + "."]
    if skipped:
        lines += ["", "Not ranked: " + "; ".join(f"{k}: {v}" for k, v in skipped.items())]
    return "\n".join(lines) + "\n"


def _ranking_agreement(board: pd.DataFrame, theirs: pd.DataFrame) -> tuple[float, float, int]:
    """Kendall's tau (with its p-value and the variants compared) of two boards' rankings: the
    mean amplification at each board's ranking budget."""
    return kendall_agreement(ranking_rows(board).amplification.to_dict(),
                             ranking_rows(theirs).amplification.to_dict())


def agreement_line(board: pd.DataFrame, other: Path, other_scans: pd.DataFrame | None,
                   why: str = "") -> str:
    """One line: Kendall's tau between this board's ranking and the board in folder ``other``
    (mean amplification at each board's middle budget, over the variants both rank), with its
    bootstrap interval from ``other_scans`` (:func:`board_scans` of ``other``; None: no interval,
    ``why`` says why).

    Raises:
        InputError: ``other`` holds no board (``leaderboard.csv``).
    """
    path = other / "leaderboard.csv"
    if not path.is_file():
        raise InputError(f"--compare-with {other}: no board there ({path} does not exist)")
    theirs = pd.read_csv(path)
    manifest = read_manifest(other) or {}
    domain = (manifest.get("protocol") or {}).get("domain", "unknown")

    tau, p, n = _ranking_agreement(board, theirs)
    mine = _ranking_scans(board)
    if mine is not None and other_scans is not None:
        lo, hi = kendall_interval(mine, other_scans)
        spread = (f" (95% bootstrap interval {_fmt(lo)} to {_fmt(hi)}, each board's scans "
                  "resampled)")
    else:
        spread = f" (no interval: {why or 'this board has no per-scan errors'})"
    return (f"Agreement with the ranking of `{other}` (domain `{domain}`): Kendall's tau = "
            f"{_fmt(tau)}{spread} over {n} variants (two-sided p = {_fmt(p, 3)}; 1 is the same "
            "order).")


def comparison_markdown(ratios: pd.DataFrame, other: Path) -> str:
    """The Markdown table of :func:`~icpbench.harness.board_stats.paired_ratios` of this board
    against the board in ``other`` (``""`` when it is empty)."""
    if ratios.empty:
        return ""
    lines = [f"Against `{other}` on the scans both boards hold: the mean worst case of each, "
             "their ratio with a 95% bootstrap interval (the scans resampled together for both "
             "boards), and the share of scans where this board's worst case is larger / smaller "
             "by more than 1 mm:", "",
             f"| variant | scans | this board [m] | `{other.name}` [m] | ratio (95% CI) | larger "
             "| smaller |", "|---|---|---|---|---|---|---|"]
    for v, x in ratios.iterrows():
        lines.append(f"| {v} | {int(x.scans)} | {_fmt(x.mean_a)} | {_fmt(x.mean_b)} | "
                     f"{_fmt(x.ratio, 3)} ({_fmt(x.ratio_lo)}-{_fmt(x.ratio_hi)}) | "
                     f"{x.larger:.0%} | {x.smaller:.0%} |")
    return "\n".join(lines) + "\n"


def _ranking_scans(board: pd.DataFrame) -> pd.DataFrame | None:
    """Scans x variants worst-case errors (metres) of ``board`` at its ranking (middle) budget, as
    :func:`summarise` kept them; None if it kept none."""
    per_scan = board.attrs.get("per_scan") or {}
    budgets = sorted(per_scan)
    return per_scan[budgets[len(budgets) // 2]] if budgets else None


def board_scans(folder: Path) -> pd.DataFrame:
    """Scans x variants worst-case errors (metres) at the ranking budget of the board written in
    ``folder``, recomputed from its runs (``runs/<variant>``) as its manifest names them.

    Raises:
        InputError: no board manifest with its variants, or a variant's run folder is missing.
    """
    manifest = read_manifest(folder) or {}
    variants, cfg = manifest.get("variants"), manifest.get("config") or {}
    if not variants:
        raise InputError(f"{folder}: no board manifest naming its variants")
    skipped = set(manifest.get("skipped") or {})  # never run: no folder to look for
    runs = {}
    for v in variants:
        if v["label"] in skipped:
            continue
        path = folder / "runs" / Variant(v["label"], v["target"], v.get("params") or {}).slug
        if not (path / "results.csv").is_file():
            raise InputError(f"{folder}: the run of {v['label']!r} is missing ({path})")
        runs[v["label"]] = path
    scans = _ranking_scans(summarise(runs, cfg.get("budgets") or [1.0],
                                     cfg.get("extra_attacks") or []))
    if scans is None:
        raise InputError(f"{folder}: its runs hold no ensemble rows")
    return scans


def _comparison_figure(board: pd.DataFrame, other: Path, cfg: LeaderboardConfig, path: Path) -> None:
    """:func:`~icpbench.harness.board_figures.domain_figure` of this board against the board in
    ``other`` (already checked to exist by :func:`agreement_line`), named by their domains."""
    theirs = pd.read_csv(other / "leaderboard.csv")
    domain = ((read_manifest(other) or {}).get("protocol") or {}).get("domain")
    tau, _, n = _ranking_agreement(board, theirs)
    domain_figure(board, theirs, path, label=f"this board ({cfg.protocol().domain})",
                  other_label=f"`{other}`" + (f" ({domain})" if domain else ""),
                  title=f"The same variants on two boards: Kendall's tau = {_fmt(tau)} over {n}")


def carried_markdown(carried: Mapping[str, Mapping[str, Any]], cfg: LeaderboardConfig) -> str:
    """The board's line on the runs it carried over from a board of an earlier protocol version
    (:func:`~icpbench.harness.carry_over.carry_over`)."""
    p = cfg.protocol()
    parts = []
    for label, c in carried.items():
        v = (c.get("protocol") or {}).get("version", "?")
        parts.append(f"{label} (v{v}, `{c.get('from')}`)")
    return (f"Carried over to {p.name} v{p.version}, because this protocol computes the same rows "
            f"for them (the run's configuration, files and settings as they act on its target): "
            f"{'; '.join(parts)}. Every other variant was computed under v{p.version}.")


def write_board(board: pd.DataFrame, out: Path, cfg: LeaderboardConfig,
                skipped: dict[str, str], compare_with: str | Path | None = None) -> None:
    """Write ``leaderboard.md``, ``.csv``, ``.png`` and ``manifest.json`` (``skipped``: the
    variants not ranked and why; ``extra_not_run``) into ``out``; with
    ``compare_with`` (another board's folder), the Markdown states the agreement of the two
    rankings (:func:`agreement_line`), ``comparison.png`` draws the variants of both against
    each other (:func:`~icpbench.harness.board_figures.domain_figure`) and, where the boards hold
    the same scans, compares them
    variant by variant (:func:`~icpbench.harness.board_stats.paired_ratios`, also written to
    ``comparison.csv``)."""
    unused = [f"won_{m}" for m in MEMBERS if m not in ran_members(board)]
    write_csv(out / "leaderboard.csv", board.drop(
        columns=unused + [c for c in board if c.startswith("ran_")]), index=False,
        float_format="%.6g")
    md = board_markdown(board, cfg, skipped)
    carried = board.attrs.get("carried_over") or {}
    if carried:
        md += "\n" + carried_markdown(carried, cfg) + "\n"
    (out / COMPARISON_FIGURE).unlink(missing_ok=True)  # a stale figure of an earlier comparison
    if compare_with is not None:
        other = Path(compare_with)
        try:  # its per-scan errors, read once for tau's interval and the paired ratios
            theirs, why = board_scans(other), ""
        except InputError as exc:
            theirs, why = None, str(exc)
        md += "\n" + agreement_line(board, other, theirs, why) + "\n"
        _comparison_figure(board, other, cfg, out / COMPARISON_FIGURE)
        mine = _ranking_scans(board)
        ratios = paired_ratios(mine, theirs) if mine is not None and theirs is not None else None
        if ratios is not None and not ratios.empty:  # the same scans: variant by variant
            md += "\n" + comparison_markdown(ratios, other)
            write_csv(out / "comparison.csv", ratios.rename_axis("variant"), float_format="%.6g")
    write_file(out / "leaderboard.md", md)
    board_figure(board, out / "leaderboard.png", SAFE_AMPLIFICATION)
    write_json(out / "manifest.json", {
        "kind": BOARD_KIND, "protocol": cfg.protocol().as_dict(),
        "config": asdict(cfg), "variants": [asdict(v) for v in cfg.resolve()],
        "skipped": skipped, "extra_not_run": board.attrs.get("extra_not_run", {}),
        "carried_over": board.attrs.get("carried_record", carried),
        "standard_variants_missing": cfg.missing_standard(),
        # the commit that wrote this board; those that made each variant's rows:
        "rows_made_by": {label: commits_of(row_makers(path))
                         for label, path in (board.attrs.get("runs") or {}).items()},
        "versions": package_versions(), "git": git_commit(), "finished": True,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
