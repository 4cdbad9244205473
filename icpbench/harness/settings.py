"""Rules shared by the option models of :mod:`icpbench.harness.options`: list fields, budgets and
the ``--config`` path.

A flag is parsed by the CLI (``--budgets 1,5`` is a list of numbers), a config file by YAML, whose
values may have any type. The list fields (:data:`LIST_FIELDS`: attacks, targets, budgets, seeds,
corruptions, severities) are read by one rule wherever they come from (:class:`ListField`, used by
the option models, and :func:`check_list_field`): a single value is a list of one, as the flag
reads it; a comma-separated text is split as the flag splits it; a mapping is refused (never read
as its keys); every item must have the field's type and range, and no item may repeat (severity
levels, a set, are merged). Budgets must moreover be physically sensible and tell apart in the
tables (:func:`check_budgets`). pydantic has no notion of a flag's comma-separated spelling, so
this part is written here; every other check of a field is the model's.
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from icpbench.core.errors import InputError
from icpbench.corruptions.base import SEVERITIES

#: Seeds are stored in the results CSV and read back as 64-bit integers.
SEED_MIN, SEED_MAX = -(2**63), 2**63 - 1

#: The budgets λ a run accepts (metres; normalised units for ``objects``). Below ``BUDGET_MIN`` a
#: displacement is under the 1e-6 tolerance of the displacement audit and under the resolution of
#: float32 coordinates a few metres from the sensor, so the attack could not be told from no attack;
#: above ``BUDGET_MAX`` a point may move farther than any lidar sees (100-200 m) and far beyond the
#: unit objects.
BUDGET_MIN, BUDGET_MAX = 1e-6, 1e3

#: Corruption severity levels.
SEVERITY_MIN, SEVERITY_MAX = min(SEVERITIES), max(SEVERITIES)

#: The flag of ``icpbench run`` that sets each field (named in messages about values not read
#: from a file).
FLAGS: dict[str, str] = {
    "dataset": "--dataset", "surrogate": "--surrogate", "split": "--split", "executor": "--executor",
    "attacks": "--attacks", "targets": "--targets", "budgets": "--budgets", "seeds": "--seed",
    "samples": "--samples", "batch_size": "--batch-size", "threads": "--threads",
    "strict": "--strict", "strict_files": "--strict-files",
    "replica_queries": "--replica-queries", "dataset_params": "--dataset-param",
    "attack_params": "--attack-param", "target_params": "--target-param",
    "corruptions": "--corruptions", "severities": "--severities", "monitors": "--monitors",
    "monitor_params": "--monitor-param", "false_alarm_rate": "--false-alarm-rate",
    "calibration_samples": "--calibration-samples", "monitor_aware": "--monitor-aware",
}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


class _Bad(ValueError):
    """A field value that does not fit (the text says what it must be; ``detail``, where given,
    which part of it does not)."""

    def __init__(self, what: str, detail: str = "") -> None:
        super().__init__(what)
        self.detail = detail


def seed_ok(s: Any) -> bool:
    """Whether ``s`` is an integer the results store can hold as a seed."""
    return _is_int(s) and SEED_MIN <= s <= SEED_MAX


def _show(x: Any) -> str:
    """An item for a message: a number as the tables print it, anything else as its repr."""
    return f"{x:g}" if _is_number(x) else repr(x)


def check_budgets(budgets: list[float]) -> list[float]:
    """``budgets`` (numbers) as floats, each physically sensible, no two alike in the tables.

    Checked: each is a positive finite number (:func:`~icpbench.attacks.base.validate_budget`,
    the rule of every attack), from :data:`BUDGET_MIN` to :data:`BUDGET_MAX` (see there why);
    no budget repeats, and no two print alike in the tables (``λ={b:g}``, 6 significant digits),
    since their columns and rows could not be told apart.

    Raises:
        InputError: the first budget that breaks a rule, and why.
    """
    from icpbench.attacks.base import validate_budget

    out = [validate_budget(b) for b in budgets]
    for b in out:
        if not BUDGET_MIN <= b <= BUDGET_MAX:
            raise InputError(
                f"budget must be at least {BUDGET_MIN:g} and at most {BUDGET_MAX:g} (metres; "
                f"normalised units for objects), got {b!r}: a smaller one is under the resolution "
                "of float32 coordinates and of the displacement audit (1e-6), a larger one moves "
                "points beyond any lidar's range")
    printed: dict[str, float] = {}
    for b in out:
        label = f"{b:g}"
        if label in printed:
            if printed[label] == b:
                raise InputError(f"budget {label} is given twice")
            raise InputError(f"budgets {printed[label]!r} and {b!r} both print as λ={label} in the "
                             "tables, so their results could not be told apart; give budgets that "
                             "differ within 6 significant digits")
        printed[label] = b
    return out


@dataclass(frozen=True)
class ListField:
    """How one list field of a run configuration is read and checked.

    Attributes:
        noun: one item in words (``"budget"``).
        items: the items in words, with their range (``"integers 1..5"``).
        item: checks one item of a list (the value, converted) or raises :class:`_Bad` saying
            what an item must be.
        piece: converts one piece of a comma-separated text, as the flag does (ValueError or
            :class:`_Bad` if it cannot).
        none: what None (YAML ``null``) means: ``"default"`` (None, the field's default is
            resolved later), ``"empty"`` (no items) or ``"refused"``.
        empty_ok: whether a list without items is a valid value.
        repeats: ``"refused"`` (an item given twice is a mistake: two rows would share one key)
            or ``"merged"`` (the items are a set, kept in their first order: a repeat changes
            nothing the run computes).
        whole: further checks of the whole list (raises InputError), e.g. :func:`check_budgets`.
    """

    noun: str
    items: str
    item: Callable[[Any], Any]
    piece: Callable[[str], Any]
    none: str = "refused"
    empty_ok: bool = False
    repeats: str = "refused"
    whole: Callable[[list[Any]], list[Any]] | None = None

    def what(self, flag: str) -> str:
        """What a value must be, in words."""
        return (f"{'a' if self.empty_ok else 'a non-empty'} list of {self.items} (or one of them, "
                f"or a comma-separated text of them as {flag} takes)")

    def _one(self, check: Callable[[Any], Any], x: Any, what: str) -> Any:
        try:
            return check(x)
        except (_Bad, ValueError, TypeError) as exc:
            must = str(exc) if isinstance(exc, _Bad) else "what the flag takes"
            raise _Bad(what, f"{self.noun} must be {must}, got {x!r}") from None

    def check(self, v: Any, flag: str) -> list[Any] | None:
        """``v`` as a list of checked items (None: the default), or :class:`_Bad` saying why not."""
        what = self.what(flag)
        if v is None:
            if self.none == "refused":
                raise _Bad(what, "null is not a list")
            return None if self.none == "default" else []
        if isinstance(v, Mapping):
            raise _Bad(what, "a mapping is not a list")
        if isinstance(v, str):
            out = [self._one(self.piece, x.strip(), what) for x in v.split(",") if x.strip()]
        elif isinstance(v, list | tuple):
            out = [self._one(self.item, x, what) for x in v]
        else:  # one value: a list of one, as the flag reads it
            out = [self._one(self.item, v, what)]
        if not out and not self.empty_ok:
            raise _Bad(what, "it holds none")
        if self.repeats == "merged":
            return list(dict.fromkeys(out))
        for i, x in enumerate(out):
            if x in out[:i]:
                raise _Bad(what, f"{_show(x)} is given twice")
        return out


def _name(v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise _Bad("a non-empty name")
    return v.strip()


def _integer(v: Any) -> int:
    """An integer item (a NumPy integer too, for lists built in code); never a boolean."""
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise _Bad("an integer")
    return int(v)


def _number(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise _Bad("a number")
    return float(v)


def _seed(v: Any) -> int:
    s = _integer(v)
    if not seed_ok(s):
        raise _Bad(f"an integer from {SEED_MIN} to {SEED_MAX}")
    return s


def _severity(v: Any) -> int:
    s = _integer(v)
    if not SEVERITY_MIN <= s <= SEVERITY_MAX:
        raise _Bad(f"an integer {SEVERITY_MIN}..{SEVERITY_MAX}")
    return s


def _from_text(conv: Callable[[str], Any], check: Callable[[Any], Any], must: str
               ) -> Callable[[str], Any]:
    """One piece of a flag's comma-separated text, converted as the CLI converts it (``float``,
    ``int``), then checked as an item of a list."""
    def piece(text: str) -> Any:
        try:
            v = conv(text)
        except ValueError:
            raise _Bad(must) from None
        return check(v)
    return piece


#: The list fields of a run configuration and how each is read and checked.
LIST_FIELDS: dict[str, ListField] = {
    "attacks": ListField("attack", "attack names ('all': every attack that loads)", _name, _name),
    "targets": ListField("target", "target names ('all': every target that loads)", _name, _name),
    "budgets": ListField("budget", f"budgets λ, numbers from {BUDGET_MIN:g} to {BUDGET_MAX:g} "
                         "(metres; normalised units for objects)", _number,
                         _from_text(float, _number, "a number"),
                         none="default", whole=check_budgets),
    "seeds": ListField("seed", f"integers from {SEED_MIN} to {SEED_MAX}", _seed,
                       _from_text(int, _seed, "an integer")),
    "corruptions": ListField("corruption", "corruption names ('all': every corruption that "
                             "loads; an empty list or null: none)", _name, _name, none="empty",
                             empty_ok=True),
    "monitors": ListField("monitor", "monitor names ('all': every monitor that loads; an empty "
                          "list or null: none)", _name, _name, none="empty", empty_ok=True),
    "severities": ListField("severity", f"integers {SEVERITY_MIN}..{SEVERITY_MAX} (corruption "
                            "severity levels; a repeated level counts once)", _severity,
                            _from_text(int, _severity, "an integer"), repeats="merged"),
}


def check_list_field(key: str, v: Any, source: str | None = None) -> list[Any] | None:
    """The list field ``key`` of a run configuration, checked (see the module docstring).

    Args:
        key: a key of :data:`LIST_FIELDS`.
        v: its value (from a file, the flags or code).
        source: the file it was read from, named in messages (None: the flags or code; the
            message then names the flag).

    Raises:
        InputError: a value that is not such a list, an item of the wrong type or out of range,
            an item given twice, or budgets that break :func:`check_budgets`.
    """
    spec, flag = LIST_FIELDS[key], FLAGS[key]
    where = f"{key} ({flag})" if source is None else f"{source}: setting {key!r}"
    try:
        out = spec.check(v, flag)
    except _Bad as exc:
        raise InputError(f"{where} must be {exc}, got {v!r}"
                         + (f" ({exc.detail})" if exc.detail else "")) from None
    if out is not None and spec.whole is not None:
        try:
            out = spec.whole(out)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
    return out


def config_file(path: str | Path) -> Path:
    """``path`` checked to be a file a run configuration can be read from (``--config``).

    A path is classified as precisely as the message needs: missing, a link to something missing,
    a folder (with the ``manifest.json`` to give instead, when it is a results folder), something
    that is not a regular file, or a regular file (a link to one included), which is returned.

    Raises:
        InputError: anything but a regular file, saying which and what to give instead.
    """
    p = Path(path)
    link = f" (a link to {os.readlink(p)})" if p.is_symlink() else ""
    if p.is_symlink() and not p.exists():
        raise InputError(f"config file {p} is a link to {os.readlink(p)}, which does not exist")
    if p.is_dir():
        manifest = p / "manifest.json"
        raise InputError(
            f"config file {p}{link} is a folder; "
            + (f"to repeat the run it holds, give its manifest: --config {manifest}"
               if manifest.is_file() else
               "it holds no manifest.json; give a YAML file of run settings or a run's "
               "manifest.json"))
    if not p.exists():
        raise InputError(f"config file {p} does not exist")
    if not p.is_file():
        raise InputError(f"config file {p}{link} is not a regular file (a pipe, socket or device); "
                         "give a YAML file of run settings or a run's manifest.json")
    return p
