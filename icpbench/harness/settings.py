"""Type and range checks of the fields of a run configuration read from a file.

``icpbench run --config FILE`` must accept exactly what the command-line flags accept: a flag is
parsed by the CLI (``--budgets 1,5`` is a list of numbers, ``--strict`` a boolean), a config file by
YAML, whose values may have any type. :func:`check_run_fields` checks each field of such a mapping,
turns the spellings the flags accept (``budgets: "1,5"``, ``seeds: 3``) into the field's type, and
refuses anything else with a message naming the file and the field.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from icpbench.core.errors import InputError

#: Seeds are stored in the results CSV and read back as 64-bit integers.
SEED_MIN, SEED_MAX = -(2**63), 2**63 - 1


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


class _Bad(ValueError):
    """A field value that does not fit (the text says what it must be)."""


def _text(v: Any) -> str:
    if not isinstance(v, str) or not v.strip():
        raise _Bad("a non-empty name")
    return v


def _optional_text(v: Any) -> str | None:
    return None if v is None else _text(v)


def _names(v: Any) -> str | list[str]:
    """``"all"``, ``"a,b"`` (as the flag) or a non-empty list of names."""
    if isinstance(v, str) and v.strip():
        return v
    if isinstance(v, list) and v and all(isinstance(x, str) and x.strip() for x in v):
        return v
    raise _Bad("a comma-separated text of names or a non-empty list of names")


def _split(text: str, conv: Callable[[str], Any], what: str) -> list[Any]:
    """A comma-separated text parsed as the CLI parses ``--budgets`` and ``--seed``."""
    try:
        return [conv(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise _Bad(what) from None


def _numbers(v: Any) -> list[float] | None:
    """A number, ``"1,5"`` (as ``--budgets``) or a non-empty list of numbers; None = default."""
    what = "a number, a comma-separated text of numbers (as --budgets) or a list of numbers"
    if v is None:
        return None
    if _is_number(v):
        return [float(v)]
    if isinstance(v, str):
        out = _split(v, float, what)
    elif isinstance(v, list) and all(_is_number(x) for x in v):
        out = [float(x) for x in v]
    else:
        raise _Bad(what)
    if not out:
        raise _Bad(what + " (it holds none)")
    return out


def seed_ok(s: Any) -> bool:
    """Whether ``s`` is an integer the results store can hold as a seed."""
    return _is_int(s) and SEED_MIN <= s <= SEED_MAX


def _seeds(v: Any) -> list[int]:
    what = (f"an integer, a comma-separated text of integers (as --seed) or a non-empty list of "
            f"integers, each from {SEED_MIN} to {SEED_MAX}")
    if _is_int(v):
        out = [v]
    elif isinstance(v, str):
        out = _split(v, int, what)
    elif isinstance(v, list) and all(_is_int(x) for x in v):
        out = list(v)
    else:
        raise _Bad(what)
    if not out or not all(seed_ok(s) for s in out):
        raise _Bad(what)
    return out


def _int_at_least(lo: int, optional: bool = False) -> Callable[[Any], int | None]:
    def check(v: Any) -> int | None:
        if v is None and optional:
            return None
        if not _is_int(v) or v < lo or v > SEED_MAX:
            raise _Bad(f"an integer from {lo} to {SEED_MAX}" + (" or null (all)" if optional else ""))
        return v
    return check


def _flag(v: Any) -> bool:
    if not isinstance(v, bool):
        raise _Bad("true or false")
    return v


def _mapping(v: Any) -> dict[str, Any]:
    if v is None:
        return {}
    if not isinstance(v, Mapping) or not all(isinstance(k, str) for k in v):
        raise _Bad("a mapping of settings (KEY: VALUE)")
    return dict(v)


def _nested(v: Any) -> dict[str, dict[str, Any]]:
    if v is None:
        return {}
    if not isinstance(v, Mapping) or not all(
            isinstance(k, str) and isinstance(p, Mapping) and all(isinstance(x, str) for x in p)
            for k, p in v.items()):
        raise _Bad("a mapping of plugin names to mappings of settings (NAME: {KEY: VALUE})")
    return {k: dict(p) for k, p in v.items()}


#: Field -> check (returns the value as the field's type, or raises :class:`_Bad`).
FIELD_CHECKS: dict[str, Callable[[Any], Any]] = {
    "dataset": _text, "surrogate": _text, "split": _text, "executor": _text,
    "icp_preset": _optional_text,
    "attacks": _names, "targets": _names,
    "budgets": _numbers, "seeds": _seeds,
    "samples": _int_at_least(1, optional=True), "batch_size": _int_at_least(1),
    "threads": _int_at_least(1), "dataset_seed": _int_at_least(0),
    "strict": _flag, "strict_files": _flag,
    "dataset_params": _mapping, "attack_params": _nested, "target_params": _nested,
}


def check_run_fields(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The fields of ``data`` checked and converted (see the module docstring).

    Raises:
        InputError: a value of the wrong type or out of range; the message names ``source`` (the
            file) and the field, and says what it must be.
    """
    out = {}
    for k, v in data.items():
        check = FIELD_CHECKS.get(k)
        if check is None:
            out[k] = v
            continue
        try:
            out[k] = check(v)
        except _Bad as exc:
            raise InputError(f"{source}: setting {k!r} must be {exc}, got {v!r}") from None
    return out
