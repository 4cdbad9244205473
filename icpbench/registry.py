"""Plugin registry over entry points.

Built-in attacks, targets and datasets are registered exactly like third-party plugins: through the
entry-point groups ``icpbench.attacks``, ``icpbench.targets`` and ``icpbench.datasets`` of an installed
distribution. Entry points are loaded lazily, so a plugin whose optional library is missing is
reported as unavailable (with the reason) instead of breaking the rest of the tool.
Plugins can also be registered at run time with :meth:`Registry.register` (tests, notebooks).
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from icpbench.errors import InputError, PluginUnavailableError


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

    def __init__(self, kind: str, group: str) -> None:
        self.kind = kind
        self.group = group
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
        for mod in filter(None, os.environ.get("ICPBENCH_PLUGINS", "").split(",")):
            importlib.import_module(mod.strip())  # modules register themselves
        self._discovered = True

    def register(self, name: str, cls: type | None = None) -> Any:
        """Register ``cls`` under ``name`` (usable as a decorator). Raises on name collisions."""

        def deco(c: type) -> type:
            self.discover()
            if name in self._classes and self._classes[name] is not c:
                raise ValueError(f"{self.kind} {name!r} is already registered")
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
            raise InputError(
                f"unknown {self.kind} {name!r}; valid {self.kind}s: {', '.join(self.names())}"
            )
        try:
            cls = self._entry_points[name].load()
        except Exception as exc:  # missing optional dependency, syntax error in a plugin, ...
            reason = f"{type(exc).__name__}: {exc}"
            self._errors[name] = reason
            raise PluginUnavailableError(f"{self.kind} {name!r} cannot be loaded ({reason})") from exc
        self._classes[name] = cls
        return cls

    def available(self, name: str) -> tuple[bool, str]:
        """(True, "") if ``name`` loads, else (False, reason)."""
        try:
            self.get(name)
            return True, ""
        except PluginUnavailableError:
            return False, self._errors.get(name, "")

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


attacks = Registry("attack", "icpbench.attacks")
targets = Registry("target", "icpbench.targets")
datasets = Registry("dataset", "icpbench.datasets")
