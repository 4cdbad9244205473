"""Regression tests of the reliability guarantees in docs/reliability.md (data loss, wrong results
without a word, paths built from user text, tracebacks, messages naming the wrong problem). Each
test failed before the change it covers."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.harness.results import RESULTS_FILE
from icpbench.harness.runner import RunConfig, run

torch.set_num_threads(1)
cli = CliRunner()
SYN = dict(dataset="synthetic", targets=["p2plane"], dataset_params={"n_samples": 3, "n_scan": 200,
                                                                      "n_map": 2000})


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run")
    run(RunConfig(**SYN, attacks=["none", "uniform"], budgets=[0.5], samples=2), out,
        progress=False)
    return out


# -- data loss: `table --out` ---------------------------------------------------------------------
def _table(run_dir: Path, out: Path):
    return cli.invoke(app, ["table", str(run_dir), "--reference", "uniform", "--out", str(out)])


def test_table_out_never_overwrites_a_file_it_did_not_write(tiny_run, tmp_path, user_error):
    victim = tmp_path / "generator.pt"
    victim.write_bytes(b"\x80\x02weights")
    user_error(_table(tiny_run, victim), "not a table written by `icpbench table`")
    assert victim.read_bytes() == b"\x80\x02weights"
    new = tmp_path / "t.md"  # a new file, then the table it wrote, may be written
    for _ in range(2):
        res = _table(tiny_run, new)
        assert res.exit_code == 0, res.output
    assert new.read_text().startswith("| Method")


def test_table_out_never_writes_through_a_link(tiny_run, tmp_path, user_error):
    run_dir = tmp_path / "r"
    shutil.copytree(tiny_run, run_dir)
    before = (run_dir / RESULTS_FILE).read_bytes()
    link = tmp_path / "t.md"
    os.symlink(run_dir / RESULTS_FILE, link)
    user_error(_table(run_dir, link), "through the link")
    linked_dir = tmp_path / "alias"
    os.symlink(run_dir, linked_dir)
    user_error(_table(run_dir, linked_dir / RESULTS_FILE), "file of the results folder")
    assert (run_dir / RESULTS_FILE).read_bytes() == before
