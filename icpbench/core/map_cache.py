"""Structures derived from a map, built once per ``MapIndex`` object and dropped with it.

Replicas of black-box ICPs and the one-step cost models derive per-map structures (KISS's thinned
voxel map, GICP covariances) from the batch's :class:`~icpbench.core.mapindex.MapIndex`. A
:class:`PerMapCache` keys them weakly on the map object, so they live as long as the map does, and
pickles empty (weak references do not pickle): a copy sent to another process rebuilds on first use.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from icpbench.core.errors import InputError
from icpbench.core.mapindex import MapIndex

T = TypeVar("T")


class PerMapCache(Generic[T]):
    """A weak ``MapIndex -> T`` cache (module docstring)."""

    def __init__(self) -> None:
        self._items: weakref.WeakKeyDictionary[MapIndex, T] = weakref.WeakKeyDictionary()

    def get(self, m: MapIndex, build: Callable[[MapIndex], T]) -> T:
        """The structure of map ``m``, built by ``build(m)`` on first use.

        Raises:
            InputError: ``m`` is not a ``MapIndex``.
        """
        if not isinstance(m, MapIndex):
            raise InputError(f"maps must be MapIndex objects, got {type(m).__name__}")
        out = self._items.get(m)
        if out is None:
            out = self._items[m] = build(m)
        return out

    def __len__(self) -> int:
        return len(self._items)

    def __getstate__(self) -> dict[str, Any]:
        return {}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self._items = weakref.WeakKeyDictionary()
