"""Runner: resume after SIGKILL, determinism, failed plugins become rows, manifest contents."""

import json
import os
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest
import torch

from icpbench.attacks.base import Attack
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.harness.results import (
    MANIFEST_FILE,
    RESULTS_FILE,
    ResultsStore,
    load_results,
    read_manifest,
)
from icpbench.harness.runner import RunConfig, run

GRID = ["--dataset", "synthetic", "--attacks", "none,uniform", "--targets", "p2plane",
        "--budgets", "0.5,1", "--samples", "12", "--batch-size", "2", "--quiet"]


def _cli(out, **kw):
    return subprocess.Popen([sys.executable, "-m", "icpbench.cli", "run", *GRID, "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "OMP_NUM_THREADS": "1"}, **kw)


def _data_rows(path):
    if not path.exists():
        return 0
    return max(path.read_text().count("\n") - 1, 0)


def _sorted(df):
    keep = [c for c in df.columns if c not in ("attack_time_s", "icp_time_s")]
    return df[keep].sort_values(["sample_id", "attack", "target", "budget", "seed"]).reset_index(
        drop=True)


@pytest.mark.slow
def test_sigkill_then_resume_equals_uninterrupted(tmp_path):
    ref, killed = tmp_path / "ref", tmp_path / "killed"
    assert _cli(ref).wait(timeout=600) == 0
    p = _cli(killed)
    csv_path = killed / RESULTS_FILE
    deadline = time.time() + 300
    while _data_rows(csv_path) < 4 and p.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    p.send_signal(signal.SIGKILL)
    p.wait()
    n_partial = _data_rows(csv_path)
    full = _data_rows(ref / RESULTS_FILE)
    assert 0 < n_partial < full, (n_partial, full)
    # simulate a torn write on top of the kill: a partial trailing line must be dropped on resume
    with open(csv_path, "a") as f:
        f.write("synthetic/test/000099,none,p2pl")
    assert _cli(killed).wait(timeout=600) == 0
    a, b = load_results(ref), load_results(killed)
    assert len(b) == full == 12 * 2 * 2
    assert not b.duplicated(["sample_id", "attack", "target", "budget", "seed"]).any()
    pd.testing.assert_frame_equal(_sorted(a), _sorted(b))


def test_same_seed_same_results_and_resume_skips(tmp_path):
    cfg = dict(dataset="synthetic", attacks=["none", "uniform", "normal"], targets=["p2plane"],
               budgets=[1.0], samples=4, batch_size=2, dataset_params={"n_samples": 4})
    run(RunConfig(**cfg), tmp_path / "a", progress=False)
    run(RunConfig(**cfg), tmp_path / "b", progress=False)
    pd.testing.assert_frame_equal(_sorted(load_results(tmp_path / "a")),
                                  _sorted(load_results(tmp_path / "b")))
    calls = []
    run(RunConfig(**cfg), tmp_path / "a", progress=False, on_unit=calls.append)
    assert calls == []  # nothing recomputed
    assert len(load_results(tmp_path / "a")) == 4 * 3


def test_manifest_and_config_mismatch(tmp_path):
    cfg = RunConfig(dataset="synthetic", attacks=["uniform"], targets=["p2plane"], budgets=[1.0],
                    samples=2, dataset_params={"n_samples": 2})
    run(cfg, tmp_path, progress=False)
    m = read_manifest(tmp_path)
    assert m["config"]["budgets"] == [1.0] and m["threads"]["torch"] == 1
    assert m["versions"]["torch"].startswith("2.") and "commit" in m["git"]
    assert m["targets"]["p2plane"]["cauchy_c"] == 1.0 and m["completed_rows"] == 2
    with pytest.raises(InputError, match="different configuration"):
        run(RunConfig(dataset="synthetic", attacks=["uniform"], targets=["p2plane"],
                      budgets=[2.0], samples=2, dataset_params={"n_samples": 2}),
            tmp_path, progress=False)


def test_resume_with_more_samples_adds_only_the_new_ones(tmp_path):
    """Growing --samples on resume computes the new samples only and equals a fresh run of the
    larger count; shrinking it is refused (the store would hold rows outside the run)."""
    cfg = dict(dataset="synthetic", attacks=["none", "uniform"], targets=["p2plane"],
               budgets=[1.0], batch_size=2, dataset_params={"n_samples": 6})
    run(RunConfig(samples=2, **cfg), tmp_path / "grown", progress=False)
    calls = []
    run(RunConfig(samples=5, **cfg), tmp_path / "grown", progress=False, on_unit=calls.append)
    assert len(calls) == 2 * 2  # samples 2-3 and 4: two batches x two attacks
    run(RunConfig(samples=5, **cfg), tmp_path / "fresh", progress=False)
    pd.testing.assert_frame_equal(_sorted(load_results(tmp_path / "grown")),
                                  _sorted(load_results(tmp_path / "fresh")))
    assert read_manifest(tmp_path / "grown")["config"]["samples"] == 5
    with pytest.raises(InputError, match="samples: stored 5, now 3"):
        run(RunConfig(samples=3, **cfg), tmp_path / "grown", progress=False)
    calls.clear()
    run(RunConfig(samples=None, **cfg), tmp_path / "grown", progress=False, on_unit=calls.append)
    assert len(calls) == 2 and len(load_results(tmp_path / "grown")) == 6 * 2
    with pytest.raises(InputError, match="samples: stored None, now 6"):
        run(RunConfig(samples=6, **cfg), tmp_path / "grown", progress=False)


def test_resume_with_another_attack_adds_only_its_rows(tmp_path):
    """Adding an attack on resume computes its rows only and equals a fresh run of both; changing
    a stored attack's settings, or dropping an attack, is still refused."""
    cfg = dict(dataset="synthetic", targets=["p2plane"], budgets=[1.0], samples=2, batch_size=2,
               dataset_params={"n_samples": 2})
    run(RunConfig(attacks=["uniform"], **cfg), tmp_path / "grown", progress=False)
    calls = []
    both = RunConfig(attacks=["uniform", "sector-adaptive"],
                     attack_params={"sector-adaptive": {"iterations": 1}}, **cfg)
    run(both, tmp_path / "grown", progress=False, on_unit=calls.append)
    assert len(calls) == 1  # one batch x the added attack
    run(RunConfig(attacks=["uniform", "sector-adaptive"],
                  attack_params={"sector-adaptive": {"iterations": 1}}, **cfg),
        tmp_path / "fresh", progress=False)
    cols = ["sample_id", "attack", "trans_err_xy"]
    pd.testing.assert_frame_equal(_sorted(load_results(tmp_path / "grown"))[cols],
                                  _sorted(load_results(tmp_path / "fresh"))[cols])
    with pytest.raises(InputError, match="attack_params"):
        run(RunConfig(attacks=["uniform", "sector-adaptive"],
                      attack_params={"sector-adaptive": {"iterations": 2}}, **cfg),
            tmp_path / "grown", progress=False)
    with pytest.raises(InputError, match="attacks"):
        run(RunConfig(attacks=["sector-adaptive"],
                      attack_params={"sector-adaptive": {"iterations": 1}}, **cfg),
            tmp_path / "grown", progress=False)


def test_resume_refuses_results_of_a_changed_checkpoint(tmp_path):
    """The manifest stores a hash of each generator checkpoint; resuming after the file changed
    (e.g. a newly shipped model) is refused instead of silently mixing old and new results."""
    from icpbench.learning.checkpoint import save_checkpoint
    from icpbench.learning.network import Generator, generator_config

    ckpt = tmp_path / "g.pt"
    save_checkpoint(Generator(generator_config("objects")), ckpt)
    cfg = RunConfig(dataset="synthetic", attacks=["generator"], targets=["p2plane"],
                    budgets=[1.0], samples=1, dataset_params={"n_samples": 1},
                    attack_params={"generator": {"checkpoint": str(ckpt)}})
    run(cfg, tmp_path / "r", progress=False)
    fp = read_manifest(tmp_path / "r")["fingerprints"]["generator"]
    assert set(fp) == {"1"} and len(fp["1"]) == 16
    run(cfg, tmp_path / "r", progress=False)  # same file: resumes
    torch.manual_seed(1)
    save_checkpoint(Generator(generator_config("objects")), ckpt)  # other weights, same path
    with pytest.raises(InputError, match="other files for attack.*generator"):
        run(cfg, tmp_path / "r", progress=False)


def test_resume_refuses_a_manifest_without_fingerprints(tmp_path):
    """A results folder from before fingerprints were recorded cannot show which checkpoint made
    its generator rows: resuming into it with a generator is refused (it used to be accepted, and
    the rewritten manifest then named the new checkpoint and commit for the old rows); an attack
    without files still resumes."""
    from icpbench.learning.checkpoint import save_checkpoint
    from icpbench.learning.network import Generator, generator_config

    ckpt = tmp_path / "g.pt"
    save_checkpoint(Generator(generator_config("objects")), ckpt)
    for attack, refused in (("uniform", False), ("generator", True)):
        out = tmp_path / attack
        params = {"generator": {"checkpoint": str(ckpt)}} if attack == "generator" else {}
        cfg = RunConfig(dataset="synthetic", attacks=[attack], targets=["p2plane"],
                        budgets=[1.0], samples=1, dataset_params={"n_samples": 1},
                        attack_params=params)
        run(cfg, out, progress=False)
        m = read_manifest(out)
        del m["fingerprints"]  # as written before fingerprints existed
        (out / MANIFEST_FILE).write_text(json.dumps(m))
        if refused:
            with pytest.raises(InputError, match="other files for attack.*generator"):
                run(cfg, out, progress=False)
            assert "fingerprints" not in read_manifest(out)  # left as it was
        else:
            run(cfg, out, progress=False)
            assert read_manifest(out)["completed_rows"] == 1


class _Crashing(Attack):
    name = "crashing-test-attack"

    def _perturb(self, batch, budget_m, *, surrogate, generator):
        raise RuntimeError("boom inside plugin")


def test_crashing_plugin_becomes_failed_rows(tmp_path):
    registry.attacks.register("crashing-test-attack", _Crashing)
    try:
        cfg = RunConfig(dataset="synthetic", attacks=["crashing-test-attack", "uniform"],
                        targets=["p2plane"], budgets=[1.0], samples=2,
                        dataset_params={"n_samples": 2})
        run(cfg, tmp_path, progress=False)
    finally:
        registry.attacks.unregister("crashing-test-attack")
    df = load_results(tmp_path)
    bad = df[df["attack"] == "crashing-test-attack"]
    assert len(bad) == 2 and (bad["status"] == "error").all() and not bad["converged"].any()
    assert bad["error"].str.contains("boom inside plugin").all()
    assert (df[df["attack"] == "uniform"]["status"] == "ok").all()


def test_results_store_repairs_torn_line(tmp_path):
    store = ResultsStore(tmp_path)
    row = {"sample_id": "a", "attack": "none", "target": "p2plane", "budget": 1.0, "seed": 0,
           "converged": True, "status": "ok", "meta": {"x": 1}, "extra": {}}
    store.append([row])
    store.append([row])  # duplicate key ignored
    with open(tmp_path / RESULTS_FILE, "a") as f:
        f.write("b,none,p2pl")
    store2 = ResultsStore(tmp_path)
    assert len(store2) == 1
    df = load_results(tmp_path)
    assert list(df["sample_id"]) == ["a"] and df["meta.x"].iloc[0] == 1


def test_uniform_error_equals_budget_on_synthetic(tmp_path):
    cfg = RunConfig(dataset="synthetic", attacks=["none", "uniform"], targets=["p2plane"],
                    budgets=[0.5, 1.0], samples=4, dataset_params={"n_samples": 4})
    run(cfg, tmp_path, progress=False)
    df = load_results(tmp_path)
    for b in (0.5, 1.0):
        u = df[(df["attack"] == "uniform") & (df["budget"] == b)]
        assert u["converged"].all()
        assert abs(u["trans_err_xy"].mean() - b) < 0.1 * b
        assert (u["disp_max"] - b).abs().max() < 1e-9 and (u["frac_over_budget"] == 0).all()
    n = df[df["attack"] == "none"]
    assert n["trans_err_xy"].max() < 0.05 and (n["disp_max"] == 0).all()
    assert torch.get_num_threads() == 1


def test_git_dirty_ignores_output_folders(monkeypatch):
    import subprocess

    from icpbench.harness import runner as rmod

    def fake(status):
        def run(args, **kw):
            out = "abc123\n" if args[1] == "rev-parse" else status
            return subprocess.CompletedProcess(args, 0, stdout=out, stderr="")
        return run

    monkeypatch.setattr(rmod.subprocess, "run", fake(" M results/table1.md\n M runs/x/a.csv\n"))
    info = rmod.git_commit()
    assert info["commit"] == "abc123" and info["dirty"] is False
    assert info["dirty_paths"] == ["results/table1.md", "runs/x/a.csv"]
    monkeypatch.setattr(rmod.subprocess, "run", fake(" M results/table1.md\n M icpbench/core/se3.py\n"))
    assert rmod.git_commit()["dirty"] is True
