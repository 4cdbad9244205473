"""Process-wide allocator setting for long CPU jobs (training): keep freed memory for reuse.

PyTorch on the CPU has no caching allocator: every tensor is a ``malloc``, and glibc serves blocks
above its mmap threshold (128 KiB, rising to at most 32 MiB) with fresh ``mmap`` pages, which the
kernel must fault in and zero on first touch, then returns them on ``free``. A generator training
step at N = 10,000 allocates hundreds of such buffers (activations of up to 80 MB and their
gradients); on the 2-core VM a new 41 MB buffer cost 20 ms against 4 ms for a copy into an
existing one, and a training step took 1.4x less CPU time with freed memory kept in the heap
(docs/performance.md). :func:`retain_freed_memory` sets glibc's ``M_MMAP_THRESHOLD`` and
``M_TRIM_THRESHOLD`` to their maximum (the same as the environment variables
``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``): the process then keeps its peak
memory instead of returning it, which is what a training process wants and a library should not
impose on every user: :func:`icpbench.learning.training.train` turns it on for its own process
(:func:`retain_for_training`; ``ICPBENCH_KEEP_FREED_MEMORY=0`` turns it off), nothing else does.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MAX = 2**31 - 1  # mallopt takes an int


def retain_freed_memory() -> bool:
    """Make glibc keep freed memory in the process (no mmap per large block, no trimming).

    Returns True if the settings were applied (Linux with glibc), False otherwise (nothing
    changed). Idempotent."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl has no mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(_M_TRIM_THRESHOLD, _MAX)) and bool(mallopt(_M_MMAP_THRESHOLD, _MAX))


#: Environment variable that turns :func:`retain_for_training` off (``0``, ``false``, ``no``,
#: ``off``); any other value or none leaves it on.
KEEP_FREED_MEMORY_ENV = "ICPBENCH_KEEP_FREED_MEMORY"


def retain_for_training() -> bool:
    """What :func:`icpbench.learning.training.train` calls first: :func:`retain_freed_memory`,
    unless the environment variable ``ICPBENCH_KEEP_FREED_MEMORY`` is ``0``/``false``/``no``/``off``
    (for a process that must return memory, e.g. training inside a larger application).

    Measured on the quick-lidar recipe (benchmarks/bench_training.py, docs/performance.md): faster
    in every run, on 1 process and on 2 data-parallel ones. Returns whether the setting was
    applied."""
    if os.environ.get(KEEP_FREED_MEMORY_ENV, "").strip().lower() in ("0", "false", "no", "off"):
        return False
    return retain_freed_memory()
