"""A small per-sample cache of ICP results, so that one forward pass is never computed twice.

In one run the same adversarial scan is often registered twice with the same ICP settings: the
``p2plane`` evaluation of the generator's output and the first step of ``generator-refine`` from
it; the refinement's best iterate and its evaluation; the sector attack's output and the first
iterate of ``sector-iter``. A forward pass (up to 100 iterations, each a KD-tree query of every
point) costs about as much as a whole cheap attack, so :func:`icpbench.targets.icp.icp` keeps the
result of each sample here and takes it back when the same sample comes again. The black-box
libraries' registrations (:class:`~icpbench.targets.blackbox.BlackBoxTarget`, their ``OneResult``)
are kept here too: a row registers the ensemble's best scan, which the attack's query registered
already (on small_gicp's GICP, ``unseen`` board, 0.9 s of its 37 s per scan).

A key holds everything that decides a forward pass: the ICP settings except ``backprop`` (the
implicit-gradient mode runs the very same iterations, its pose has their value), the mode, the
scan's bytes and dtype, the initial pose's bytes and the map object (the entry keeps a reference
to the map, so its ``id`` cannot be reused while the entry lives). Samples of a batch are
independent (a converged sample is frozen), so a sample's result does not depend on the batch it
was computed in. Only exact correspondence searches are cached (``nn_reuse_m = 0``). The cache is
per process, least recently used first out, and :func:`disabled` turns it off (tests compare
both).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

#: Entries kept (each a few hundred bytes plus a reference to its map).
CAPACITY = 512

_lock = threading.Lock()
_entries: OrderedDict[tuple, tuple[Any, Any]] = OrderedDict()  # (map, SampleResult / OneResult)
_enabled = [True]


@dataclass(frozen=True)
class SampleResult:
    """The result of one sample's forward pass.

    Attributes:
        R: (3, 3) final rotation, scan to map; t: (3,) final translation (metres); both detached,
            in the scan's dtype.
        converged: the increment fell below the tolerance (before the health check).
        iterations: iterations used.
        n_inliers: correspondences within the gate at the last iteration.
        H_last: (6, 6) the last normal-equation matrix (for the health check).
    """

    R: torch.Tensor
    t: torch.Tensor
    converged: bool
    iterations: int
    n_inliers: int
    H_last: torch.Tensor


def sample_key(settings: tuple, scan: torch.Tensor | np.ndarray, T_init: torch.Tensor | np.ndarray,
               map_obj: Any) -> tuple:
    """The cache key of one sample: ``settings`` (hashable: the ICP settings without ``backprop``
    and the mode; a black box's class and settings), the scan (N, 3) and initial pose (4, 4) by
    content, the map by identity."""
    h = hashlib.blake2b(digest_size=16)
    for x in (scan, T_init):
        a = np.ascontiguousarray(x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else x)
        h.update(str(a.dtype).encode())
        h.update(a.tobytes())
    return (settings, h.hexdigest(), id(map_obj))


def get(key: tuple) -> Any:
    """The cached result of ``key``, or None (always None while disabled)."""
    if not _enabled[0]:
        return None
    with _lock:
        entry = _entries.get(key)
        if entry is None:
            return None
        _entries.move_to_end(key)
        return entry[1]


def put(key: tuple, map_obj: Any, result: Any) -> None:
    """Keep ``result`` for ``key`` (and a reference to its map); the oldest entry leaves when full."""
    if not _enabled[0]:
        return
    with _lock:
        _entries[key] = (map_obj, result)
        _entries.move_to_end(key)
        while len(_entries) > CAPACITY:
            _entries.popitem(last=False)


def clear() -> None:
    """Forget every entry."""
    with _lock:
        _entries.clear()


def size() -> int:
    """Entries held."""
    return len(_entries)


@contextmanager
def disabled() -> Iterator[None]:
    """Run the enclosed code without the cache (nothing is read or written)."""
    old = _enabled[0]
    _enabled[0] = False
    try:
        yield
    finally:
        _enabled[0] = old
