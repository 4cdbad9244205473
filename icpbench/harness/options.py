"""Typed models of the options of every command: the one validation layer of the entry points.

Each command's options are a pydantic model (:class:`RunOptions` for ``icpbench run`` and its
config files and manifests, :class:`LeaderboardOptions`, :class:`MapOptions`,
:class:`ValidateMapOptions`, :class:`TrainOptions`, :class:`ObjectStudyOptions`). A field states
once its type, its physically sensible range (``ge``/``gt``/``le``/``lt``) and its meaning (the
``description``, which is also the option's ``--help``). :meth:`Options.parse` checks a mapping
of option values from any source (the flags, a YAML/JSON file, a manifest, code) and turns the
first bad one into one :class:`~icpbench.core.errors.InputError` that names the file (if any), the
field, the flag, what the value must be and the value given.

Models are strict: a YAML ``threads: '2'`` is text, not an integer, and ``strict: 1`` is not a
boolean. The list fields (attacks, budgets, ...) keep the flag's spellings (``"1,5"``, one value
for a list of one) through :class:`~icpbench.harness.settings.ListField`, which pydantic has no
counterpart for; their items are then checked by the model like any other value.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

import annotated_types as at
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)
from pydantic.fields import FieldInfo

from icpbench.core.errors import InputError
from icpbench.harness import settings as S

#: Upper bound of counts (samples, epochs, ...): what a 64-bit results store holds.
COUNT_MAX = S.SEED_MAX
#: Threads a process may ask for (torch, KISS's oneTBB): far above any CPU's core count.
THREADS_MAX = 1024
#: Largest error threshold and bootstrap count that still mean something (metres; resamples).
METRES_MAX, BOOTSTRAP_MAX = 1e3, 1_000_000


class _Across(ValueError):
    """A value that does not fit another field's (``field``: the one named; ``text``: what it
    must be, and the value)."""

    def __init__(self, field: str, text: str) -> None:
        super().__init__(text)
        self.field = field


def _list(key: str) -> BeforeValidator:
    """The list field ``key`` of :data:`~icpbench.harness.settings.LIST_FIELDS`, read as its flag
    reads it (a text split at commas, one value a list of one), items checked, repeats refused."""
    spec = S.LIST_FIELDS[key]

    def read(v: Any) -> Any:
        out = spec.check(v, S.FLAGS.get(key, "--" + key))
        return None if out is None else (spec.whole(out) if spec.whole else out)

    return BeforeValidator(read)


def _comma_names(v: Any) -> Any:
    """Names given as one comma-separated text (the flag) or a list (a file)."""
    if isinstance(v, str):
        return [x.strip() for x in v.split(",") if x.strip()]
    return v


Name = Annotated[str, at.MinLen(1), BeforeValidator(lambda v: v.strip() if isinstance(v, str) else v)]
Count = Annotated[int, Field(ge=1, le=COUNT_MAX)]
Seed = Annotated[int, Field(ge=S.SEED_MIN, le=S.SEED_MAX)]
Budget = Annotated[float, Field(ge=S.BUDGET_MIN, le=S.BUDGET_MAX, allow_inf_nan=False)]
#: ``--redo``: attacks of a run whose stored rows are computed again (``icpbench run``,
#: ``icpbench validate-map``).
Redo = Annotated[list[Name], BeforeValidator(_comma_names)]
_REDO = Field([], description="Comma-separated attacks of the run whose stored rows are removed "
                              "and computed again with their current settings (e.g. after a "
                              "default changed).")


def _folder(v: str) -> str:
    """An output folder: a path that is missing or a folder (a file, a link, a device refused)."""
    from icpbench.harness.outputs import PATH_WORDS, path_kind

    what = path_kind(v)
    if what not in ("missing", "folder"):
        raise InputError(f"{v!r} is {PATH_WORDS[what]}, not a folder")
    return v


#: An output folder (``--out``): a non-empty path that is missing or a folder.
OutFolder = Annotated[Name, AfterValidator(_folder)]
#: An executor name, checked against the known ones by ``check_executor`` (its message lists them).
Executor = Name
Settings = dict[str, Any]
PluginSettings = dict[str, dict[str, Any]]


class Options(BaseModel):
    """Base of the option models: strict types, unknown fields refused, :meth:`parse`."""

    model_config = ConfigDict(strict=True, extra="forbid", validate_default=False,
                              arbitrary_types_allowed=True)
    #: The flag of each field where it is not ``--`` + the field's name with dashes.
    flags: ClassVar[dict[str, str]] = {}

    @classmethod
    def flag(cls, name: str) -> str:
        """The command-line flag of field ``name``."""
        return cls.flags.get(name, "--" + name.replace("_", "-"))

    @classmethod
    def help(cls, name: str) -> str:
        """The ``--help`` text of field ``name``: its description."""
        return cls.model_fields[name].description or ""

    @classmethod
    def must(cls, name: str) -> str:
        """What a value of field ``name`` must be, in words, from its type and range."""
        return must(cls.model_fields[name])

    @classmethod
    def parse(cls, data: Mapping[str, Any], source: str | None = None) -> Options:
        """The options in ``data`` checked (fields not given keep their defaults).

        Args:
            data: field -> value, from the flags, a file or code.
            source: the file the values were read from, named in messages (None: the flags).

        Raises:
            InputError: ``data`` is not a mapping, names an unknown field (the valid ones are
                listed) or a value is not what its field takes (named with its flag or file).
        """
        where = "options" if source is None else source
        if not isinstance(data, Mapping):
            raise InputError(f"{where} must be a mapping of settings, got {type(data).__name__}")
        unknown = sorted(map(str, set(data) - set(cls.model_fields)))
        if unknown:
            raise InputError(f"{where}: unknown setting(s) {', '.join(map(repr, unknown))}; valid: "
                             f"{', '.join(cls.model_fields)}")
        try:
            return cls.model_validate(dict(data))
        except ValidationError as exc:
            raise cls._refusal(exc, data, source) from None

    @classmethod
    def _refusal(cls, exc: ValidationError, data: Mapping[str, Any],
                 source: str | None) -> InputError:
        err = exc.errors()[0]
        name = str(err["loc"][0]) if err["loc"] else ""
        bad = (err.get("ctx") or {}).get("error")
        if isinstance(bad, _Across):  # a check of two fields together
            where = cls.flag(bad.field) if source is None else f"{source}: setting {bad.field!r}"
            return InputError(f"{where} {bad}")
        if name not in cls.model_fields:
            return InputError(f"{source + ': ' if source else ''}{bad or err['msg']}")
        given = data.get(name)
        if isinstance(bad, S._Bad):  # a list field: ListField says what and which item
            what = str(bad) + (f" ({bad.detail})" if bad.detail else "")
            if source is None:
                return InputError(f"{name} ({cls.flag(name)}) must be {what}, got {given!r}")
            return InputError(f"{source}: setting {name!r} must be {what}, got {given!r}")
        if isinstance(bad, InputError):  # a whole-list rule (budgets)
            where = f"{name} ({cls.flag(name)})" if source is None else f"{source}: setting {name!r}"
            return InputError(f"{where}: {bad}")
        what = cls.must(name)
        if source is None:
            return InputError(f"{cls.flag(name)} must be {what}, got {given!r}")
        return InputError(f"{source}: setting {name!r} must be {what}, got {given!r}")


def _bounds(meta: list[Any]) -> str:
    parts = []
    for m in meta:
        for attr, sym in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
            v = getattr(m, attr, None)
            if v is not None and not (isinstance(v, int | float) and abs(v) >= 2**62):
                parts.append(f"{sym} {v:g}" if v != int(v) or abs(v) < 1e-4 else f"{sym} {int(v)}")
        if isinstance(m, at.MinLen) and m.min_length:
            parts.append("non-empty")
    return " and ".join(parts)


def _base(tp: Any) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        inner, meta = args[0], list(args[1:])
        for m in meta:  # Field(...) inside Annotated carries its bounds in .metadata
            meta += list(getattr(m, "metadata", []) or [])
        words, bounds = _base(inner), _bounds(meta)
        return f"{words} {bounds}" if bounds and bounds != "non-empty" else (
            "a non-empty text" if bounds == "non-empty" else words)
    if origin is Literal:
        return "one of " + ", ".join(map(str, args))
    if origin in (typing.Union, types.UnionType):
        kinds = [a for a in args if a is not type(None)]
        text = " or ".join(_base(a) for a in kinds)
        return text + (" or null" if len(kinds) < len(args) else "")
    if origin is dict:
        return "a mapping of settings (KEY: VALUE)" if args[1] is Any or args[1] == "Any" else \
            "a mapping of plugin names to mappings of settings (NAME: {KEY: VALUE})"
    if origin is list:
        return f"a list, each item {_base(args[0])}"
    return {int: "an integer", float: "a number", bool: "true or false",
            str: "a text"}.get(tp, getattr(tp, "__name__", str(tp)))


def must(info: FieldInfo) -> str:
    """What a value of a field must be, in words (type and range)."""
    text = _base(Annotated[(info.annotation, *info.metadata)] if info.metadata
                 else info.annotation)
    return text


# -- icpbench run (flags, config files, manifests, code) -----------------------------------------
class RunOptions(Options):
    """The settings of ``icpbench run`` (the fields of
    :class:`~icpbench.harness.runner.RunConfig`; names, plugin settings and executors are then
    checked against the registry by ``RunConfig.validate``)."""

    flags: ClassVar[dict[str, str]] = S.FLAGS

    dataset: Name = Field("lidar-sim", description="Registered dataset name.")
    attacks: Annotated[list[Name], _list("attacks")] = Field(
        ["all"], description="'all' or attack names.")
    targets: Annotated[list[Name], _list("targets")] = Field(
        ["p2plane"], description="Target names.")
    budgets: Annotated[list[Budget] | None, _list("budgets")] = Field(
        None, description="Budgets λ (metres; normalised units for objects); null: the "
                          "dataset's.")
    samples: Count | None = Field(
        None, description="Scans: the first K of the split (null: all; a resumed run may grow it).")
    seeds: Annotated[list[Seed], _list("seeds")] = Field([0], description="Attack seeds.")
    surrogate: Name = Field("p2plane", description="Differentiable target of gradient attacks, "
                                                   "or 'self'.")
    split: Name = Field("test", description="Dataset split.")
    dataset_seed: Annotated[int, Field(ge=0, le=S.SEED_MAX)] = Field(
        0, description="Seed of the dataset itself.")
    dataset_params: Settings = Field({}, description="Dataset settings.")
    icp_preset: Name | None = Field(None, description="ICP preset of every target (null: the "
                                                      "dataset's).")
    batch_size: Count = Field(8, description="Scans per batch (results do not depend on it).")
    strict: bool = Field(False, description="Project displacements onto the λ-ball.")
    threads: Annotated[int, Field(ge=1, le=THREADS_MAX)] = Field(
        1, description="torch threads (1 is fastest on small CPUs).")
    attack_params: PluginSettings = Field({}, description="Per-attack settings.")
    target_params: PluginSettings = Field({}, description="Per-target settings.")
    executor: Executor = Field("local", description="local, processes or ray.")
    strict_files: bool = Field(False, description="Stop at a bad input file.")
    replica_queries: bool = Field(
        True, description="Let a target's exact replica answer the query attacks' queries (the "
                          "rows stay the target's own registrations).")
    corruptions: Annotated[list[Name], _list("corruptions")] = Field(
        [], description="Corruptions run beside the attacks ('all' or names).")
    severities: Annotated[list[Annotated[int, Field(ge=S.SEVERITY_MIN, le=S.SEVERITY_MAX)]],
                          _list("severities")] = Field(
        [1, 2, 3, 4, 5], description="Corruption severity levels.")
    monitors: Annotated[list[Name], _list("monitors")] = Field(
        [], description="Integrity monitors whose alarms every row records ('all' or names).")
    monitor_params: PluginSettings = Field({}, description="Per-monitor settings.")
    false_alarm_rate: Annotated[float, Field(gt=0, le=0.5, allow_inf_nan=False)] = Field(
        0.01, description="False-alarm rate each monitor is calibrated for, on the clean "
                          "calibration scans.")
    calibration_samples: Annotated[int, Field(ge=2, le=1_000_000)] = Field(
        100, description="Clean scans the monitors are calibrated on (at least "
                         "1 / false_alarm_rate).")
    calibration_split: Literal["train", "heldout"] = Field(
        "train", description="Where the calibration scans come from: 'train' (the train split) or "
                             "'heldout' (the evaluated split's scans after the first --samples, "
                             "never evaluated).")
    monitor_aware: bool = Field(False, description="Query attacks maximise the undetected error.")

    @model_validator(mode="after")
    def _heldout_needs_samples(self) -> RunOptions:
        if self.calibration_split == "heldout" and self.samples is None:
            raise _Across("calibration_split", "'heldout' needs samples: the calibration scans are "
                                               "those after the first --samples")
        return self


class RunCommandOptions(Options):
    """The options of ``icpbench run`` that are not run settings (not :class:`RunOptions`, not
    in a config file): where the rows go and the table's reference attack."""

    out: OutFolder = Field("runs/latest", description="Results directory (re-run to resume).")
    reference: Name = Field("generator", description="Reference attack of '% Ours is Larger'.")
    redo: Redo = _REDO

    def check_reference(self, attacks: list[str] | set[str]) -> None:
        """``reference`` must name a registered attack or one of ``attacks`` (those of the
        results). Raises InputError listing the valid names."""
        from icpbench.core import registry

        if self.reference not in attacks and self.reference not in registry.attacks.names():
            valid = sorted(set(registry.attacks.names()) | set(attacks))
            raise InputError(f"--reference {self.reference!r} is not an attack; valid: "
                             f"{', '.join(valid)}")


# -- icpbench leaderboard --------------------------------------------------------------------------
class LeaderboardOptions(Options):
    """The options of ``icpbench leaderboard``."""

    flags: ClassVar[dict[str, str]] = {"add_target": "--add-target",
                                       "dataset_param": "--dataset-param",
                                       "ensemble_param": "--ensemble-param"}

    domain: Literal["town", "unseen"] = Field(
        "town", description="Standard domain: 'town' (the default simulated town and sensor) or "
                            "'unseen' (town 101, 64-beam sensor).")
    samples: Count | None = Field(
        None, description="Scans per variant (the first K of the split); departs from the "
                          "standard protocol. [default: the protocol's, 48]")
    budgets: Annotated[list[Budget] | None, _list("budgets")] = Field(
        None, description="Comma-separated budgets λ (metres); departs from the standard "
                          "protocol. [default: the protocol's, 1]")
    variants: Name | None = Field(
        None, description="Comma-separated labels of the standard variants to rank. "
                          "[default: all]")
    add_target: list[Name] = Field(
        [], description="A further target plugin to rank with its defaults (repeatable): your "
                        "own ICP.")
    extra_attacks: Annotated[list[Name], BeforeValidator(_comma_names)] = Field(
        [], description="Comma-separated attacks run on every variant beside the ensemble, with "
                        "their defaults (your own attack plugin); a scan's worst case is the "
                        "largest over the ensemble and these. [default: none]")
    dataset: Name | None = Field(
        None, description="Dataset; departs from the standard protocol. [default: the domain's, "
                          "lidar-sim]")
    dataset_param: Settings = Field(
        {}, description="Dataset setting KEY=VALUE, repeatable; departs from the standard "
                        "protocol.")
    ensemble_param: Settings = Field(
        {}, description="Ensemble setting KEY=VALUE, repeatable (members, pgd_steps, "
                        "pgd_step_size, sector_iterations, queries, patience, spoof_queries, "
                        "valley_queries, valley_line_steps, valley_kernel_model, directions, "
                        "screen); departs from "
                        "the standard protocol.")
    seed: Seed | None = Field(
        None, description="Attack seed; departs from the standard protocol. [default: 0]")
    executor: Executor = Field("local", description="local, processes or ray (see `icpbench "
                                                    "run`).")
    out: OutFolder | None = Field(
        None, description="Board folder (re-run to resume). [default: results/leaderboard, "
                          "results/leaderboard-unseen for the unseen domain]")
    compare_with: Name | None = Field(
        None, description="Another board's folder (e.g. the other domain's): state the agreement "
                          "of the two rankings (Kendall's tau) on this board.")
    carry_over: Name | None = Field(
        None, description="A board of an earlier version of the same protocol: copy in each of "
                          "its runs whose rows this version computes again (the same run "
                          "settings as they act on the variant's target); compute the rest.")
    monitors: Annotated[list[Name], _list("monitors")] = Field(
        [], description="Integrity monitors ('all' or comma-separated): the board adds each "
                        "variant's detection rate and undetected worst case. [default: none]")
    monitor_aware: bool = Field(False, description="The attacks maximise the undetected error "
                                                   "(needs --monitors).")
    quiet: bool = Field(False, description="No progress output.")


# -- icpbench map ---------------------------------------------------------------------------------
class MapOptions(Options):
    """The options of ``icpbench map``."""

    flags: ClassVar[dict[str, str]] = {"attack_param": "--attack-param",
                                       "dataset_param": "--dataset-param"}

    attack: Name = Field("generator", description="Attack that estimates the worst case.")
    budget: Budget = Field(1.0, description="Budget λ in metres.")
    dataset: Name = Field("lidar-sim", description="A route dataset (lidar-sim, kitti, boreas).")
    split: Name = Field("test", description="Dataset split (test passes).")
    samples: Count | None = Field(None, description="Locations x passes (default all).")
    compare: Name | None = Field(
        None, description="Also run this attack and write the difference figure (paper fig. "
                          "6), e.g. sector.")
    attack_param: PluginSettings = Field({}, description="NAME.KEY=VALUE.")
    dataset_param: Settings = Field({}, description="KEY=VALUE.")
    out: OutFolder = Field("runs/map", description="Output directory (re-run to resume).")
    executor: Executor = Field(
        "local", description="local (one process), processes or ray (one worker per core); "
                             "results do not depend on it.")
    monitors: Annotated[list[Name], _list("monitors")] = Field(
        [], description="Integrity monitors ('all' or comma-separated, see `icpbench list`), "
                        "calibrated as in `icpbench run`: the map of the error no monitor "
                        "catches is drawn beside the unmonitored one. [default: none]")
    monitor_aware: bool = Field(False, description="The attack maximises the undetected error "
                                                   "(needs --monitors).")
    quiet: bool = Field(False, description="No progress output.")


# -- icpbench validate-map ------------------------------------------------------------------------
class ValidateMapOptions(Options):
    """The options of ``icpbench validate-map``."""

    flags: ClassVar[dict[str, str]] = {"attack_param": "--attack-param",
                                       "dataset_param": "--dataset-param",
                                       "fail_m": "--fail-m"}

    dataset: Name = Field("lidar-sim", description="A route dataset (lidar-sim, kitti, boreas).")
    split: Name = Field("test", description="Dataset split.")
    samples: Annotated[int, Field(ge=0, le=COUNT_MAX)] = Field(
        96, description="Places: the first K scans of the split (a resumed run may grow it); "
                        "0 = all.")
    attacks: Annotated[list[Name], _list("attacks")] = Field(
        ["generator", "sector-iter"],
        description="Comma-separated attacks whose error at --budget is the worst case.")
    budget: Budget = Field(1.0, description="Budget λ of the attacks and the sector estimate "
                                            "(metres).")
    corruptions: Annotated[list[Name], _list("corruptions")] = Field(
        ["all"], description="'all' or comma-separated corruptions.")
    severities: Annotated[list[Annotated[int, Field(ge=S.SEVERITY_MIN, le=S.SEVERITY_MAX)]],
                          _list("severities")] = Field(
        [1, 2, 3, 4, 5], description="Corruption levels, comma-separated 1..5.")
    fail_m: Annotated[float, Field(gt=0, le=METRES_MAX, allow_inf_nan=False)] = Field(
        0.5, description="A place fails when its largest error over corruptions at a severity "
                         "exceeds this (metres).")
    headline_severity: Annotated[int, Field(ge=S.SEVERITY_MIN, le=S.SEVERITY_MAX)] = Field(
        3, description="Severity whose failures the route figure rings.")
    bootstrap: Annotated[int, Field(ge=1, le=BOOTSTRAP_MAX)] = Field(
        1000, description="Bootstrap resamples of the intervals.")
    route: str = Field("", description="A name for the route in the summary and figure.")
    attack_param: PluginSettings = Field({}, description="NAME.KEY=VALUE.")
    dataset_param: Settings = Field({}, description="KEY=VALUE.")
    executor: Executor = Field("local", description="local, processes or ray; results do not "
                                                    "depend on it.")
    out: OutFolder = Field("runs/danger-validation", description="Output folder (re-run to resume).")
    redo: Redo = _REDO
    quiet: bool = Field(False, description="No progress output.")


# -- icpbench train -------------------------------------------------------------------------------
#: Largest learning rate accepted (AdamW steps of this size already throw the weights about).
MAX_LR = 1.0


class TrainOptions(Options):
    """The options of ``icpbench train`` (None: the preset's value)."""

    flags: ClassVar[dict[str, str]] = {"init": "--init"}

    preset: Name = Field("quick-lidar", description="quick-lidar, quick-lidar-soft, paper-lidar, "
                                                    "quick-objects, paper-objects.")
    out: OutFolder = Field("runs/train", description="Output directory (re-run to resume).")
    budgets: Annotated[list[Budget] | None, _list("budgets")] = Field(
        None, description="λ values; several = one conditioned model.")
    weights: Name | None = Field(None, description="xy, x-only or theta-only.")
    epochs: Annotated[int, Field(ge=0, le=COUNT_MAX)] | None = Field(
        None, description="Attack-phase epochs.")
    pretrain_epochs: Annotated[int, Field(ge=0, le=COUNT_MAX)] | None = Field(
        None, description="Pretraining epochs.")
    train_samples: Count | None = Field(None, description="Training samples per epoch.")
    eval_samples: Count | None = Field(None, description="Held-out evaluation samples.")
    batch_size: Count | None = Field(None, description="Batch size.")
    lr: Annotated[float, Field(ge=0, le=MAX_LR, allow_inf_nan=False)] | None = Field(
        None, description="Learning rate.")
    device: Name | None = Field(None, description="cpu or cuda.")
    threads: Annotated[int, Field(ge=1, le=THREADS_MAX)] | None = Field(
        None, description="torch threads.")
    max_minutes: Annotated[float, Field(gt=0, le=1e7, allow_inf_nan=False)] | None = Field(
        None, description="Stop after this much training.")
    dataset: Name | None = Field(
        None, description="Training data (a registered dataset, e.g. kitti with --dataset-param "
                          "root=...); default: the preset's.")
    dataset_param: Settings = Field({}, description="Dataset KEY=VALUE.")
    strict: bool = Field(False, description="Project displacements onto the λ-balls inside "
                                            "training (beyond the paper).")
    generator_param: Settings = Field(
        {}, description="Generator config KEY=VALUE (e.g. output=bounded, conditioned=false).")
    adv_per_budget: bool | None = Field(None, description="Divide each sample's adversarial loss "
                                                          "by its λ.")
    init: Name | None = Field(None, description="Start from this checkpoint (fine-tuning, e.g. "
                                                "one model per λ).")
    icp_preset: Name | None = Field(
        None, description="Surrogate ICP during training: lidar-train (25 iterations), lidar "
                          "(100), ...")
    icp_backprop: Literal["unrolled", "implicit"] | None = Field(
        None, description="unrolled (dICP, the paper) or implicit (implicit-function gradient "
                          "of the final pose; beyond the paper).")
    alpha: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] | None = Field(
        None, description="Weight of the adversarial loss (eq. 2).")
    sector_iter_param: Settings = Field(
        {}, description="Settings KEY=VALUE of the iterated sector attack that makes a "
                        "prior='sector-iter' model's prior during training (iterations, "
                        "step_size, icp_iterations, icp_nn_reuse, d_max).")
    quiet: bool = Field(False, description="No progress bar.")


# -- icpbench object-study ------------------------------------------------------------------------
class ObjectStudyOptions(Options):
    """The options of ``icpbench object-study``."""

    model: Settings = Field(description="NAME=CHECKPOINT, repeatable.")
    budget: Annotated[float, Field(gt=0, le=S.BUDGET_MAX, allow_inf_nan=False)] = Field(
        0.05, description="Budget (normalised units).")
    objects: Annotated[int, Field(ge=1, le=100_000)] = Field(
        24, description="Held-out objects in the table.")
    figure_objects: Annotated[int, Field(ge=1, le=100_000)] = Field(
        4, description="Objects shown in the figure (at most --objects).")
    out: OutFolder = Field("runs/object-study", description="Output directory.")
    soft_bound: bool = Field(False, description="Also run each model unprojected (the paper's "
                                                "soft bound; may exceed the budget).")

    @model_validator(mode="after")
    def _figure_within_table(self) -> ObjectStudyOptions:
        if self.figure_objects > self.objects:
            raise _Across("figure_objects", f"must be between 1 and --objects ({self.objects}), "
                                            f"got {self.figure_objects}")
        return self


#: Every command's option model, by command name.
COMMANDS: dict[str, type[Options]] = {
    "run": RunOptions, "run (output)": RunCommandOptions, "leaderboard": LeaderboardOptions,
    "map": MapOptions, "validate-map": ValidateMapOptions, "train": TrainOptions,
    "object-study": ObjectStudyOptions,
}

__all__ = ["COMMANDS", "MAX_LR", "LeaderboardOptions", "MapOptions", "ObjectStudyOptions",
           "Options", "OutFolder", "RunCommandOptions", "RunOptions", "TrainOptions",
           "ValidateMapOptions", "must"]
