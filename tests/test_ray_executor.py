"""Determinism and the Ray executor.

* the same command with the same seed writes the same results file, row for row (wall-time columns
  aside), and another seed does not;
* on a local Ray cluster, ``--executor ray`` writes exactly the local executor's file (same rows, same
  order); a run started locally can be finished on Ray; a plugin crashing inside a Ray worker becomes
  error rows, and icpbench's own errors reach the driver unwrapped;
* the executor preserves item order even when later items finish first.

The Ray tests are skipped when Ray is not installed (``pip install 'icpbench[ray]'``).
"""

import csv
import io
import os
import subprocess
import sys
import textwrap
import time

import pytest
import torch

from icpbench.attacks.uniform import UniformTranslationAttack
from icpbench.core import registry
from icpbench.core.errors import InputError, PluginUnavailableError
from icpbench.harness.executors import LocalExecutor, RayExecutor, WorkItem, check_executor, get_executor
from icpbench.harness.results import RESULTS_FILE, TIMING_COLUMNS, load_results, read_manifest
from icpbench.harness.runner import RunConfig, run

torch.set_num_threads(1)

GRID = ["--dataset", "synthetic", "--attacks", "none,uniform,pgd", "--targets", "p2plane,open3d",
        "--budgets", "0.5,1", "--samples", "2", "--attack-param", "pgd.steps=2",
        "--dataset-param", "n_samples=2", "--quiet"]


def _cfg(**kw) -> RunConfig:
    base = dict(dataset="synthetic", attacks=["none", "uniform", "normal"],
                targets=["p2plane", "open3d"], budgets=[0.5, 1.0], samples=6, batch_size=2,
                dataset_params={"n_samples": 6},
                target_params={"p2plane": {"max_iterations": 30}, "open3d": {"max_iterations": 30}})
    cfg = {**base, **kw}  # settings only for the targets in the run (others are refused)
    cfg["target_params"] = {t: p for t, p in cfg["target_params"].items() if t in cfg["targets"]}
    return RunConfig(**cfg)


def _rows_without_timing(out_dir) -> list[tuple]:
    """The results file as a list of rows in file order, wall-time columns blanked."""
    text = (out_dir / RESULTS_FILE).read_text()
    reader = csv.DictReader(io.StringIO(text))
    return [tuple("" if k in TIMING_COLUMNS else v for k, v in row.items()) for row in reader]


def _cli_run(out, *extra):
    subprocess.run([sys.executable, "-m", "icpbench.cli", "run", *GRID, *extra, "--out", str(out)],
                   check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
                   timeout=600)


@pytest.mark.slow
def test_same_command_same_results_file(tmp_path):
    _cli_run(tmp_path / "a")
    _cli_run(tmp_path / "b")
    a, b = _rows_without_timing(tmp_path / "a"), _rows_without_timing(tmp_path / "b")
    assert len(a) == 2 * 3 * 2 * 2
    assert a == b  # identical, in the same order
    df = load_results(tmp_path / "a")
    assert (df["status"] != "error").all(), df["error"].unique()
    assert df["attack_time_s"].gt(0).all()  # timing columns are real, just not compared
    # the comparison has teeth: another attack seed moves the random attacks
    _cli_run(tmp_path / "c", "--seed", "1")
    c = _rows_without_timing(tmp_path / "c")
    assert c != a
    dc = load_results(tmp_path / "c")
    same_none = (dc[dc.attack == "none"]["trans_err_xy"].to_numpy()
                 == df[df.attack == "none"]["trans_err_xy"].to_numpy())
    assert same_none.all()  # ... but not the clean scans


def test_executor_names():
    assert check_executor("local") == "local"
    assert isinstance(get_executor("local"), LocalExecutor)
    with pytest.raises(InputError, match="unknown executor 'dask'; valid executors: local, processes, ray"):
        check_executor("dask")
    with pytest.raises(InputError, match="unknown executor"):
        _cfg(executor="dask").validate()


def test_missing_ray_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` fail
    with pytest.raises(PluginUnavailableError, match=r"pip install 'icpbench\[ray\]'"):
        check_executor("ray")
    with pytest.raises(PluginUnavailableError, match="ray executor needs Ray"):
        _cfg(executor="ray").validate()


# -- Ray -------------------------------------------------------------------------------------------
PLUGIN = textwrap.dedent('''
    """Plugins for the Ray tests: imported by every Ray worker through ICPBENCH_PLUGINS."""
    import numpy as np

    from icpbench.core import registry
    from icpbench.attacks.base import Attack
    from icpbench.datasets.synthetic import SyntheticSceneDataset


    class CrashingAttack(Attack):
        name = "ray-test-crash"

        def _perturb(self, batch, budget_m, *, surrogate, generator):
            raise RuntimeError("boom inside a ray worker")


    class BadSampleDataset(SyntheticSceneDataset):
        """The synthetic scene whose sample 3 has a NaN scan point."""

        name = "ray-test-bad"

        def __getitem__(self, i):
            s = super().__getitem__(i)
            if i == 3:
                scan = s.scan.copy()
                scan[0] = np.nan
                s = type(s)(s.id, scan, s.map, s.map_normals, s.T_gt, s.T_init, s.meta)
            return s


    if "ray-test-crash" not in registry.attacks.names():
        registry.attacks.register("ray-test-crash", CrashingAttack)
        registry.datasets.register("ray-test-bad", BadSampleDataset)
''')


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory):
    """A local 2-CPU Ray cluster whose workers import the test plugins (and the same cache)."""
    ray = pytest.importorskip("ray")
    plugin_dir = tmp_path_factory.mktemp("ray-plugins")
    (plugin_dir / "icpbench_ray_test_plugins.py").write_text(PLUGIN)
    saved = {k: os.environ.get(k) for k in ("PYTHONPATH", "ICPBENCH_PLUGINS")}
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(plugin_dir), saved["PYTHONPATH"]]))
    os.environ["ICPBENCH_PLUGINS"] = "icpbench_ray_test_plugins"
    sys.path.insert(0, str(plugin_dir))
    try:
        ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="ERROR",
                 log_to_driver=False)  # always a new cluster, whatever RAY_ADDRESS says
    finally:  # workers inherit the environment from here on; the test process gets its own back
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    import icpbench_ray_test_plugins  # noqa: F401  (registers the plugins in this process)

    yield ray
    ray.shutdown()
    registry.attacks.unregister("ray-test-crash")
    registry.datasets.unregister("ray-test-bad")
    sys.path.remove(str(plugin_dir))


@pytest.fixture(scope="module")
def local_reference(tmp_path_factory):
    """The grid of :func:`_cfg` run by the local executor."""
    out = tmp_path_factory.mktemp("local")
    run(_cfg(), out, progress=False)
    return out


@pytest.mark.slow
def test_ray_results_equal_local_results(ray_cluster, local_reference, tmp_path):
    run(_cfg(executor="ray"), tmp_path, progress=False)
    local, on_ray = _rows_without_timing(local_reference), _rows_without_timing(tmp_path)
    assert len(local) == 6 * 3 * 2 * 2
    assert on_ray == local  # same rows, same order
    assert load_results(local_reference)["trans_err_xy"].nunique() > 30  # not vacuous
    m = read_manifest(tmp_path)
    assert m["execution"]["executor"] == "ray" and m["execution"]["workers"] == 2
    assert read_manifest(local_reference)["execution"] == {"executor": "local"}


@pytest.mark.slow
def test_resume_a_local_run_on_ray(ray_cluster, local_reference, tmp_path):
    class Stop(Exception):
        pass

    def stop_after(k):
        if k == 3:
            raise Stop

    with pytest.raises(Stop):
        run(_cfg(), tmp_path / "r", progress=False, on_unit=stop_after)
    assert len(load_results(tmp_path / "r")) == 3 * 2 * 2  # 3 units of 2 samples x 2 targets
    run(_cfg(executor="ray"), tmp_path / "r", progress=False)  # same config, other executor
    resumed = sorted(_rows_without_timing(tmp_path / "r"))
    assert resumed == sorted(_rows_without_timing(local_reference))
    assert len(resumed) == len(set(resumed)) == 6 * 3 * 2 * 2


@pytest.mark.slow
def test_crash_inside_a_ray_worker_becomes_error_rows(ray_cluster, tmp_path):
    cfg = _cfg(attacks=["ray-test-crash", "uniform"], targets=["p2plane"], executor="ray")
    run(cfg, tmp_path, progress=False)
    df = load_results(tmp_path)
    bad = df[df["attack"] == "ray-test-crash"]
    assert len(bad) == 12 and (bad["status"] == "error").all()
    assert bad["error"].str.contains("RuntimeError: boom inside a ray worker").all()
    assert (df[df["attack"] == "uniform"]["status"] == "ok").all()


@pytest.mark.slow
def test_input_error_in_a_ray_worker_reaches_the_driver_unwrapped(ray_cluster, tmp_path):
    cfg = _cfg(dataset="ray-test-bad", attacks=["none"], targets=["p2plane"], executor="ray",
               strict_files=True)  # without it the bad sample is skipped (error rows)
    msg = r"^sample 'synthetic/test/000003': scan has 1 point\(s\) with NaN or Inf coordinates$"
    with pytest.raises(InputError, match=msg):
        run(cfg, tmp_path, progress=False)
    # as with the local executor: the batch before the bad sample is written, nothing after it
    ids = load_results(tmp_path)["sample_id"]
    assert len(ids) == 4 and set(ids) == {"synthetic/test/000000", "synthetic/test/000001"}


class _DriverOnly(UniformTranslationAttack):
    name = "driver-only-test-attack"


@pytest.mark.slow
def test_a_plugin_ray_workers_cannot_load_is_a_clear_error(ray_cluster, tmp_path):
    registry.attacks.register("driver-only-test-attack", _DriverOnly)  # in this process only
    try:
        with pytest.raises(InputError, match="a Ray worker could not set up the run: unknown attack "
                                             "'driver-only-test-attack'.*ICPBENCH_PLUGINS"):
            run(_cfg(attacks=["driver-only-test-attack"], executor="ray"), tmp_path, progress=False)
    finally:
        registry.attacks.unregister("driver-only-test-attack")


class _SlowFirst:
    """A fake worker: item 0 takes longest, so items finish in reverse order on 2 actors."""

    def run(self, item):
        time.sleep(0.6 if item.start == 0 else 0.05)
        for budget, attack in item.units:
            yield [{"start": item.start, "budget": budget, "attack": attack}]

    def factory(self):
        return _SlowFirst


@pytest.mark.slow
def test_ray_executor_yields_in_item_order(ray_cluster):
    ray_cluster.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    items = [WorkItem(seed=0, start=s, stop=s + 1, units=((1.0, "a"), (2.0, "b")))
             for s in range(4)]
    got = [(it.start, k, rows[0]["attack"])
           for it, k, rows in RayExecutor(num_workers=2).map(_SlowFirst(), items)]
    assert got == [(s, k, a) for s in range(4) for k, a in ((0, "a"), (1, "b"))]
    local = [(it.start, k, rows[0]["attack"]) for it, k, rows in LocalExecutor().map(_SlowFirst(), items)]
    assert local == got
