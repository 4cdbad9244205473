"""``icpbench leaderboard``: a small board runs end to end, parses, ranks and resumes."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core.errors import InputError
from icpbench.harness.leaderboard import LeaderboardConfig, Variant

runner = CliRunner()
ARGS = ["leaderboard", "--samples", "2", "--dataset", "synthetic", "--dataset-param", "n_scan=600",
        "--dataset-param", "n_map=6000", "--budgets", "0.5,1", "--ensemble-param", "queries=2",
        "--ensemble-param", "pgd_steps=1", "--ensemble-param", "sector_iterations=1",
        "--variants", "p2plane (Cauchy),p2point,kiss-icp", "--quiet"]


def test_small_board_runs_parses_ranks_and_resumes(tmp_path):
    out = tmp_path / "board"
    res = runner.invoke(app, [*ARGS, "--out", str(out)])
    assert res.exit_code == 0, res.output
    board = pd.read_csv(out / "leaderboard.csv")
    assert set(board.variant) == {"p2plane (Cauchy)", "p2point", "kiss-icp"}
    assert sorted(board.budget.unique()) == [0.5, 1.0]
    assert (board.scans == 2).all()
    # the ensemble is never below its uniform member, and amplification = mean error / lambda
    assert (board.worst_mean >= board.uniform_mean - 1e-9).all()
    np.testing.assert_allclose(board.amplification, board.worst_mean / board.budget, rtol=1e-5)
    # ranked by amplification at the middle budget (1 m), most robust first
    mid = board[board.budget == 1.0]
    assert list(mid.amplification) == sorted(mid.amplification)
    # the Markdown lists the variants in that order; every scan's winner is counted
    md = (out / "leaderboard.md").read_text()
    ranked = re.findall(r"^\| (\d+) \| ([^|]+) \|", md, flags=re.M)
    assert [v.strip() for _, v in ranked] == list(mid.variant)
    won = board[[c for c in board if c.startswith("won_")]].sum(axis=1)
    assert (won == board.scans).all()
    assert (out / "leaderboard.png").stat().st_size > 10_000
    assert (out / "manifest.json").is_file()
    # a second call resumes: same board, nothing recomputed
    mtime = (out / "runs" / "p2point" / "results.csv").stat().st_mtime_ns
    res = runner.invoke(app, [*ARGS, "--out", str(out)])
    assert res.exit_code == 0, res.output
    pd.testing.assert_frame_equal(pd.read_csv(out / "leaderboard.csv"), board)
    assert (out / "runs" / "p2point" / "results.csv").stat().st_mtime_ns == mtime


def test_unknown_variant_or_target_is_refused_with_the_valid_names():
    with pytest.raises(InputError, match="valid: p2plane"):
        LeaderboardConfig(variants=["p2plane (quantum)"]).resolve()
    with pytest.raises(InputError):
        LeaderboardConfig(extra_targets=["no-such-icp"]).resolve()
    assert Variant("a/b (c)", "p2plane").slug == "a-b-c"
