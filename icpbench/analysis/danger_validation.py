"""Do danger maps predict real trouble? Worst-case errors and cheap predictors against the errors
realistic corruptions cause, place by place along a route.

For every place (one test scan of a route dataset: a route vertex seen on one repeat pass) this
module puts side by side:

* the *worst-case error* at budget lambda of each attack of the settings (``worst_<attack>``:
  ``trans_err_xy`` of the attacked scan registered by ``p2plane``, non-converged runs at their final
  error, as in :mod:`icpbench.analysis.danger_map`);
* the *cheap predictors* of :mod:`icpbench.analysis.predictors` (Hessian conditioning, X-ICP-style
  localisability, the analytic sector estimate), from the clean scan and its map at the true pose;
* the *realistic error* at each severity s: the largest ``trans_err_xy`` over the corruptions of
  :mod:`icpbench.corruptions` at that severity (``realistic_s<s>``), and the label
  **"the place fails under realistic corruption at severity s"**: ``realistic_s<s> > fail_m``
  (0.5 m by default, the alert limit of :mod:`icpbench.core.sector_math`). A diverged run counts at
  its final error; a non-finite error counts as a failure; a crashed row is left out of the max.

For each quantity, oriented so that a larger value means more danger (the predictors whose small
values are dangerous are negated, :data:`icpbench.analysis.predictors.PREDICTORS`), it reports
Spearman's correlation with the realistic error and the ROC AUC for the failure label, each with a
bootstrap 95 % interval over places (:mod:`icpbench.analysis.rank_stats`), at every severity.

All error rows come from the runner (:func:`icpbench.harness.runner.run`), so the expensive part is
resumable; predictors and statistics are recomputed on every call (seconds).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from icpbench.analysis.predictors import PREDICTORS, sample_predictors
from icpbench.analysis.rank_stats import N_BOOT, auc_ci, spearman_ci
from icpbench.core.errors import InputError
from icpbench.corruptions.base import SEVERITIES
from icpbench.harness.corruption_report import corruption_mask
from icpbench.harness.progress import RunProgress

#: Default failure threshold of the realistic label (metres).
FAIL_M = 0.5
#: The severity whose label heads the summary (the middle of Robo3D's scale).
HEADLINE_SEVERITY = 3
#: The target every error row is measured on.
TARGET = "p2plane"


@dataclass
class ValidationSettings:
    """What a validation computes (recorded in its manifest).

    Attributes:
        dataset, split, samples, dataset_params: the places: the first ``samples`` scans of the
            split (a seeded shuffle of the route for ``lidar-sim``; None = all).
        attacks: attacks whose error at ``budget_m`` is a worst-case estimate (a setting, so that a
            new attack can be added and the grid resumed); at least one, each once, never
            ``none`` (the clean error, computed for every place anyway).
        budget_m: lambda of the attacks and of the sector estimate, metres.
        corruptions: corruption names (``["all"]``: every one that loads).
        severities: corruption levels 1..5.
        fail_m: failure threshold of the realistic label, metres.
        headline_severity: the severity whose label the figure marks and the summary leads with.
        n_boot: bootstrap resamples.
        seed: attack/corruption seed and bootstrap seed.
        executor: where the grid runs (``local`` or ``ray``); results do not depend on it.
        attack_params: per-attack settings, ``{name: {key: value}}``.
    """

    dataset: str = "lidar-sim"
    split: str = "test"
    samples: int | None = 96
    dataset_params: dict[str, Any] = field(default_factory=dict)
    attacks: list[str] = field(default_factory=lambda: ["generator", "sector-iter"])
    budget_m: float = 1.0
    corruptions: list[str] = field(default_factory=lambda: ["all"])
    severities: list[int] = field(default_factory=lambda: list(SEVERITIES))
    fail_m: float = FAIL_M
    headline_severity: int = HEADLINE_SEVERITY
    n_boot: int = N_BOOT
    seed: int = 0
    executor: str = "local"
    attack_params: dict[str, dict[str, Any]] = field(default_factory=dict)

    def run_config(self) -> Any:
        """The :class:`~icpbench.harness.runner.RunConfig` of the error rows (``none`` added: the
        clean error of each place, for reference)."""
        from icpbench.harness.runner import RunConfig

        if not self.attacks:
            raise InputError("no attacks given; the worst case needs at least one")
        if "none" in self.attacks:  # its rows are the clean error, not a worst case
            raise InputError("attack 'none' is the clean reference every validation computes "
                             "(clean_err), not a worst case; give attacks that search for one "
                             "(e.g. sector-iter, generator)")
        for i, a in enumerate(self.attacks):
            if a in self.attacks[:i]:
                raise InputError(f"attack {a!r} is given twice")
        if self.headline_severity not in self.severities:
            raise InputError(f"headline severity {self.headline_severity} is not among the "
                             f"severities {self.severities}")
        if not (self.fail_m > 0 and np.isfinite(self.fail_m)):
            raise InputError(f"fail_m must be a positive number of metres, got {self.fail_m}")
        attacks = ["none", *self.attacks]
        return RunConfig(dataset=self.dataset, split=self.split, samples=self.samples,
                         dataset_params=dict(self.dataset_params), attacks=attacks,
                         targets=[TARGET], budgets=[float(self.budget_m)], seeds=[self.seed],
                         corruptions=list(self.corruptions), severities=list(self.severities),
                         executor=self.executor, attack_params=dict(self.attack_params))


def quantity_columns(attacks: Sequence[str]) -> dict[str, int]:
    """Quantity column -> orientation (+1: larger = more dangerous; -1: smaller)."""
    out = {f"worst_{a}": +1 for a in attacks}
    out.update({name: sign for name, (_, sign) in PREDICTORS.items()})
    return out


def _errors(rows: pd.DataFrame) -> pd.Series:
    """``trans_err_xy`` per row, a non-finite error as +inf, a crashed row as NaN."""
    err = pd.to_numeric(rows["trans_err_xy"], errors="coerce").astype(float)
    err = err.where(np.isfinite(err) | err.isna(), np.inf)
    err[rows["status"] == "nonfinite"] = np.inf
    err[rows["status"] == "error"] = np.nan
    return err


def error_table(df: pd.DataFrame, attacks: Sequence[str], severities: Sequence[int],
                budget_m: float) -> pd.DataFrame:
    """One row per place: metadata, ``clean_err`` (attack ``none``), ``worst_<attack>`` and, per
    severity s, ``realistic_s<s>`` (largest error over corruptions) and ``worst_corruption_s<s>``.

    Raises:
        InputError: the results lack an attack or a severity of the settings.
    """
    d = df[df["target"] == TARGET].copy()
    d["err"] = _errors(d)
    is_corr = corruption_mask(d)
    meta = [c for c in ("meta.x", "meta.y", "meta.stretch", "meta.pass", "meta.frame") if c in d]
    out = d.groupby("sample_id")[meta].first().rename(columns=lambda c: c.split(".", 1)[1])
    att = d[~is_corr & np.isclose(d["budget"], budget_m)]
    for a in ["none", *attacks]:
        g = att[att["attack"] == a].set_index("sample_id")["err"]
        if g.empty:
            raise InputError(f"no rows of attack {a!r} at λ={budget_m:g} in the results")
        out["clean_err" if a == "none" else f"worst_{a}"] = g
    cor = d[is_corr]
    for s in severities:
        g = cor[np.isclose(cor["budget"], s)]
        if g.empty:
            raise InputError(f"no corruption rows at severity {s} in the results")
        wide = g.pivot_table(index="sample_id", columns="attack", values="err", aggfunc="max",
                             dropna=False)
        out[f"realistic_s{s}"] = wide.max(axis=1, skipna=True)
        filled = wide.fillna(-1.0)
        out[f"worst_corruption_s{s}"] = filled.idxmax(axis=1).where(wide.notna().any(axis=1))
    return out


def predictor_table(dataset: Any, n: int, *, preset: str, budget_m: float,
                    progress: bool = True) -> pd.DataFrame:
    """:func:`~icpbench.analysis.predictors.sample_predictors` of the first ``n`` samples, indexed by
    sample id (a sample that cannot be read or associated gets NaN)."""
    rows: dict[str, dict[str, Any]] = {}
    bar = RunProgress(total=n, desc="predictors", unit="place", enabled=progress)
    try:
        for i in range(n):
            try:
                s = dataset[i]
                rows[s.id] = sample_predictors(s, preset=preset, budget_m=budget_m)
            except InputError as exc:
                rows[dataset.sample_id(i)] = {"predictor_error": str(exc)}
            bar.update(1)
    finally:
        bar.close()
    return pd.DataFrame.from_dict(rows, orient="index")


def statistics(places: pd.DataFrame, quantities: dict[str, int], severities: Sequence[int],
               fail_m: float, n_boot: int, seed: int) -> dict[str, Any]:
    """Per severity: the failure count and, per quantity, Spearman with the realistic error and the
    AUC for the failure label (each with its bootstrap interval), on danger-oriented values."""
    out: dict[str, Any] = {}
    for s in severities:
        real = places[f"realistic_s{s}"].to_numpy(float)
        have = ~np.isnan(real)
        fails = real > fail_m
        per: dict[str, Any] = {}
        for q, sign in quantities.items():
            x = sign * places[q].to_numpy(float)
            ok = have & ~np.isnan(x)
            per[q] = {"spearman": spearman_ci(x[ok], real[ok], n_boot, seed).as_dict(),
                      "auc": auc_ci(x[ok], fails[ok], n_boot, seed).as_dict()}
        out[str(s)] = {"places": int(have.sum()), "failures": int(fails[have].sum()),
                       "quantities": per}
    return out


def _fmt(est: dict[str, Any]) -> str:
    v, (lo, hi) = est["value"], est["ci95"]
    if not np.isfinite(v):
        return "—"
    return f"{v:.2f} [{lo:.2f}, {hi:.2f}]"


def summary_markdown(summary: dict[str, Any]) -> str:
    """The correlation table: one block per severity, rows = quantities, Spearman and AUC with
    their 95 % intervals."""
    st = summary["settings"]
    lines = [f"# Danger validation: {summary['route']}", "",
             f"{summary['places']} places ({st['dataset']}, split {st['split']}, "
             f"{summary['dataset_params'] or 'default town and sensor'}); worst cases at "
             f"λ = {st['budget_m']:g} m on `{TARGET}`; realistic error = largest `trans_err_xy` "
             f"over the corruptions {', '.join(summary['corruptions'])} at one severity; a place "
             f"fails when it exceeds {st['fail_m']:g} m. Quantities oriented so that larger = more "
             "dangerous (`hessian_min_eig`, `loc_*` negated). Spearman with the realistic error "
             "and ROC AUC for the failure label; bootstrap 95 % intervals over places "
             f"({st['n_boot']} resamples).", ""]
    for s, block in summary["by_severity"].items():
        head = " (headline)" if int(s) == st["headline_severity"] else ""
        lines += [f"## Severity {s}{head}: {block['failures']} of {block['places']} places fail", "",
                  "| quantity | Spearman ρ [95 % CI] | AUC [95 % CI] |", "|---|---|---|"]
        for q, v in block["quantities"].items():
            lines.append(f"| `{q}` | {_fmt(v['spearman'])} | {_fmt(v['auc'])} |")
        lines.append("")
    return "\n".join(lines)


def validate(settings: ValidationSettings, out_dir: str | Path, *, route: str = "",
             command: str = "", progress: bool = True, redo: Sequence[str] = ()) -> dict[str, Any]:
    """Run (or resume) the error grid into ``out_dir/run`` (``redo``: attacks whose stored rows
    are computed again, :func:`icpbench.harness.runner.run`), compute the predictors and the
    statistics, and write ``places.csv``, ``summary.json``, ``summary.md``, ``route.png`` (for a
    dataset with route positions) and ``manifest.json`` to ``out_dir``. Returns the summary.

    Raises:
        InputError: bad settings, or results that lack a quantity of the settings.
    """
    from icpbench.analysis.validation_figure import plot_validation_route
    from icpbench.harness.outputs import claim, write_csv, write_file, write_json
    from icpbench.harness.results import commits_of, load_results, row_makers
    from icpbench.harness.runner import git_commit, load_dataset, package_versions
    from icpbench.harness.runner import run as run_grid

    cfg = settings.run_config().validate()
    out = claim(out_dir, "validate-map")
    t0 = time.perf_counter()
    run_grid(cfg, out / "run", progress=progress, redo=redo)
    t_grid = time.perf_counter() - t0
    df = load_results(out / "run")
    errors = error_table(df, settings.attacks, cfg.severities, settings.budget_m)
    t1 = time.perf_counter()
    dataset = load_dataset(cfg)
    n = len(dataset) if cfg.samples is None else min(cfg.samples, len(dataset))
    preds = predictor_table(dataset, n, preset=cfg.icp_preset or dataset.icp_preset,
                            budget_m=settings.budget_m, progress=progress)
    t_pred = time.perf_counter() - t1
    places = errors.join(preds, how="left")
    places.index.name = "sample_id"
    quantities = quantity_columns(settings.attacks)
    by_sev = statistics(places, quantities, cfg.severities, settings.fail_m, settings.n_boot,
                        settings.seed)
    write_csv(out / "places.csv", places)
    summary = {
        "route": route or f"{settings.dataset} {settings.split}",
        "places": int(len(places)),
        "settings": asdict(settings),
        "dataset_params": dict(settings.dataset_params),
        "corruptions": list(cfg.corruptions),
        "failure_definition": (f"a place fails at severity s when the largest trans_err_xy over "
                               f"the corruptions at s exceeds {settings.fail_m:g} m (non-converged "
                               "runs at their final error, non-finite = failure)"),
        "orientation": {q: ("larger = more dangerous" if s > 0 else "negated: smaller = more "
                            "dangerous") for q, s in quantities.items()},
        "predictors": {k: v[0] for k, v in PREDICTORS.items()},
        "by_severity": by_sev,
        "files": ["places.csv", "summary.json", "summary.md", "manifest.json", "run/"],
    }
    if {"x", "y"} <= set(places.columns):  # a route dataset: the figure
        plot_validation_route(places, quantities, settings.headline_severity, settings.fail_m,
                              out / "route.png", title=summary["route"])
        summary["files"].insert(3, "route.png")
    write_json(out / "summary.json", summary)
    write_file(out / "summary.md", summary_markdown(summary) + "\n")
    manifest = {"command": command, "settings": asdict(settings), "run_config": asdict(cfg),
                # the commit that computed the predictors and wrote this folder; those that
                # made the grid's rows (a resumed grid keeps each run's, run/manifest.json):
                "rows_made_by": commits_of(row_makers(out / "run")),
                "git": git_commit(), "versions": package_versions(),
                "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "seconds": {"grid_this_call": round(t_grid, 1), "predictors": round(t_pred, 1),
                            "total_this_call": round(time.perf_counter() - t0, 1)}}
    write_json(out / "manifest.json", manifest)
    return summary
