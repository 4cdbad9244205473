"""Plugin registry over entry points.

Built-in attacks, targets, datasets, corruptions and monitors are registered exactly like third-party
plugins: through the entry-point groups ``icpbench.attacks``, ``icpbench.targets``,
``icpbench.datasets``, ``icpbench.corruptions`` and ``icpbench.monitors`` of an installed
distribution. Entry points are loaded lazily, so a plugin whose optional library is missing is
reported as unavailable (with the reason) instead of breaking the rest of the tool.
Plugins can also be registered at run time with :meth:`Registry.register` (tests, notebooks).

Every plugin is checked when it is first loaded: its class must subclass the base of its kind
(:class:`~icpbench.attacks.base.Attack`, :class:`~icpbench.targets.base.Target`,
:class:`~icpbench.datasets.base.Dataset`, :class:`~icpbench.corruptions.base.Corruption`,
:class:`~icpbench.monitors.base.Monitor`) and its ``name`` must equal the key it is registered
under (rows are written under ``cls.name`` and resumed under the key, so a mismatch would break
resume).
User settings of a plugin (``--attack-param NAME.KEY=VALUE`` etc.) are checked against the
settings the class declares (:func:`check_params`) before anything is built.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import os
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any, Literal

from icpbench.core.errors import InputError, PluginUnavailableError


@dataclass
class PluginInfo:
    """What ``icpbench list`` shows about one plugin."""

    kind: str
    name: str
    origin: str
    available: bool
    description: str
    reason: str = ""


class Registry:
    """Name -> plugin class lookup for one plugin kind (lazy, entry-point based)."""

    def __init__(self, kind: str, group: str, base: str) -> None:
        self.kind = kind
        self.group = group
        self.base = base  # "module:Class" of the base class every plugin of this kind subclasses
        self._entry_points: dict[str, EntryPoint] = {}
        self._classes: dict[str, type] = {}
        self._errors: dict[str, str] = {}
        self._discovered = False

    # -- discovery ---------------------------------------------------------------------------
    def discover(self, force: bool = False) -> None:
        """Collect the entry points of the group (does not import them)."""
        if self._discovered and not force:
            return
        for ep in entry_points(group=self.group):
            self._entry_points.setdefault(ep.name, ep)
        self._discovered = True
        import_plugin_modules()  # modules register themselves; failures are kept, not raised

    def register(self, name: str, cls: type | None = None) -> Any:
        """Register ``cls`` under ``name`` (usable as a decorator). Raises on name collisions."""

        def deco(c: type) -> type:
            self.discover()
            if name in self._classes and self._classes[name] is not c:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            self.check_contract(name, c, f"registered at run time as {name!r}")
            self._classes[name] = c
            return c

        return deco(cls) if cls is not None else deco

    def unregister(self, name: str) -> None:
        """Remove a run-time registration (tests)."""
        self._classes.pop(name, None)

    # -- lookup ------------------------------------------------------------------------------
    def names(self) -> list[str]:
        """All known names (available or not), sorted."""
        self.discover()
        return sorted(set(self._entry_points) | set(self._classes))

    def get(self, name: str) -> type:
        """Return the plugin class for ``name``.

        Raises:
            InputError: unknown name (the message lists the valid names).
            PluginUnavailableError: the plugin exists but cannot be imported (reason included).
        """
        self.discover()
        if name in self._classes:
            return self._classes[name]
        if name not in self._entry_points:
            failed = plugin_module_errors()
            note = ("; " + "; ".join(f"{PLUGINS_ENV} module {m!r} did not load ({r})"
                                     for m, r in failed.items())) if failed else ""
            raise InputError(
                f"unknown {self.kind} {name!r}; valid {self.kind}s: {', '.join(self.names())}{note}"
            )
        try:
            cls = self._entry_points[name].load()
        except Exception as exc:  # missing optional dependency, syntax error in a plugin, ...
            reason = f"{type(exc).__name__}: {exc}"
            self._errors[name] = reason
            raise PluginUnavailableError(f"{self.kind} {name!r} cannot be loaded ({reason})") from exc
        self.check_contract(name, cls, f"entry point {name!r} = {self._entry_points[name].value}")
        self._classes[name] = cls
        return cls

    def base_class(self) -> type:
        """The class every plugin of this kind must subclass."""
        module, _, attr = self.base.partition(":")
        return getattr(importlib.import_module(module), attr)

    def check_contract(self, name: str, cls: Any, origin: str) -> None:
        """Raise :class:`InputError` unless ``cls`` subclasses this kind's base class and its
        ``name`` equals the key ``name`` it is registered under."""
        base = self.base_class()
        if not (isinstance(cls, type) and issubclass(cls, base)):
            what = cls.__name__ if isinstance(cls, type) else type(cls).__name__
            raise InputError(f"{self.kind} plugin {origin}: {what} is not a subclass of "
                             f"{base.__module__}.{base.__qualname__}")
        if getattr(cls, "name", None) != name:
            raise InputError(f"{self.kind} plugin {origin}: its class {cls.__name__} has name "
                             f"{getattr(cls, 'name', None)!r}; the name must equal the key {name!r} "
                             "(rows are stored under the name and resumed under the key)")

    def check_params(self, name: str, params: Mapping[str, Any] | None) -> dict[str, Any]:
        """The settings ``params`` of plugin ``name``, checked and coerced (see :func:`check_params`)
        and inside the ranges the class declares in ``param_ranges``."""
        cls = self.get(name)
        return check_params(f"{self.kind} {name!r}", cls.param_types(), params or {},
                            getattr(cls, "param_ranges", None) or {})

    def available(self, name: str) -> tuple[bool, str]:
        """(True, "") if ``name`` loads, else (False, reason)."""
        try:
            self.get(name)
            return True, ""
        except PluginUnavailableError:
            return False, self._errors.get(name, "")
        except InputError as exc:  # a plugin that breaks the contract (wrong base class or name)
            self._errors[name] = str(exc)
            return False, str(exc)

    def info(self) -> list[PluginInfo]:
        """Load every plugin and describe it (for ``icpbench list``)."""
        out = []
        for name in self.names():
            ok, reason = self.available(name)
            ep = self._entry_points.get(name)
            origin = ep.value if ep is not None else "registered at run time"
            desc = ""
            if ok:
                cls = self.get(name)
                desc = (getattr(cls, "description", "") or (cls.__doc__ or "")).strip()
                desc = desc.splitlines()[0] if desc else ""
            out.append(PluginInfo(self.kind, name, origin, ok, desc, reason))
        return out

    def resolve(self, spec: str | list[str]) -> list[str]:
        """Parse ``"all"`` or ``"a,b"`` (or a list) into validated names.

        ``all`` expands to every *available* plugin. Unknown names raise :class:`InputError`.
        """
        if isinstance(spec, str):
            items = [s.strip() for s in spec.split(",") if s.strip()]
        else:
            items = list(spec)
        if not items:
            raise InputError(f"no {self.kind}s given; valid {self.kind}s: {', '.join(self.names())}")
        if items == ["all"]:
            return [n for n in self.names() if self.available(n)[0]]
        for n in items:
            self.get(n)  # raises with the list of valid names
        return items


# -- modules named in ICPBENCH_PLUGINS -------------------------------------------------------------
#: Environment variable naming extra plugin modules (comma-separated) that register themselves.
PLUGINS_ENV = "ICPBENCH_PLUGINS"
_module_errors: dict[str, dict[str, str]] = {}  # env value -> {module: reason}


def import_plugin_modules() -> dict[str, str]:
    """Import every module named in ``$ICPBENCH_PLUGINS`` (once per value of the variable).

    A module that cannot be imported (unknown, or raising while it runs) does not stop anything:
    its reason is kept and returned, ``icpbench list`` shows it, and a lookup of a name that is
    not registered mentions it. Empty entries (``' , '``) are ignored.

    Returns:
        ``{module: reason}`` of the modules that did not load.
    """
    value = os.environ.get(PLUGINS_ENV, "")
    if value in _module_errors:
        return _module_errors[value]
    errors: dict[str, str] = {}
    _module_errors[value] = errors  # before importing: a module may look plugins up itself
    for mod in (m.strip() for m in value.split(",")):
        if not mod:
            continue
        try:
            importlib.import_module(mod)
        except Exception as exc:  # a plugin module's own error, whatever it is
            errors[mod] = f"{type(exc).__name__}: {exc}"
    return errors


def plugin_module_errors() -> dict[str, str]:
    """``{module: reason}`` of the ``$ICPBENCH_PLUGINS`` modules that did not load."""
    return import_plugin_modules()


# -- plugin settings ----------------------------------------------------------------------------
def keyword_params(func: Callable[..., Any], skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """The named parameters of ``func`` (``self``, ``*args``, ``**kwargs`` and ``skip`` left out)
    with their type hints (``Any`` where a hint cannot be resolved)."""
    sig = inspect.signature(func)
    try:
        hints = typing.get_type_hints(func)
    except Exception:  # a hint naming something only imported for type checking
        hints = {}
    return {n: hints.get(n, Any) for n, p in sig.parameters.items()
            if n not in ("self", *skip)
            and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def accepts_extra(func: Callable[..., Any]) -> bool:
    """Whether ``func`` takes ``**kwargs``."""
    return any(p.kind is p.VAR_KEYWORD for p in inspect.signature(func).parameters.values())


@dataclass(frozen=True)
class Range:
    """The valid values of a numeric plugin setting: ``lo <= v <= hi`` (``<`` where open)."""

    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, v: float) -> bool:
        """Whether ``v`` lies in the range."""
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return above and below

    def __str__(self) -> str:
        lo = "" if self.lo == -math.inf else f"{'>' if self.lo_open else '>='} {self.lo:g}"
        hi = "" if self.hi == math.inf else f"{'<' if self.hi_open else '<='} {self.hi:g}"
        return " and ".join(x for x in (lo, hi) if x) or "finite"


def _numbers_in(v: Any, path: str = "") -> typing.Iterator[tuple[str, float]]:
    """``(path, number)`` of every number in ``v``, in lists and mappings at any depth
    (``[1]``, ``.mount_height_m``)."""
    if isinstance(v, bool):
        return
    if isinstance(v, int | float):
        yield path, v
    elif isinstance(v, list | tuple):
        for i, x in enumerate(v):
            yield from _numbers_in(x, f"{path}[{i}]")
    elif isinstance(v, Mapping):
        for k, x in v.items():
            yield from _numbers_in(x, f"{path}.{k}")


def _check_number(owner: str, key: str, v: Any, rng: Range | None) -> None:
    """Every number a plugin setting holds must be finite (also inside lists and mappings; the
    message names its path, ``lidar.mount_height_m``), and inside ``rng`` where declared (the
    setting itself or the items of a list setting)."""
    for path, x in _numbers_in(v):
        where = key + path
        if not math.isfinite(x):
            raise InputError(f"setting {where!r} of {owner} must be a finite number"
                             f"{'' if rng is None else f' ({rng})'}, got {x!r}")
        nested = "." in path or path.count("[") > 1
        if rng is not None and not nested and not rng.contains(x):
            raise InputError(f"setting {where!r} of {owner} must be {rng}, got {x!r}")


def check_ranges(owner: str, values: Mapping[str, Any], ranges: Mapping[str, Range]) -> None:
    """Check the settings in ``values`` that ``ranges`` names (None passes; NaN/Inf never).

    Raises:
        InputError: a number out of its range; the message names the setting and ``owner``.
    """
    for k, rng in ranges.items():
        if values.get(k) is not None:
            _check_number(owner, k, values[k], rng)


def check_params(owner: str, types_: Mapping[str, Any], params: Mapping[str, Any],
                 ranges: Mapping[str, Range] | None = None) -> dict[str, Any]:
    """Check user settings against the settings a plugin declares; return them coerced.

    Args:
        owner: what the settings belong to, for messages (``"attack 'pgd'"``).
        types_: setting name -> type hint (from the plugin's ``param_types()``).
        params: the user's settings; strings that spell a number are turned into numbers where the
            hint asks for one (``"1e-3"`` for a float), numbers into strings where it asks for text.
        ranges: setting name -> :class:`Range` (the plugin's ``param_ranges``). Whatever the
            ranges, a number (or a number in a list) that is NaN or infinite is refused.

    Raises:
        InputError: an unknown setting (the message lists the valid ones), a value of the wrong
            type (``pgd.steps=abc``), or a number that is not finite or out of its range.
    """
    unknown = sorted(set(params) - set(types_))
    if unknown:
        raise InputError(f"unknown setting(s) {', '.join(map(repr, unknown))} for {owner}; valid: "
                         f"{', '.join(sorted(types_)) or '(none)'}")
    out = {}
    for k, v in params.items():
        try:
            out[k] = coerce(v, types_[k])
        except NestedSettingError as exc:
            raise InputError(f"setting '{k}{exc.path}' of {owner} {exc.message}") from exc
        except (TypeError, ValueError) as exc:
            raise InputError(f"setting {k!r} of {owner} must be {describe_type(types_[k])}, "
                             f"got {v!r}") from exc
        _check_number(owner, k, out[k], (ranges or {}).get(k))
    return out


class NestedSettingError(ValueError):
    """A value inside a setting (an item of a list, a field of a mapping) that does not fit.

    Attributes:
        path: where it is, below the setting (``.mount_height_m``, ``[1]``, ``.vfov_deg[0]``).
        message: what is wrong (``must be a number, got 'abc'``, ``is unknown; valid: ...``).
    """

    def __init__(self, path: str, message: str) -> None:
        super().__init__(f"{path} {message}")
        self.path, self.message = path, message

    def under(self, step: str) -> NestedSettingError:
        """The same error seen one level up (``step`` is ``.key`` or ``[i]``)."""
        return NestedSettingError(step + self.path, self.message)


def _coerce_item(value: Any, hint: Any, step: str) -> Any:
    """``value`` (an item of a list or a field of a mapping, at ``step``) checked against
    ``hint``. It is returned as given, except a text that the hint turns into a number or a
    flag: only checked, a nested value keeps its type (an integer stays an integer), so that
    settings recorded before this check existed compare equal.

    Raises:
        NestedSettingError: the value does not fit; the path starts with ``step``.
    """
    try:
        got = coerce(value, hint)
    except NestedSettingError as exc:
        raise exc.under(step) from None
    except (TypeError, ValueError):
        raise NestedSettingError(step, f"must be {describe_type(hint)}, got {value!r}") from None
    return got if isinstance(value, str) else value


def _coerce_items(value: Any, hint: Any) -> list[Any] | tuple[Any, ...]:
    """A list setting whose hint names its items (``list[float]``, ``tuple[float, float]``,
    ``Sequence[int]``), each item checked (:func:`_coerce_item`); ValueError for a value that is
    not a list or, for a fixed-length tuple, has another length."""
    if not isinstance(value, list | tuple):
        raise ValueError("not a list")
    args = typing.get_args(hint)
    if not args:
        return value
    if len(args) == 2 and args[1] is Ellipsis or len(args) == 1:
        item_hints = [args[0]] * len(value)
    else:
        if len(value) != len(args):
            raise ValueError(f"needs {len(args)} values")
        item_hints = list(args)
    return type(value)(_coerce_item(x, h, f"[{i}]") for i, (x, h) in
                       enumerate(zip(value, item_hints, strict=True)))


def _coerce_fields(value: Any, hint: type) -> dict[str, Any]:
    """A mapping setting that overrides fields of the dataclass ``hint`` (lidar-sim's ``lidar``,
    a :class:`~icpbench.datasets.lidar_model.LidarConfig`): every key must be a field, every value
    fit the field's type hint (:func:`_coerce_item`). Fields left out keep the plugin's values."""
    if not isinstance(value, Mapping):
        raise ValueError("not a mapping")
    try:
        hints = typing.get_type_hints(hint)
    except Exception:  # a hint naming something only imported for type checking
        hints = {}
    names = [f.name for f in dataclasses.fields(hint) if f.init]
    for k in value:
        if k not in names:
            raise NestedSettingError(f".{k}", f"is unknown; valid: {', '.join(names)}")
    return {k: _coerce_item(v, hints.get(k, Any), f".{k}") for k, v in value.items()}


_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def coerce(value: Any, hint: Any) -> Any:
    """``value`` as the type hint ``hint`` asks (see :func:`check_params`); ValueError if it cannot be.
    Hints this function does not know (classes, generics) let the value through unchanged."""
    if hint is Any or hint is inspect.Parameter.empty:
        return value
    origin = typing.get_origin(hint)
    if origin is typing.Union or origin is types.UnionType:
        args = typing.get_args(hint)
        if value is None:
            if type(None) in args:
                return None
            raise ValueError("None is not allowed")
        fields_of = [a for a in args if _is_dataclass_type(a)]
        if isinstance(value, Mapping) and fields_of:  # a mapping of (some of) its fields
            return _coerce_fields(value, fields_of[0])
        for a in args:  # an exact match first (``str | list[float]`` keeps a string a string)
            if a is not type(None) and _is_exactly(value, a):
                return value
        inner: NestedSettingError | None = None
        for a in args:
            if a is type(None):
                continue
            try:
                return coerce(value, a)
            except NestedSettingError as exc:  # the right kind of value, a bad item inside
                inner = inner or exc
            except (TypeError, ValueError):
                continue
        if inner is not None:
            raise inner
        raise ValueError(f"{value!r} fits none of the types")
    if _is_dataclass_type(hint):
        return value if isinstance(value, hint) else _coerce_fields(value, hint)
    if origin is Literal:
        if value in typing.get_args(hint):
            return value
        raise ValueError(f"not one of {typing.get_args(hint)}")
    if hint is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in _TRUE + _FALSE:
            return value.strip().lower() in _TRUE
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise ValueError("not a boolean")
    if hint is int:
        if isinstance(value, bool):
            raise ValueError("a boolean is not an integer")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            return int(value.strip())
        raise ValueError("not an integer")
    if hint is float:
        if isinstance(value, bool):
            raise ValueError("a boolean is not a number")
        if isinstance(value, int | float):
            return float(value)
        if isinstance(value, str):
            return float(value.strip())
        raise ValueError("not a number")
    if hint is str:
        if isinstance(value, str):
            return value
        if isinstance(value, int | float) and not isinstance(value, bool):
            return str(value)
        raise ValueError("not text")
    if hint is Path:
        if isinstance(value, str | Path) and str(value):
            return value
        raise ValueError("not a path")
    if origin in (list, tuple) or getattr(origin, "__name__", "") == "Sequence":
        return _coerce_items(value, hint)
    if origin is dict or hint is dict:
        if isinstance(value, dict):
            return value
        raise ValueError("not a mapping")
    if hint in (list, tuple):
        if isinstance(value, list | tuple):
            return value
        raise ValueError("not a list")
    return value


def _is_exactly(value: Any, hint: Any) -> bool:
    if hint in (int, float):
        return isinstance(value, hint) and not isinstance(value, bool)
    if hint in (bool, str, Path, dict, list, tuple):
        return isinstance(value, hint)
    origin = typing.get_origin(hint)
    if origin is Literal:
        return value in typing.get_args(hint)
    if origin is dict:
        return isinstance(value, origin)
    if origin is not None:  # a list of typed items: its items are checked by coerce
        return False
    return isinstance(hint, type) and isinstance(value, hint)


def _is_dataclass_type(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def describe_type(hint: Any) -> str:
    """A type hint in words, for messages (``int | None`` -> ``an integer or None``)."""
    names = {int: "an integer", float: "a number", bool: "true or false", str: "text",
             Path: "a path", type(None): "None"}
    if hint in names:
        return names[hint]
    origin = typing.get_origin(hint)
    if origin is typing.Union or origin is types.UnionType:
        return " or ".join(describe_type(a) for a in typing.get_args(hint))
    if origin is Literal:
        return "one of " + ", ".join(map(repr, typing.get_args(hint)))
    if origin in (list, tuple) or getattr(origin, "__name__", "") == "Sequence":
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        plural = {int: "integers", float: "numbers", bool: "flags (true or false)", str: "texts",
                  Path: "paths"}
        if not args or any(a not in plural for a in args) or len(set(args)) > 1:
            return "a list"
        fixed = origin is tuple and Ellipsis not in typing.get_args(hint) and len(args) > 1
        return f"a list of {len(args)} {plural[args[0]]}" if fixed else f"a list of {plural[args[0]]}"
    if _is_dataclass_type(hint):
        return f"a mapping of {hint.__name__} fields"
    if hint is dict or origin is dict:
        return "a mapping"
    return getattr(hint, "__name__", str(hint))


attacks = Registry("attack", "icpbench.attacks", "icpbench.attacks.base:Attack")
targets = Registry("target", "icpbench.targets", "icpbench.targets.base:Target")
datasets = Registry("dataset", "icpbench.datasets", "icpbench.datasets.base:Dataset")
corruptions = Registry("corruption", "icpbench.corruptions", "icpbench.corruptions.base:Corruption")
monitors = Registry("monitor", "icpbench.monitors", "icpbench.monitors.base:Monitor")
