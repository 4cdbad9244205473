"""Executors: where the runner's units of work are computed.

The runner cuts the evaluation grid into *work items*: one batch of samples under one attack seed,
with the (budget, attack) units of that batch that the results store still lacks, in grid order.
A *worker* (:class:`icpbench.harness.runner.GridWorker`, built from the run's configuration: dataset,
targets, surrogate, attacks and their caches) turns a work item into one list of result rows per
unit. An executor decides only where workers live; every row is computed by the same code from the
same seeds, and the driver appends rows to the results store itself, in item order, so the results
file does not depend on the executor (wall-time columns aside):

* ``local`` (default, no dependency): one worker in this process; items one after another.
* ``processes``: a pool of worker processes on this machine (the standard library's
  ``concurrent.futures``; no dependency), one worker each, fed one *sample* at a time: a batch is
  cut into single-sample items (a sample's rows do not depend on its batch, up to floating-point
  rounding: a batch of one sums its products in another order) and its rows are put back in the
  local executor's order, so a short run of a few batches still uses every core. A worker sends a
  sample's rows back unit by unit, so each unit is written once every sample of its batch has it.
  Workers: ``ICPBENCH_WORKERS`` if set, else the machine's CPUs divided by the torch threads.
* ``ray``: a pool of Ray actors (Moritz et al., "Ray: A Distributed Framework for Emerging AI
  Applications", OSDI 2018), each holding its own worker, on the Ray cluster this process connects to
  (``RAY_ADDRESS``, else a running local cluster, else a new one on this machine). Work items are
  handed to idle actors; finished items come back to the driver, which writes them in the order of
  the grid. Workers never touch the results directory, so the cluster needs no shared filesystem;
  it does need icpbench (same version) and any data folders or checkpoints named in the
  configuration on every node. Ray is imported only when this executor is used
  (``pip install 'icpbench[ray]'``).

A killed driver loses at most the items in flight (they are recomputed on resume); an item that a
plugin crashes inside is already turned into error rows by the worker.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import queue
import signal
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

from icpbench.core.errors import IcpbenchError, InputError, PluginUnavailableError
from icpbench.harness.results import BAD_INPUT

Row = dict[str, Any]

#: Seconds the process executor waits on its queue before it checks its workers.
POLL_S = 0.5
#: Seconds after every awaited worker ended without its rows arriving before that is an error.
LOST_AFTER_S = 30.0

#: Executors by name (``icpbench run --executor NAME``).
EXECUTORS: tuple[str, ...] = ("local", "processes", "ray")


@dataclass(frozen=True)
class WorkItem:
    """One batch of one seed and the units still to compute for it.

    Attributes:
        seed: attack seed.
        start, stop: sample indices ``[start, stop)`` of the batch in the dataset split.
        units: ``(budget, attack name)`` pairs, in grid order (budgets outer, attacks inner).
    """

    seed: int
    start: int
    stop: int
    units: tuple[tuple[float, str], ...]


class Worker(Protocol):
    """What an executor needs from a worker."""

    def run(self, item: WorkItem) -> Iterator[list[Row]]:
        """Compute ``item``; yield the rows of each unit, in the order of ``item.units``."""
        ...

    def factory(self) -> Callable[[], Worker]:
        """A picklable zero-argument callable that builds an equivalent worker elsewhere."""
        ...


class Executor(ABC):
    """Computes work items and yields their rows in a fixed order."""

    name: ClassVar[str] = ""

    @abstractmethod
    def map(self, worker: Worker, items: Sequence[WorkItem]) -> Iterator[tuple[WorkItem, int, list[Row]]]:
        """Yield ``(item, unit index, rows)`` for every unit of every item, in the order of
        ``items`` and of each item's units, whatever order they were computed in.

        Args:
            worker: a worker built in this process (the local executor uses it; others rebuild
                equivalent workers from ``worker.factory()``).
            items: the work, in grid order.
        """

    def describe(self) -> dict[str, Any]:
        """Recorded in the results manifest."""
        return {"executor": self.name}


class LocalExecutor(Executor):
    """Today's sequential loop: one worker, in this process."""

    name: ClassVar[str] = "local"

    def map(self, worker: Worker, items: Sequence[WorkItem]) -> Iterator[tuple[WorkItem, int, list[Row]]]:
        for item in items:
            for k, rows in enumerate(worker.run(item)):
                yield item, k, rows


class ProcessExecutor(Executor):
    """Single-sample work items on a pool of processes of this machine; rows in grid order.

    Each process builds its own worker once (``worker.factory()``, as a Ray actor does) and then
    computes one sample's units at a time, so the cores stay busy even when the run has fewer
    batches than cores. The rows of a batch's samples are merged back into the order the local
    executor writes (:func:`merge_sample_rows`), so the results file does not depend on the
    executor. Processes are *spawned* (not forked: a forked copy of a process that already ran
    torch's or OpenMP's thread pools can hang), so plugins registered at run time are unknown to
    them, as to Ray workers: install them as a package or name their modules in
    ``ICPBENCH_PLUGINS``.

    Args:
        workers: processes in the pool; default: the CPUs divided by ``threads``, at most one per
            sample of the run.
        threads: torch threads of each worker.
    """

    name: ClassVar[str] = "processes"

    def __init__(self, workers: int | None = None, *, threads: int = 1) -> None:
        if workers is not None and workers < 1:
            raise InputError(f"workers must be >= 1, got {workers}")
        self.workers = workers
        self.threads = max(1, int(threads))
        self._used_workers = 0

    def describe(self) -> dict[str, Any]:
        return {"executor": self.name, "workers": self._used_workers, "threads": self.threads}

    def map(self, worker: Worker, items: Sequence[WorkItem]) -> Iterator[tuple[WorkItem, int, list[Row]]]:
        if not items:
            return
        pieces = [[WorkItem(seed=it.seed, start=i, stop=i + 1, units=it.units)
                   for i in range(it.start, it.stop)] for it in items]
        n_pieces = sum(len(p) for p in pieces)
        n = self.workers or max(1, (os.cpu_count() or 1) // self.threads)
        n = min(n, n_pieces)
        self._used_workers = n
        ctx = multiprocessing.get_context("spawn")
        # each worker sends a sample's rows unit by unit through this queue as soon as a unit is
        # done, so a unit is written when every sample of its batch has it (not when the batch's
        # last unit is done): a long run of costly attacks saves, and shows, its progress
        channel = ctx.Queue()
        pool = ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_process_init,
                                   initargs=(worker.factory(), self.threads, channel))
        try:
            with _stop_signals_held():  # the pool starts its processes in submit()
                futures = [pool.submit(_process_run, (i, s), piece)
                           for i, group in enumerate(pieces) for s, piece in enumerate(group)]
            yield from self._in_order(items, pieces, channel, futures)
        except BaseException:
            # interrupted (Ctrl-C) or failed: stop the scans in flight now rather than wait for
            # them; their rows were not written, so a resumed run computes them again
            # (the pool has no public way to stop a running task: its private process table is
            # read before shutdown() clears it)
            procs = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()
            _reap(procs)
            channel.cancel_join_thread()
            raise
        pool.shutdown(wait=True)
        channel.close()

    def _in_order(self, items: Sequence[WorkItem], pieces: Sequence[Sequence[WorkItem]],
                  channel: Any, futures: Sequence[Future]
                  ) -> Iterator[tuple[WorkItem, int, list[Row]]]:
        """Yield every item's units in grid order, each as soon as all of its samples sent it.

        A sample whose worker raised sends its error after the units it finished (the queue
        delivers one process's messages in the order it sent them), so the error is raised when
        its unit's turn comes, after the rows the local executor would have written first."""
        got: dict[tuple[int, int], dict[int, list[Row]]] = {
            (i, s): {} for i, group in enumerate(pieces) for s in range(len(group))}
        failed: dict[tuple[int, int], BaseException] = {}
        flat = {key: j for j, key in enumerate(got)}  # futures are in the same order
        quiet = 0  # polls in a row that found the queue empty after the awaited samples ended
        for i, item in enumerate(items):
            keys = [(i, s) for s in range(len(pieces[i]))]
            for k in range(len(item.units)):
                while not all(k in got[key] for key in keys):
                    errs = [failed[key] for key in keys if key in failed and k not in got[key]]
                    if errs:
                        raise errs[0]
                    try:
                        key, unit, payload = channel.get(timeout=POLL_S)
                    except queue.Empty:
                        for f in futures:  # a worker process that died sends nothing
                            if f.done() and f.exception() is not None:
                                self._result(f)
                        waited = [futures[flat[key]] for key in keys if k not in got[key]]
                        quiet = quiet + 1 if all(f.done() for f in waited) else 0
                        if quiet * POLL_S > LOST_AFTER_S:  # finished, yet its rows never came
                            raise IcpbenchError("a worker process finished without sending its "
                                                "rows; re-run the same command to resume") from None
                        continue
                    quiet = 0
                    if unit is None:
                        failed[key] = payload
                    else:
                        got[key][unit] = payload
                yield item, k, merge_sample_rows([got[key].pop(k) for key in keys])

    @staticmethod
    def _result(future: Future) -> None:
        try:
            future.result()
        except BrokenProcessPool as exc:
            raise IcpbenchError(f"a worker process died ({exc}); re-run the same command to "
                                "resume") from exc


def merge_sample_rows(per_sample: Sequence[list[Row]]) -> list[Row]:
    """One unit's rows of consecutive single-sample items, in the order one batch of those
    samples gives: the rows of readable samples first, then those of skipped (bad-input)
    samples, each target by target in the order the targets first appear, samples in order.

    Args:
        per_sample: the unit's rows of each sample, in sample order.
    """
    targets: dict[str, int] = {}
    keyed = []
    for s, rows in enumerate(per_sample):
        for r in rows:
            t = targets.setdefault(str(r.get("target")), len(targets))
            bad = str(r.get("error") or "").startswith(BAD_INPUT)
            keyed.append(((bad, t, s), r))
    # targets first seen in a later sample (one whose batch had no readable sample) sort last,
    # which is where a batch puts them too
    return [r for _, r in sorted(keyed, key=lambda kr: kr[0])]


def _reap(procs: Sequence[Any], grace_s: float = 3.0) -> None:
    """Wait up to ``grace_s`` for terminated worker processes to end, then kill the rest, so
    that none outlives the run. (A worker still starting holds SIGTERM back until it is set up,
    :func:`_stop_signals_held`; it usually ends within the grace.)"""
    import time

    deadline = time.monotonic() + grace_s
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
    for proc in procs:
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)


#: The signals that stop a run (Ctrl-C, ``kill``).
STOP_SIGNALS = frozenset({signal.SIGINT, signal.SIGTERM})


@contextmanager
def _stop_signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back from this thread while it starts worker processes.

    A process inherits the signal mask of the thread that starts it, so a Ctrl-C that reaches
    the whole process group while a worker is still importing torch stays pending in that worker
    (which ignores SIGINT and releases SIGTERM once it is set up, :func:`_process_init`) instead
    of printing a KeyboardInterrupt traceback from it. This process receives a signal that came
    meanwhile as soon as the block ends, and stops the pool as for any other."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


_PROCESS_WORKER: Any = None
_PROCESS_ERROR: Exception | None = None
_PROCESS_CHANNEL: Any = None


def _process_init(factory: Callable[[], Worker], threads: int, channel: Any) -> None:
    """Pool initializer: build this process's worker (a failure is kept and sent by each item,
    instead of breaking the pool with no message) and keep the queue its rows go back by."""
    global _PROCESS_WORKER, _PROCESS_ERROR, _PROCESS_CHANNEL
    import torch

    # Ctrl-C reaches the whole process group: only the driver handles it (it stops the pool);
    # SIGTERM (the driver's terminate()) ends this process, also one that came while it started
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    torch.set_num_threads(threads)
    _PROCESS_CHANNEL = channel
    try:
        _PROCESS_WORKER = factory()
    except Exception as exc:
        _PROCESS_ERROR = exc


def _process_run(key: tuple[int, int], item: WorkItem) -> None:
    """Compute one sample's units; send ``(key, k, rows)`` per unit k as it is done, then
    ``(key, None, error)`` if the worker raised."""
    try:
        if _PROCESS_ERROR is not None:
            raise _PROCESS_ERROR
        for k, rows in enumerate(_PROCESS_WORKER.run(item)):
            _PROCESS_CHANNEL.put((key, k, rows))
    except Exception as exc:
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # the queue could not carry it (or the driver rebuild it): its text can
            exc = IcpbenchError(f"{type(exc).__name__}: {exc}")
        _PROCESS_CHANNEL.put((key, None, exc))


class RayExecutor(Executor):
    """Work items on a pool of Ray actors; rows come back to the driver in grid order.

    Args:
        address: Ray cluster address (``"auto"``, ``"ray://head:10001"``, ...). ``None`` follows
            Ray's own rule: ``RAY_ADDRESS`` if set, else a cluster started on this machine with
            ``ray start``, else a new local one (shut down again when the run ends).
        num_workers: actors in the pool; default: the cluster's CPUs divided by ``cpus_per_worker``,
            at most one per work item.
        cpus_per_worker: CPUs Ray reserves for each actor (set it to the run's torch threads).
        max_restarts: times Ray restarts an actor whose process died (the item is then retried; a
            unit is pure, so a retry gives the same rows).
    """

    name: ClassVar[str] = "ray"

    def __init__(self, address: str | None = None, *, num_workers: int | None = None,
                 cpus_per_worker: float = 1.0, max_restarts: int = 1) -> None:
        self.ray = import_ray()
        if num_workers is not None and num_workers < 1:
            raise InputError(f"num_workers must be >= 1, got {num_workers}")
        if not cpus_per_worker > 0:
            raise InputError(f"cpus_per_worker must be > 0, got {cpus_per_worker}")
        self.address = address
        self.num_workers = num_workers
        self.cpus_per_worker = float(cpus_per_worker)
        self.max_restarts = int(max_restarts)
        self._used_workers = 0
        self._cluster: dict[str, Any] = {}

    def describe(self) -> dict[str, Any]:
        return {"executor": self.name, "workers": self._used_workers,
                "cpus_per_worker": self.cpus_per_worker, "cluster": self._cluster}

    def map(self, worker: Worker, items: Sequence[WorkItem]) -> Iterator[tuple[WorkItem, int, list[Row]]]:
        if not items:
            return
        ray = self.ray
        owns = not ray.is_initialized()
        if owns:
            # Ray announces at every start that token authentication (its default for a new
            # local cluster) is on: library noise to an icpbench user, so that one logger is
            # quietened; Ray's other warnings still show
            logging.getLogger("ray._private.authentication.authentication_token_setup").setLevel(
                logging.ERROR)
            ray.init(address=self.address, include_dashboard=False, logging_level="WARNING",
                     log_to_driver=False)
        actors: list[Any] = []
        try:
            resources = ray.cluster_resources()
            self._cluster = {"cpus": resources.get("CPU", 0.0), "nodes": len(ray.nodes())}
            n = self.num_workers or max(1, int(resources.get("CPU", 1.0) // self.cpus_per_worker))
            n = min(n, len(items))
            self._used_workers = n
            actor_cls = _actor_class(ray).options(num_cpus=self.cpus_per_worker,
                                                  max_restarts=self.max_restarts,
                                                  max_task_retries=self.max_restarts)
            factory = worker.factory()
            actors += [actor_cls.remote(factory) for _ in range(n)]
            self._check_started(actors)
            yield from self._ordered(actors, items)
        finally:
            for actor in actors:  # free the cluster's CPUs now, not when the handles are collected
                ray.kill(actor)
            if owns:
                ray.shutdown()

    def _ordered(self, actors: list[Any], items: Sequence[WorkItem]
                 ) -> Iterator[tuple[WorkItem, int, list[Row]]]:
        """Keep every actor busy; yield results strictly in item order. An item that failed raises
        its error when its turn comes, so the rows written before it are those the local executor
        would have written."""
        ray = self.ray
        free = list(actors)
        pending: dict[Any, tuple[int, Any]] = {}  # ref -> (item index, actor)
        done: dict[int, list[list[Row]] | Exception] = {}
        next_submit, next_yield = 0, 0
        while next_yield < len(items):
            while free and next_submit < len(items):
                actor = free.pop()
                pending[actor.run.remote(items[next_submit])] = (next_submit, actor)
                next_submit += 1
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                i, actor = pending.pop(ref)
                try:
                    done[i] = self._get(ref)
                except IcpbenchError as exc:  # raised in turn, after every earlier item's rows
                    done[i] = exc
                free.append(actor)
            while next_yield in done:
                result = done.pop(next_yield)
                if isinstance(result, Exception):
                    raise result
                for k, rows in enumerate(result):
                    yield items[next_yield], k, rows
                next_yield += 1

    def _check_started(self, actors: list[Any]) -> None:
        """Raise the error of an actor that could not build its worker (bad data path on that
        node, a plugin that the workers cannot import, ...)."""
        for err in self.ray.get([a.ready.remote() for a in actors]):
            if err is None:
                continue
            hint = ("; plugins registered at run time (registry.register) are unknown to Ray "
                    "workers: install them as a package or name their modules in ICPBENCH_PLUGINS"
                    if "unknown" in str(err) else "")
            msg = f"a Ray worker could not set up the run: {err}{hint}"
            if isinstance(err, IcpbenchError):
                try:
                    raise type(err)(msg) from err
                except TypeError:  # an error type with another constructor
                    raise IcpbenchError(msg) from err
            raise IcpbenchError(f"{msg} ({type(err).__name__})") from err

    def _get(self, ref: Any) -> list[list[Row]]:
        """``ray.get`` that re-raises icpbench's own errors (bad data, checkpoints) unwrapped."""
        ray = self.ray
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, IcpbenchError):
                raise cause from None
            raise IcpbenchError(f"a Ray worker failed: {_first_line(exc)}; re-run the same "
                                "command to resume") from exc
        except ray.exceptions.RayError as exc:  # actor died (node lost, out of memory, ...)
            raise IcpbenchError(f"a Ray worker was lost ({type(exc).__name__}: {_first_line(exc)}); "
                                "re-run the same command to resume") from exc


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[-1] if text else type(exc).__name__


_ACTOR: Any = None


def _actor_class(ray: Any) -> Any:
    """The Ray actor class (defined lazily so that importing this module never imports Ray)."""
    global _ACTOR
    if _ACTOR is None:

        class GridActor:
            """Holds one worker (dataset, targets, attacks, caches) for the life of the run.

            A failure to build the worker is kept and reported by :meth:`ready` (an exception in
            an actor's constructor would make Ray restart the actor and retry for nothing)."""

            def __init__(self, factory: Callable[[], Worker]) -> None:
                self.worker: Worker | None = None
                self.error: Exception | None = None
                try:
                    self.worker = factory()
                except Exception as exc:
                    self.error = exc

            def ready(self) -> Exception | None:
                return self.error

            def run(self, item: WorkItem) -> list[list[Row]]:
                assert self.worker is not None, "run() on an actor whose worker failed to build"
                return list(self.worker.run(item))

        _ACTOR = ray.remote(GridActor)
    return _ACTOR


def import_ray() -> Any:
    """Import Ray, or raise :class:`PluginUnavailableError` saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise PluginUnavailableError(
            "the ray executor needs Ray: pip install 'icpbench[ray]' (or pip install 'ray>=2.9'); "
            "or use --executor local"
        ) from exc
    return ray


def check_executor(name: str) -> str:
    """Validate an executor name (and that its library imports); return it.

    Raises:
        InputError: unknown name (the message lists the valid ones).
        PluginUnavailableError: ``ray`` without Ray installed.
    """
    if name not in EXECUTORS:
        raise InputError(f"unknown executor {name!r}; valid executors: {', '.join(EXECUTORS)}")
    if name == "ray":
        import_ray()
    return name


def get_executor(name: str, *, threads: int = 1) -> Executor:
    """Build the executor ``name`` for a run whose workers use ``threads`` torch threads each.

    The Ray executor reads ``ICPBENCH_RAY_WORKERS`` (actor count) and the processes executor
    ``ICPBENCH_WORKERS`` (process count) from the environment if set.
    """
    check_executor(name)
    if name == "local":
        return LocalExecutor()
    if name == "processes":
        env = os.environ.get("ICPBENCH_WORKERS")
        try:
            n = int(env) if env else None
        except ValueError:
            raise InputError(f"ICPBENCH_WORKERS must be an integer, got {env!r}") from None
        return ProcessExecutor(n, threads=threads)
    workers = os.environ.get("ICPBENCH_RAY_WORKERS")
    try:
        n = int(workers) if workers else None
    except ValueError:
        raise InputError(f"ICPBENCH_RAY_WORKERS must be an integer, got {workers!r}") from None
    return RayExecutor(num_workers=n, cpus_per_worker=max(1, threads))
