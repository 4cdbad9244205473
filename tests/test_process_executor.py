"""The ``processes`` executor: a pool of local processes fed one sample at a time.

* it writes the local executor's results file (same rows, same order, numbers equal up to
  floating-point rounding: a batch of one sums its products in another order) for a run whose
  batches it cuts into single samples, with a transferred attack and an adaptive one on two
  targets (the per-target order of an adaptive attack's rows is the subtle part);
* a run started locally is finished by it (the executor is not part of the configuration);
* rows of bad-input samples go after the readable ones, as in a batch;
* a worker that cannot be built is a clear error, not a broken pool.
"""

import csv
import io

import pytest
import torch

from icpbench.core.errors import InputError
from icpbench.harness.executors import ProcessExecutor, check_executor, get_executor, merge_sample_rows
from icpbench.harness.results import BAD_INPUT, RESULTS_FILE, TIMING_COLUMNS, load_results, read_manifest
from icpbench.harness.runner import RunConfig, run

torch.set_num_threads(1)


def _cfg(**kw) -> RunConfig:
    base = dict(dataset="synthetic", dataset_params={"n_samples": 5, "n_scan": 600, "n_map": 6000},
                attacks=["none", "uniform", "sector-adaptive"], targets=["p2plane", "p2point"],
                budgets=[0.5], samples=5, batch_size=3, surrogate="self",
                attack_params={"sector-adaptive": {"iterations": 1}},
                target_params={"p2point": {"max_iterations": 60}})
    return RunConfig(**{**base, **kw})


def _rows(out_dir) -> list[tuple]:
    """The results file in file order, wall-time columns blanked, numbers rounded to 9 digits."""
    reader = csv.DictReader(io.StringIO((out_dir / RESULTS_FILE).read_text()))
    return [tuple("" if k in TIMING_COLUMNS else _rounded(v) for k, v in row.items())
            for row in reader]


def _rounded(v: str) -> str:
    try:
        return f"{float(v):.9g}"
    except ValueError:
        return v


@pytest.fixture(scope="module")
def local_reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    run(_cfg(), out, progress=False)
    return out


@pytest.mark.slow
def test_processes_write_the_local_results_file(local_reference, tmp_path, monkeypatch):
    monkeypatch.setenv("ICPBENCH_WORKERS", "2")
    run(_cfg(executor="processes"), tmp_path, progress=False)
    ref = _rows(local_reference)
    assert len(ref) == 5 * 3 * 2
    assert _rows(tmp_path) == ref  # same rows, same order, same numbers to 9 digits
    df = load_results(tmp_path)
    assert (df.status != "error").all()
    # the adaptive attack ran against each target: its rows differ between the targets
    ad = df[df.attack == "sector-adaptive"].set_index(["sample_id", "target"]).trans_err_xy.unstack()
    assert not (ad["p2plane"] == ad["p2point"]).all()
    assert read_manifest(tmp_path)["execution"] == {"executor": "processes", "workers": 2, "threads": 1}


@pytest.mark.slow
def test_a_local_run_is_finished_by_processes(local_reference, tmp_path, monkeypatch):
    monkeypatch.setenv("ICPBENCH_WORKERS", "2")

    def stop_after(n):
        if n == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(_cfg(), tmp_path, progress=False, on_unit=stop_after)
    run(_cfg(executor="processes"), tmp_path, progress=False)
    assert sorted(_rows(tmp_path)) == sorted(_rows(local_reference))


def test_merge_puts_rows_in_batch_order():
    def row(sid, target, bad=False):
        return {"sample_id": sid, "target": target, "error": BAD_INPUT + "x" if bad else ""}

    per_sample = [[row("a", "p"), row("a", "q")],
                  [row("b", "p", True), row("b", "q", True)],
                  [row("c", "p"), row("c", "q")]]
    got = [(r["sample_id"], r["target"]) for r in merge_sample_rows(per_sample)]
    assert got == [("a", "p"), ("c", "p"), ("a", "q"), ("c", "q"), ("b", "p"), ("b", "q")]


def test_worker_count_from_the_environment(monkeypatch):
    assert check_executor("processes") == "processes"
    monkeypatch.setenv("ICPBENCH_WORKERS", "3")
    ex = get_executor("processes", threads=2)
    assert isinstance(ex, ProcessExecutor) and ex.workers == 3 and ex.threads == 2
    monkeypatch.setenv("ICPBENCH_WORKERS", "many")
    with pytest.raises(InputError, match="ICPBENCH_WORKERS must be an integer"):
        get_executor("processes")
    with pytest.raises(InputError, match="workers must be >= 1"):
        ProcessExecutor(0)


def _broken_factory():
    raise InputError("no such data folder: /nowhere")


class _BrokenWorker:
    def factory(self):
        return _broken_factory


def test_a_worker_that_cannot_be_built_is_a_clear_error():
    from icpbench.harness.executors import WorkItem

    items = [WorkItem(seed=0, start=0, stop=2, units=((1.0, "none"),))]
    with pytest.raises(InputError, match="no such data folder"):
        list(ProcessExecutor(1).map(_BrokenWorker(), items))


class _SlowWorker:
    def factory(self):
        return _SlowWorkerImpl


class _SlowWorkerImpl:
    def run(self, item):
        import time

        time.sleep(0 if item.start == 0 else 60)
        yield [{"sample_id": str(item.start), "target": "t", "error": ""}]


def test_an_interrupted_pool_stops_its_scans_at_once():
    import time

    from icpbench.harness.executors import WorkItem

    items = [WorkItem(seed=0, start=0, stop=1, units=((1.0, "none"),)),
             WorkItem(seed=0, start=1, stop=3, units=((1.0, "none"),))]  # 60 s per sample
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        for _ in ProcessExecutor(3).map(_SlowWorker(), items):
            raise KeyboardInterrupt  # Ctrl-C while the slow samples are in flight
    assert time.perf_counter() - t0 < 30  # their processes were stopped, not waited for


class _Picky(Exception):
    """An exception that pickles but cannot be rebuilt from its arguments."""

    def __init__(self, a, b):
        super().__init__(f"{a} and {b}")


def test_an_error_the_queue_cannot_carry_still_reaches_the_driver_as_text():
    import icpbench.harness.executors as ex

    class Boom:
        def run(self, item):
            raise _Picky(1, 2)

    class Channel:
        sent: list = []

        def put(self, msg):
            self.sent.append(msg)

    ex._PROCESS_WORKER, ex._PROCESS_ERROR, ex._PROCESS_CHANNEL = Boom(), None, Channel()
    try:
        ex._process_run((0, 0), None)
    finally:
        ex._PROCESS_WORKER = ex._PROCESS_CHANNEL = None
    key, unit, err = Channel.sent[-1]
    assert key == (0, 0) and unit is None
    assert isinstance(err, ex.IcpbenchError) and "_Picky: 1 and 2" in str(err)
