"""Command-line interface (typer). The only place that prints and exits.

User errors (bad names, budgets, files, checkpoints) exit with status 2 and one readable line.
Ctrl-C (SIGINT) and SIGTERM stop every command with one line that says what is saved, and exit
status 130 or 143 (128 + the signal), never a traceback (:func:`_on_stop`).
"""

from __future__ import annotations

import os
import re
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

if TYPE_CHECKING:
    import pandas as pd

#: The signal that is stopping this command (SIGINT or SIGTERM), None while none came.
_stop: int | None = None
#: Whether :func:`main` runs a command: a stop signal then raises KeyboardInterrupt, which the
#: command turns into one line; before, nothing has started and the process just ends.
_running = False
#: Whether the line about a stop signal has been written (a later signal is then ignored).
_reported = False


def _on_stop(signum: int, frame: object) -> None:
    """SIGINT / SIGTERM handler of the ``icpbench`` process.

    While the CLI is still being imported nothing can have been saved, so one line is written and
    the process ends at once with 128 + signum. Once :func:`main` runs, KeyboardInterrupt is raised
    (also for SIGTERM, which Python would otherwise end silently, leaving worker processes behind):
    the command stops its workers, keeps what it saved and says so (:func:`_interrupted`)."""
    global _stop
    if _reported:  # the command is already saying so and exiting
        return
    _stop = signum
    if not _running:
        os.write(2, f"\n{_stop_word()} while starting; nothing was saved\n".encode())
        os._exit(128 + signum)
    raise KeyboardInterrupt


def _install_stop_handlers() -> None:
    """Handle SIGINT and SIGTERM with :func:`_on_stop` (a signal this process was started to
    ignore, e.g. by ``nohup``, stays ignored)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _on_stop)


def _stop_word() -> str:
    return "terminated (SIGTERM)" if _stop == signal.SIGTERM else "interrupted"


# As early as this module can: the process is the CLI itself (`python -m icpbench.cli`, or the
# `icpbench` script), not a program or a worker process that imports it.
if __name__ == "__main__" or (Path(sys.argv[0]).name == "icpbench" and getattr(
        sys.modules.get("__main__"), "__name__", "") == "__main__"):
    _install_stop_handlers()

import typer  # noqa: E402

from icpbench import __version__  # noqa: E402
from icpbench.core.errors import IcpbenchError  # noqa: E402
from icpbench.harness import options as opts  # noqa: E402

RC, LB, MAP, VM, TR, OS = (opts.RunCommandOptions, opts.LeaderboardOptions, opts.MapOptions,
                           opts.ValidateMapOptions, opts.TrainOptions, opts.ObjectStudyOptions)


def _opt(model: type[opts.Options], name: str, *decls: str, **kw: object) -> typer.models.OptionInfo:
    """A typer option whose help is the model field's description (stated once, in the model)."""
    return typer.Option(*decls, help=model.help(name), **kw)

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None,
                  help="Worst-case error of lidar ICP localisation under corrupted scans.")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"icpbench {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="Show the version and exit.")] = False,
) -> None:
    """icpbench: attacks x ICP targets x budgets -> Table 1, transfer tables and danger maps."""


def _fail(exc: Exception) -> None:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(2)


#: A plugin constructor called with parameters it does not take (``--dataset-param bogus=1``, a
#: dataset that needs ``root=``): the user's mistake, reported like the other user errors.
_SIGNATURE = re.compile(r"^(?P<owner>[\w.]+)\.__init__\(\) (?P<what>(got an unexpected keyword "
                        r"argument|missing \d+ required (keyword-only |positional )?arguments?).*)$")


def _user_error(exc: Exception) -> None:
    """Exit 2 with one line for a user error (bad names, values, files, parameters); re-raise
    anything else (a bug keeps its traceback)."""
    if isinstance(exc, IcpbenchError | ValueError):
        _fail(exc)
    if isinstance(exc, typer.BadParameter):
        _fail(Exception(exc.format_message()))
    if isinstance(exc, OSError):  # --out is a file, permission denied, disk full, ...
        where = f": {exc.filename}" if exc.filename else ""
        _fail(Exception(f"{exc.strerror or exc}{where}"))
    m = _SIGNATURE.match(str(exc)) if isinstance(exc, TypeError) else None
    if m is not None:
        _fail(Exception(f"bad parameters for {m['owner']}: {m['what']} (set plugin parameters with "
                        "--dataset-param KEY=VALUE, --attack-param NAME.KEY=VALUE or "
                        "--target-param NAME.KEY=VALUE)"))
    raise exc


def _kv(item: str, flag: str) -> tuple[str, object]:
    """``KEY=VALUE`` with the value read as YAML (numbers, true/false, lists); a value with a
    leading zero (a KITTI sequence ``00``) stays text; an empty value is refused."""
    import yaml

    if "=" not in item:
        raise typer.BadParameter(f"{flag} expects KEY=VALUE, got {item!r}")
    k, v = item.split("=", 1)
    if not k.strip():
        raise typer.BadParameter(f"{flag} expects KEY=VALUE, got {item!r} (no key)")
    if not v.strip():
        raise typer.BadParameter(f"{flag} {item!r} has no value; give KEY=VALUE (use KEY=null for "
                                 "none)")
    if re.fullmatch(r"0\d+", v.strip()):
        return k.strip(), v.strip()
    try:
        return k.strip(), yaml.safe_load(v)
    except yaml.YAMLError:
        return k.strip(), v


def _flat(items: list[str] | None, flag: str) -> dict:
    return dict(_kv(i, flag) for i in items or [])


def _nested(items: list[str] | None, flag: str) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for i in items or []:
        k, v = _kv(i, flag)
        if "." not in k:
            raise typer.BadParameter(f"{flag} expects NAME.KEY=VALUE, got {i!r}")
        name, key = k.split(".", 1)
        out.setdefault(name, {})[key] = v
    return out


def _saved_rows(folders: Sequence[Path]) -> int:
    """Result rows saved in the results folders ``folders`` (0 where a folder has none)."""
    files = [f / "results.csv" for f in folders if (f / "results.csv").is_file()]
    if not files:
        return 0
    from icpbench.harness.results import count_rows

    return sum(count_rows(f.parent) for f in files)


def _stopped(saved: str | None, what: str = "result") -> NoReturn:
    """One line after Ctrl-C or SIGTERM: ``saved`` (what is saved and where) and that the same
    command resumes, or that no ``what`` was saved and the same command starts from the
    beginning; exit 128 + the signal (130 for Ctrl-C)."""
    global _reported
    _reported = True
    if saved:
        typer.echo(f"\n{_stop_word()}: {saved}; re-run the same command to resume where it "
                   "stopped", err=True)
    else:
        typer.echo(f"\n{_stop_word()} before any {what} was saved; re-running the same command "
                   "starts from the beginning", err=True)
    raise typer.Exit(128 + (_stop or signal.SIGINT))


def _interrupted(folders: Path | Sequence[Path] | None, where: Path | None = None) -> NoReturn:
    """Ctrl-C or SIGTERM: how many result rows the results folder(s) ``folders`` hold
    (``where``: the folder to name, default the only one), via :func:`_stopped`."""
    folders = [] if folders is None else [folders] if isinstance(folders, Path) else list(folders)
    n = _saved_rows(folders)
    place = None if not n else where or (
        folders[0] if len(folders) == 1 else Path(os.path.commonpath(folders)))
    _stopped(f"{n} result row(s) are saved in {place}" if n else None)


def _train_interrupted(out: Path | None) -> NoReturn:
    """Ctrl-C or SIGTERM during ``train``: whether a checkpoint is saved in ``out`` (the same
    command resumes from it) or not, via :func:`_stopped`."""
    saved = out is not None and (out / "generator.pt").is_file()
    _stopped(f"the last finished epoch is saved in {out}" if saved else None, "checkpoint")


@app.command("list")
def list_plugins() -> None:
    """List every registered attack, target, dataset, corruption and monitor, and whether it loads."""
    from tabulate import tabulate

    from icpbench.core import registry

    for reg in (registry.attacks, registry.targets, registry.datasets, registry.corruptions,
                registry.monitors):
        rows = [(i.name, "yes" if i.available else "NO", i.description if i.available else i.reason)
                for i in reg.info()]
        typer.echo(f"\n{reg.kind}s ({reg.group}):")
        typer.echo(tabulate(rows, headers=["name", "loads", "description / reason"],
                            tablefmt="simple"))
    failed = registry.plugin_module_errors()
    if failed:
        typer.echo(f"\nplugin modules named in {registry.PLUGINS_ENV} that do not load:")
        typer.echo(tabulate(sorted(failed.items()), headers=["module", "reason"],
                            tablefmt="simple"))


def _warn_plugin_modules() -> None:
    """One line on stderr per ``ICPBENCH_PLUGINS`` module that did not load."""
    from icpbench.core import registry

    for mod, reason in registry.plugin_module_errors().items():
        typer.echo(f"warning: {registry.PLUGINS_ENV} module {mod!r} did not load ({reason}); "
                   "its plugins are not registered", err=True)


@app.command()
def run(
    config: Annotated[Path | None, typer.Option(
        help="A YAML file of run settings (RunConfig fields) or a previous run's manifest.json "
             "(repeats that run); options given here override it.")] = None,
    attacks: Annotated[str | None, typer.Option(
        help="'all' or comma-separated attack names. [default: all]")] = None,
    targets: Annotated[str | None, typer.Option(
        help="Comma-separated target names. [default: p2plane]")] = None,
    dataset: Annotated[str | None, typer.Option(
        help="Registered dataset name. [default: lidar-sim]")] = None,
    budgets: Annotated[str | None, typer.Option(
        help="Comma-separated budgets λ (metres). [default: the dataset's]")] = None,
    samples: Annotated[int | None, typer.Option(
        help="Number of test samples (the first K of the split; a resumed run may grow it). "
             "[default: all]")] = None,
    seed: Annotated[str | None, typer.Option(help="Attack seed(s), comma-separated. [default: 0]")]
    = None,
    surrogate: Annotated[str | None, typer.Option(
        help="Differentiable target for gradient attacks, or `self`: each evaluated target "
             "itself (or its differentiable replica) at its own converged pose, so gradient "
             "attacks adapt to each target. [default: p2plane]")] = None,
    split: Annotated[str | None, typer.Option(help="Dataset split. [default: test]")] = None,
    strict: Annotated[bool | None, typer.Option(
        "--strict/--no-strict", help="Project displacements onto the λ-ball. [default: no]")]
    = None,
    batch_size: Annotated[int | None, typer.Option(
        help="Samples per batch (results do not depend on it). [default: 8]")] = None,
    threads: Annotated[int | None, typer.Option(
        help="torch threads (1 is fastest on small CPUs). [default: 1]")] = None,
    reference: Annotated[str, _opt(RC, "reference")] = "generator",
    out: Annotated[str, _opt(RC, "out")] = "runs/latest",
    redo: Annotated[str, _opt(RC, "redo")] = "",
    attack_param: Annotated[list[str] | None, typer.Option(
        help="Attack setting NAME.KEY=VALUE, repeatable (e.g. generator.checkpoint=gen.pt).")]
    = None,
    target_param: Annotated[list[str] | None, typer.Option(
        help="Target setting NAME.KEY=VALUE, repeatable (e.g. p2plane.max_iterations=50).")]
    = None,
    dataset_param: Annotated[list[str] | None, typer.Option(
        help="Dataset setting KEY=VALUE, repeatable (e.g. root=/data/kitti).")] = None,
    executor: Annotated[str | None, typer.Option(
        help="Where units run: local (this process), processes (one process per core of this "
             "machine, one scan at a time; ICPBENCH_WORKERS sets how many) or ray (a Ray cluster: "
             "RAY_ADDRESS, else a local one; pip install 'icpbench[ray]'). Results are the same. "
             "[default: local]")]
    = None,
    strict_files: Annotated[bool | None, typer.Option(
        "--strict-files/--no-strict-files",
        help="Stop at a sample whose input file is bad instead of skipping it with a warning. "
             "[default: no]")] = None,
    replica_queries: Annotated[bool | None, typer.Option(
        "--replica-queries/--no-replica-queries",
        help="Let a target's exact replica (KISS-ICP's) answer the query attacks' queries, about "
             "twice as fast; every row is still the target's own registration. [default: yes]")
    ] = None,
    corruptions: Annotated[str | None, typer.Option(
        help="Also run these corruptions ('all' or comma-separated names, see `icpbench list`), "
             "each at every --severities level; their rows hold the severity in the budget column "
             "and get their own table. [default: none]")] = None,
    severities: Annotated[str | None, typer.Option(
        help="Corruption severity levels, comma-separated integers 1..5. [default: 1,2,3,4,5]")]
    = None,
    monitors: Annotated[str | None, typer.Option(
        help="Integrity monitors ('all' or comma-separated, see `icpbench list`): every row "
             "records whether each fired, and the table adds each attack's detection rate and "
             "undetected error. Calibrated per target on clean train-split scans. "
             "[default: none]")] = None,
    monitor_param: Annotated[list[str] | None, typer.Option(
        help="Monitor setting NAME.KEY=VALUE, repeatable (e.g. odometry.sigma_m=0.2).")] = None,
    false_alarm_rate: Annotated[float | None, typer.Option(
        help="False-alarm rate each monitor is calibrated for (0..0.5). [default: 0.01]")] = None,
    calibration_samples: Annotated[int | None, typer.Option(
        help="Clean scans the monitors are calibrated on. [default: 100]")] = None,
    calibration_split: Annotated[str | None, typer.Option(
        help="Calibration scans from 'train' (the train split) or 'heldout' (the evaluated "
             "split's scans after the first --samples, never evaluated). [default: train]")] = None,
    monitor_aware: Annotated[bool | None, typer.Option(
        "--monitor-aware/--no-monitor-aware",
        help="Query attacks maximise the undetected error (they know the monitors). "
             "[default: no]")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", help="No progress output.")] = False,
) -> None:
    """Run the grid samples x attacks x targets x budgets x seeds and print Table 1.

    Defaults are those of icpbench.harness.runner.RunConfig; --config FILE replaces them, options given
    on the command line override both.
    """
    out_dir: Path | None = None
    try:
        from icpbench.harness.corruption_report import corruption_section, split_rows
        from icpbench.harness.monitor_report import monitor_section
        from icpbench.harness.report import render, table1, transfer_frame
        from icpbench.harness.results import attacks_not_run, load_results
        from icpbench.harness.runner import RunConfig
        from icpbench.harness.runner import run as run_grid

        own = RC.parse({"out": out, "reference": reference, "redo": redo})
        out_dir = Path(own.out)
        base = RunConfig.from_file(config) if config is not None else RunConfig()
        given: dict[str, object] = {  # list fields as the flag's text: RunOptions reads them
            "attacks": attacks, "targets": targets, "dataset": dataset, "budgets": budgets,
            "samples": samples, "seeds": seed, "surrogate": surrogate, "split": split,
            "strict": strict, "batch_size": batch_size, "threads": threads, "executor": executor,
            "strict_files": strict_files, "replica_queries": replica_queries,
            "corruptions": corruptions, "severities": severities,
            "monitors": monitors, "false_alarm_rate": false_alarm_rate,
            "calibration_samples": calibration_samples, "calibration_split": calibration_split,
            "monitor_aware": monitor_aware}
        if dataset is not None and config is not None and dataset != base.dataset:
            base.dataset_params = {}  # another dataset: the file's dataset settings do not apply
            if budgets is None:
                base.budgets = None
        for k, v in given.items():
            if v is not None:
                setattr(base, k, v)
        for flag, field_, items in (("--attack-param", "attack_params", attack_param),
                                    ("--target-param", "target_params", target_param),
                                    ("--monitor-param", "monitor_params", monitor_param)):
            merged = {n: dict(p) for n, p in getattr(base, field_).items()}
            for n, p in _nested(items, flag).items():
                merged.setdefault(n, {}).update(p)
            setattr(base, field_, merged)
        base.dataset_params = {**base.dataset_params, **_flat(dataset_param, "--dataset-param")}
        _warn_plugin_modules()
        cfg = base.validate()
        own.check_reference(cfg.attacks)
        run_grid(cfg, out_dir, progress=not quiet, redo=own.redo)
        df, corrupted = split_rows(load_results(out_dir))
        for t in cfg.targets:
            if not df.empty:
                typer.echo(f"\nTable 1 ({cfg.dataset}, target {t}):\n")
                typer.echo(table1(df, "md", reference=reference, target=t, dataset=cfg.dataset))
            if not corrupted.empty:
                typer.echo(f"\n{corruption_section(corrupted, 'md', t)}")
            if cfg.monitors and not df.empty:
                typer.echo(f"\n{monitor_section(df, 'md', t)}")
        if len(cfg.targets) > 1 and not df.empty:
            for b in cfg.budgets:
                typer.echo(f"\nAttacks x targets (λ={b:g}, each target attacked through itself or "
                           f"its replica):\n" if cfg.surrogate == "self" else
                           f"\nTransfer table (λ={b:g}, surrogate {cfg.surrogate}):\n")
                typer.echo(render(transfer_frame(df, b), "md"))
        typer.echo(f"\nresults: {out_dir}/results.csv  manifest: {out_dir}/manifest.json")
        not_run = attacks_not_run(df)
        for name, why in not_run.items():
            typer.echo(f"error: attack {name} did not run on any sample: {why}; its rows are "
                       "retried when the same command is run again", err=True)
        if not_run:
            raise typer.Exit(2)
    except KeyboardInterrupt:
        _interrupted(out_dir)
    except Exception as exc:
        _user_error(exc)


@app.command()
def table(
    results_dir: Annotated[Path, typer.Argument(help="A directory written by `icpbench run`.")],
    format: Annotated[str, typer.Option("--format", help="md, latex or csv.")] = "md",
    reference: Annotated[str, typer.Option(help="Reference attack ('Ours').")] = "generator",
    target: Annotated[str | None, typer.Option(help="Target (needed if several).")] = None,
    transfer: Annotated[float | None, typer.Option(
        help="Print the attacks x targets table at this budget instead.")] = None,
    out: Annotated[str | None, typer.Option(
        help="Write to this file instead of stdout (never over a results folder's own files).")]
    = None,
) -> None:
    """Regenerate Table 1 (or the transfer table) from stored results."""
    from icpbench.harness.corruption_report import corruption_frame, corruption_section, split_rows
    from icpbench.harness.monitor_report import monitor_section
    from icpbench.harness.report import (
        check_table_destination,
        render,
        run_dataset,
        table1,
        transfer_frame,
        transfer_vs_baseline,
    )
    from icpbench.harness.results import load_results

    try:
        if format not in ("md", "latex", "csv"):
            raise typer.BadParameter(f"--format must be md, latex or csv, got {format!r}")
        if out is not None:
            check_table_destination(out)
        df, corrupted = split_rows(load_results(results_dir))
        if df.empty:  # corruptions only: their table (CSV: the same cells)
            text = corruption_section(corrupted, format, target) if format != "csv" else \
                render(corruption_frame(corrupted, target), "csv")
            _write_or_echo(text, out)
            return
        RC.parse({"reference": reference}).check_reference(set(df["attack"]))
        if transfer is not None:
            text = render(transfer_frame(df, transfer), format)
            if format != "csv" and "normal" in set(df["attack"]):
                text += ("\n\nDo attacks crafted on the surrogate beat `normal` on each target? "
                         "Difference of mean errors (converged runs) and share of samples with "
                         "a larger error (non-converged runs at their final error):\n\n"
                         + render(transfer_vs_baseline(df, transfer), format) + "\n")
        else:
            text = table1(df, format, reference=reference, target=target,
                          dataset=run_dataset(results_dir))
            if format != "csv" and not corrupted.empty:  # CSV stays one table
                text += "\n" + corruption_section(corrupted, format, target)
            if format != "csv":
                for t in [target] if target else sorted(df["target"].unique()):
                    section = monitor_section(df, format, t)
                    text += f"\n\n{section}\n" if section else ""
        _write_or_echo(text, out)
    except Exception as exc:
        _user_error(exc)


@app.command()
def leaderboard(
    domain: Annotated[str, _opt(LB, "domain")] = "town",
    samples: Annotated[int | None, _opt(LB, "samples")] = None,
    budgets: Annotated[str | None, _opt(LB, "budgets")] = None,
    variants: Annotated[str | None, _opt(LB, "variants")] = None,
    add_target: Annotated[list[str] | None, _opt(LB, "add_target")] = None,
    extra_attacks: Annotated[str | None, _opt(LB, "extra_attacks")] = None,
    dataset: Annotated[str | None, _opt(LB, "dataset")] = None,
    dataset_param: Annotated[list[str] | None, _opt(LB, "dataset_param")] = None,
    ensemble_param: Annotated[list[str] | None, _opt(LB, "ensemble_param")] = None,
    seed: Annotated[int | None, _opt(LB, "seed")] = None,
    executor: Annotated[str, _opt(LB, "executor")] = "local",
    out: Annotated[str | None, _opt(LB, "out")] = None,
    compare_with: Annotated[str | None, _opt(LB, "compare_with")] = None,
    carry_over: Annotated[str | None, _opt(LB, "carry_over")] = None,
    monitors: Annotated[str | None, _opt(LB, "monitors")] = None,
    monitor_aware: Annotated[bool, _opt(LB, "monitor_aware", "--monitor-aware")] = False,
    quiet: Annotated[bool, _opt(LB, "quiet", "--quiet")] = False,
) -> None:
    """Rank ICP variants by the worst case the attack ensemble finds against each (adaptive:
    --surrogate self), under the standard protocol of a domain unless told otherwise; writes
    leaderboard.md/.csv/.png and one results folder per variant."""
    out_dir: Path | None = None
    try:
        from icpbench.harness.leaderboard import (
            LeaderboardConfig,
            run_leaderboard,
            split_variant_labels,
        )

        o = LB.parse(dict(
            domain=domain, samples=samples, budgets=budgets, variants=variants,
            add_target=list(add_target or []), extra_attacks=extra_attacks or [],
            dataset=dataset, dataset_param=_flat(dataset_param, "--dataset-param"),
            ensemble_param=_flat(ensemble_param, "--ensemble-param"), seed=seed,
            executor=executor, out=out, compare_with=compare_with, carry_over=carry_over,
            monitors=monitors or [], monitor_aware=monitor_aware, quiet=quiet))
        out_dir = Path(o.out if o.out is not None else "results/leaderboard"
                       if o.domain == "town" else f"results/leaderboard-{o.domain}")
        cfg = LeaderboardConfig.for_domain(o.domain, executor=o.executor,
                                           extra_targets=list(o.add_target))
        if o.dataset is not None:
            cfg.dataset, cfg.dataset_params = o.dataset, {}
        if o.dataset_param:
            cfg.dataset_params = {**cfg.dataset_params, **o.dataset_param}
        if o.ensemble_param:
            cfg.ensemble = dict(o.ensemble_param)
        if o.seed is not None:
            cfg.seed = o.seed
        if extra_attacks is not None:
            cfg.extra_attacks = list(o.extra_attacks)
        if o.samples is not None:
            cfg.samples = o.samples
        if o.budgets is not None:
            cfg.budgets = list(o.budgets)
        cfg.monitors, cfg.monitor_aware = list(o.monitors), o.monitor_aware
        if o.variants is not None:  # a label may contain commas only if it is a known one
            cfg.variants = split_variant_labels(o.variants)
        n = len(cfg.resolve())
        proto = cfg.protocol()
        if not quiet:
            typer.echo(f"protocol: {proto.name} v{proto.version}, domain {proto.domain} "
                       f"({proto.dataset}, {proto.samples} scans, budgets "
                       f"{', '.join(f'{b:g}' for b in proto.budgets)} m)", err=True)

        def note(v, status: str) -> None:
            if not quiet:
                typer.echo(f"[{v.label}] {status}", err=True)

        if compare_with is not None and not (Path(compare_with) / "leaderboard.csv").is_file():
            raise typer.BadParameter(f"--compare-with {compare_with}: no board there (no "
                                     "leaderboard.csv)")
        board = run_leaderboard(cfg, out_dir, progress=not quiet, on_variant=note,
                                compare_with=compare_with, carry_over_from=o.carry_over)
        typer.echo((out_dir / "leaderboard.md").read_text())
        typer.echo(f"{board.variant.nunique()} of {n} variant(s) ranked, {len(board)} rows: "
                   f"{out_dir}/leaderboard.md, .csv, .png")
        if _board_warnings(board):
            raise typer.Exit(2)
    except KeyboardInterrupt:
        _interrupted(_board_runs(out_dir), None if out_dir is None else out_dir / "runs")
    except Exception as exc:
        _user_error(exc)


def _board_runs(out_dir: Path | None) -> list[Path]:
    """The results folders of a board's variants (``out/runs/*``)."""
    runs = None if out_dir is None else out_dir / "runs"
    return sorted(p for p in runs.iterdir() if p.is_dir()) if runs and runs.is_dir() else []


def _board_warnings(board: pd.DataFrame) -> bool:
    """Say on stderr what a board does not rank or count: variants not ranked, extra attacks that
    did not run on a variant, scans that failed. True if something was not measured because its
    rows failed (not merely skipped by the configuration): the command then exits with 2."""
    skipped = board.attrs.get("skipped", {})
    failed = False
    for label, why in board.attrs.get("not_ranked", {}).items():
        typer.echo(f"{'warning' if label in skipped else 'error'}: variant {label!r} is not "
                   f"ranked: {why}", err=True)
        failed |= label not in skipped
    for attack, where in board.attrs.get("extra_not_run", {}).items():
        for label, why in where.items():
            typer.echo(f"error: extra attack {attack} did not run on variant {label!r}: {why}",
                       err=True)
            failed = True
    for r in board[board.failed > 0].itertuples():
        typer.echo(f"warning: variant {r.variant!r} at λ={r.budget:g}: {r.failed} of {r.scans} "
                   "scan(s) failed (left out of its numbers; see the results in its runs/ "
                   "folder)", err=True)
    return failed


def _write_or_echo(text: str, out: str | None) -> None:
    """Print a table, or write it to ``out`` (never over a file it did not write)."""
    from icpbench.harness.report import write_table

    if out is None:
        typer.echo(text)
    else:
        write_table(out, text)


@app.command("show-dataset")
def show_dataset(
    name: Annotated[str, typer.Argument(help="Dataset name, e.g. lidar-sim.")] = "lidar-sim",
    out: Annotated[Path, typer.Option(help="Output directory for the PNGs.")] = Path("results"),
    sample: Annotated[int | None, typer.Option(help="Sample index of the scan overlay.")] = None,
    dataset_param: Annotated[list[str] | None, typer.Option(help="KEY=VALUE.")] = None,
) -> None:
    """Write a top view of the dataset (route by stretch type) and a scan overlaid on its map."""
    from icpbench.analysis.dataset_figures import show_dataset as show

    try:
        paths = show(name, out, sample_index=sample, **_flat(dataset_param, "--dataset-param"))
        for p in paths:
            typer.echo(str(p))
    except Exception as exc:
        _user_error(exc)


@app.command("map")
def danger_map(
    attack: Annotated[str, _opt(MAP, "attack")] = "generator",
    budget: Annotated[float, _opt(MAP, "budget")] = 1.0,
    dataset: Annotated[str, _opt(MAP, "dataset")] = "lidar-sim",
    split: Annotated[str, _opt(MAP, "split")] = "test",
    samples: Annotated[int | None, _opt(MAP, "samples")] = None,
    compare: Annotated[str | None, _opt(MAP, "compare")] = None,
    attack_param: Annotated[list[str] | None, _opt(MAP, "attack_param")] = None,
    dataset_param: Annotated[list[str] | None, _opt(MAP, "dataset_param")] = None,
    out: Annotated[str, _opt(MAP, "out")] = "runs/map",
    executor: Annotated[str, _opt(MAP, "executor")] = "local",
    monitors: Annotated[str | None, _opt(MAP, "monitors")] = None,
    monitor_aware: Annotated[bool, _opt(MAP, "monitor_aware", "--monitor-aware")] = False,
    quiet: Annotated[bool, _opt(MAP, "quiet", "--quiet")] = False,
) -> None:
    """Worst-case error at every location of a route: CSVs and route maps (paper fig. 5/6); with
    --monitors also the error that no integrity monitor catches."""
    out_dir: Path | None = None
    try:
        from icpbench.analysis.danger_map import write_maps
        from icpbench.harness.results import load_results
        from icpbench.harness.runner import RunConfig
        from icpbench.harness.runner import run as run_grid

        o = MAP.parse(dict(attack=attack, budget=budget, dataset=dataset, split=split,
                           samples=samples, compare=compare,
                           attack_param=_nested(attack_param, "--attack-param"),
                           dataset_param=_flat(dataset_param, "--dataset-param"), out=out,
                           executor=executor, quiet=quiet, monitor_aware=monitor_aware,
                           **({} if monitors is None else {"monitors": monitors})))
        from icpbench.harness.outputs import claim

        attack, budget, compare = o.attack, o.budget, o.compare
        attacks = [attack] + ([compare] if compare else [])
        cfg = RunConfig(dataset=o.dataset, attacks=attacks, targets=["p2plane"], budgets=[budget],
                        samples=o.samples, split=o.split, executor=o.executor,
                        attack_params=o.attack_param, dataset_params=o.dataset_param,
                        monitors=o.monitors, monitor_aware=o.monitor_aware).validate()
        out = out_dir = claim(o.out, "map")  # after the checks: a refused map makes no folder
        run_grid(cfg, out / "run", progress=not quiet)
        summary = write_maps(load_results(out / "run"), attack, budget, out, compare)
        for name in attacks:
            s = summary[name]
            typer.echo(f"{name}: {s['locations']} locations, {s['passes']} passes, mean error "
                       f"{s['mean_trans_err_xy']:.2f} m, AUC open-vs-dense "
                       f"{s.get('auc_open_vs_dense', float('nan')):.3f}, pass rank correlation "
                       f"{s['pass_rank_correlation']:.3f}" + (
                           f", undetected by the monitors {s['mean_undetected']:.2f} m "
                           f"({s['detected_pct']:.0f}% of registrations detected)"
                           if "mean_undetected" in s else ""))
        if compare:
            c = summary["comparison"]
            typer.echo(f"{attack} - {compare}: median {c['median']:.2f} m, IQR [{c['q1']:.2f}, "
                       f"{c['q3']:.2f}] m, {attack} larger at {100 * c['share_ours_larger']:.0f}%")
        typer.echo(f"written to {out}: " + ", ".join(summary["files"]))
    except KeyboardInterrupt:
        _interrupted(None if out_dir is None else out_dir / "run")
    except Exception as exc:
        _user_error(exc)


@app.command("validate-map")
def validate_map(
    dataset: Annotated[str, _opt(VM, "dataset")] = "lidar-sim",
    split: Annotated[str, _opt(VM, "split")] = "test",
    samples: Annotated[int, _opt(VM, "samples")] = 96,
    attacks: Annotated[str, _opt(VM, "attacks")] = "generator,sector-iter",
    budget: Annotated[float, _opt(VM, "budget")] = 1.0,
    corruptions: Annotated[str, _opt(VM, "corruptions")] = "all",
    severities: Annotated[str, _opt(VM, "severities")] = "1,2,3,4,5",
    fail_m: Annotated[float, _opt(VM, "fail_m")] = 0.5,
    headline_severity: Annotated[int, _opt(VM, "headline_severity")] = 3,
    bootstrap: Annotated[int, _opt(VM, "bootstrap")] = 1000,
    route: Annotated[str, _opt(VM, "route")] = "",
    attack_param: Annotated[list[str] | None, _opt(VM, "attack_param")] = None,
    dataset_param: Annotated[list[str] | None, _opt(VM, "dataset_param")] = None,
    executor: Annotated[str, _opt(VM, "executor")] = "local",
    out: Annotated[str, _opt(VM, "out")] = "runs/danger-validation",
    redo: Annotated[str, _opt(VM, "redo")] = "",
    quiet: Annotated[bool, _opt(VM, "quiet", "--quiet")] = False,
) -> None:
    """Do danger maps predict real trouble? Worst cases and cheap predictors against the errors of
    realistic corruptions, place by place: Spearman and ROC AUC with bootstrap intervals, a route
    figure, summary.json/md and a manifest in --out (the error rows in --out/run, resumable)."""
    out_dir: Path | None = None
    try:
        from icpbench.analysis.danger_validation import ValidationSettings, validate

        o = VM.parse(dict(dataset=dataset, split=split, samples=samples, attacks=attacks,
                          budget=budget, corruptions=corruptions, severities=severities,
                          fail_m=fail_m, headline_severity=headline_severity,
                          bootstrap=bootstrap, route=route,
                          attack_param=_nested(attack_param, "--attack-param"),
                          dataset_param=_flat(dataset_param, "--dataset-param"),
                          executor=executor, out=out, redo=redo, quiet=quiet))
        out_dir = Path(o.out)
        settings = ValidationSettings(
            dataset=o.dataset, split=o.split, samples=None if o.samples == 0 else o.samples,
            dataset_params=o.dataset_param, attacks=list(o.attacks), budget_m=o.budget,
            corruptions=list(o.corruptions), severities=list(o.severities), fail_m=o.fail_m,
            headline_severity=o.headline_severity, n_boot=o.bootstrap, executor=o.executor,
            attack_params=o.attack_param)
        command = "icpbench " + " ".join(sys.argv[1:]) if sys.argv[1:] else "icpbench validate-map"
        summary = validate(settings, out_dir, route=route, command=command, progress=not quiet,
                           redo=o.redo)
        block = summary["by_severity"][str(headline_severity)]
        typer.echo(f"{summary['route']}: {summary['places']} places, {block['failures']} fail at "
                   f"severity {headline_severity} (> {fail_m:g} m)")
        for q, v in block["quantities"].items():
            sp, auc = v["spearman"], v["auc"]
            typer.echo(f"  {q:<22} Spearman {sp['value']:+.2f} [{sp['ci95'][0]:+.2f}, "
                       f"{sp['ci95'][1]:+.2f}]  AUC {auc['value']:.2f} [{auc['ci95'][0]:.2f}, "
                       f"{auc['ci95'][1]:.2f}]")
        typer.echo(f"written to {out_dir}: " + ", ".join(summary["files"]))
    except KeyboardInterrupt:
        _interrupted(None if out_dir is None else out_dir / "run")
    except Exception as exc:
        _user_error(exc)


@app.command("object-study")
def object_study(
    model: Annotated[list[str], _opt(OS, "model")],
    budget: Annotated[float, _opt(OS, "budget")] = 0.05,
    objects: Annotated[int, _opt(OS, "objects")] = 24,
    figure_objects: Annotated[int, _opt(OS, "figure_objects")] = 4,
    out: Annotated[str, _opt(OS, "out")] = "runs/object-study",
    soft_bound: Annotated[bool, _opt(OS, "soft_bound")] = False,
) -> None:
    """Paper figure 4: objects attacked by generators trained with different loss weights
    (every attack within the budget unless --soft-bound adds the unprojected rows)."""
    from icpbench.analysis.object_study import figure, study, summary_table
    from icpbench.harness.report import render

    try:
        o = OS.parse(dict(model=dict(_kv(m, "--model") for m in model), budget=budget,
                          objects=objects, figure_objects=figure_objects, out=out,
                          soft_bound=soft_bound))
        models, budget, objects, figure_objects = o.model, o.budget, o.objects, o.figure_objects
        from icpbench.harness.outputs import check_owner, claim, write_csv, write_file

        check_owner(o.out, "object-study")  # before the study: a refused folder costs nothing
        rows, clouds, _ = study({k: str(v) for k, v in models.items()}, budget, objects,
                                figure_objects, soft_bound=soft_bound)
        out = claim(o.out, "object-study")
        write_csv(out / "object_study_rows.csv", rows, index=False)
        table = summary_table(rows)
        write_csv(out / "object_study_table.csv", table, index=False)
        write_file(out / "object_study_table.md", render(table.round(4), "md") + "\n")
        figure(rows, clouds, out / "object_study.png", budget)
        typer.echo(render(table.round(4), "md"))
        typer.echo(f"written to {out}")
    except Exception as exc:
        _user_error(exc)


@app.command()
def train(
    preset: Annotated[str, _opt(TR, "preset")] = "quick-lidar",
    out: Annotated[str, _opt(TR, "out")] = "runs/train",
    budgets: Annotated[str | None, _opt(TR, "budgets")] = None,
    weights: Annotated[str | None, _opt(TR, "weights")] = None,
    epochs: Annotated[int | None, _opt(TR, "epochs")] = None,
    pretrain_epochs: Annotated[int | None, _opt(TR, "pretrain_epochs")] = None,
    train_samples: Annotated[int | None, _opt(TR, "train_samples")] = None,
    eval_samples: Annotated[int | None, _opt(TR, "eval_samples")] = None,
    batch_size: Annotated[int | None, _opt(TR, "batch_size")] = None,
    lr: Annotated[float | None, _opt(TR, "lr")] = None,
    device: Annotated[str | None, _opt(TR, "device")] = None,
    threads: Annotated[int | None, _opt(TR, "threads")] = None,
    max_minutes: Annotated[float | None, _opt(TR, "max_minutes")] = None,
    dataset: Annotated[str | None, _opt(TR, "dataset")] = None,
    dataset_param: Annotated[list[str] | None, _opt(TR, "dataset_param")] = None,
    strict: Annotated[bool, _opt(TR, "strict")] = False,
    generator_param: Annotated[list[str] | None, _opt(TR, "generator_param")] = None,
    adv_per_budget: Annotated[bool | None, _opt(
        TR, "adv_per_budget", "--adv-per-budget/--no-adv-per-budget")] = None,
    init: Annotated[str | None, _opt(TR, "init")] = None,
    icp_preset: Annotated[str | None, _opt(TR, "icp_preset")] = None,
    icp_backprop: Annotated[str | None, _opt(TR, "icp_backprop")] = None,
    alpha: Annotated[float | None, _opt(TR, "alpha")] = None,
    sector_iter_param: Annotated[list[str] | None, _opt(TR, "sector_iter_param")] = None,
    quiet: Annotated[bool, _opt(TR, "quiet", "--quiet")] = False,
) -> None:
    """Train a generator through the differentiable ICP; checkpoints every epoch, resumable."""
    try:
        from icpbench.learning.training import train as run_training
        from icpbench.learning.training import train_config

        o = TR.parse(dict(
            preset=preset, out=out, budgets=budgets, weights=weights, epochs=epochs,
            pretrain_epochs=pretrain_epochs, train_samples=train_samples,
            eval_samples=eval_samples, batch_size=batch_size, lr=lr, device=device,
            threads=threads, max_minutes=max_minutes, dataset=dataset,
            dataset_param=_flat(dataset_param, "--dataset-param"), strict=strict,
            generator_param=_flat(generator_param, "--generator-param"),
            adv_per_budget=adv_per_budget, init=init, icp_preset=icp_preset,
            icp_backprop=icp_backprop, alpha=alpha,
            sector_iter_param=_flat(sector_iter_param, "--sector-iter-param"), quiet=quiet))
        out_dir, preset = Path(o.out), o.preset
        over = {k: v for k, v in dict(
            weights=o.weights, epochs=o.epochs, pretrain_epochs=o.pretrain_epochs,
            train_samples=o.train_samples, eval_samples=o.eval_samples,
            batch_size=o.batch_size, lr=o.lr, device=o.device, threads=o.threads,
            max_minutes=o.max_minutes, strict=o.strict or None,
            adv_per_budget=o.adv_per_budget, init_checkpoint=o.init, icp_preset=o.icp_preset,
            icp_backprop=o.icp_backprop, dataset=o.dataset, alpha=o.alpha,
            budgets=None if o.budgets is None else list(o.budgets),
            dataset_params=o.dataset_param or None,
            generator_overrides=o.generator_param or None).items() if v is not None}
        if o.sector_iter_param:
            over["sector_iter"] = {**train_config(preset).sector_iter, **o.sector_iter_param}
        card = run_training(train_config(preset, **over), out_dir, progress=not quiet,
                            log=None if quiet else typer.echo)
        typer.echo(f"checkpoint: {out_dir}/generator.pt")
        for lam, r in card.get("heldout_eval", {}).items():
            typer.echo(f"held-out λ={lam}: mean trans_err_xy {r['trans_err_xy_mean']} m "
                       f"({r['converged']}/{r['samples']} converged), mean max displacement "
                       f"{r['disp_max_mean']:.3f}")
    except KeyboardInterrupt:
        _train_interrupted(Path(out) if out.strip() else None)
    except Exception as exc:
        _user_error(exc)


def main() -> None:
    """Console-script entry point. A stop signal that reached no command's own handling (while
    the options are parsed, or in a command that saves nothing) still gives one line and
    128 + the signal."""
    global _running, _reported
    _install_stop_handlers()
    _running = True
    try:
        app()
    except KeyboardInterrupt:
        pass
    except SystemExit:
        if _stop is None or _reported:
            raise
    finally:
        if _stop is not None:
            _keep_exit_status()
    if not _reported:
        _reported = True
        typer.echo(f"\n{_stop_word()} before any result was saved; re-running the same command "
                   "starts from the beginning", err=True)  # no command got to save anything
    sys.exit(128 + (_stop or signal.SIGINT))


def _keep_exit_status() -> None:
    """Make the exit status after a stop signal 128 + the signal, also under ``python -m``.

    CPython (3.11) marks a KeyboardInterrupt that ends code run by ``exec`` of a string (as
    ``dataclasses`` and ``namedtuple`` do while a module is imported) as unhandled, and a process
    started with ``-m`` then kills itself with SIGINT at exit whatever ``sys.exit`` was given
    (measured: 3 of 40 Ctrl-Cs at 0.4-3 s into ``icpbench run`` ended by signal 2). The mark is
    cleared whenever an ``exec`` of a string finishes, so one that does nothing restores the status.
    """
    exec("pass")  # noqa: S102 - a constant string; see the docstring


if __name__ == "__main__":
    main()
