"""scripts/member_ab.py: a member run alone reproduces the error its board recorded for it, and a
changed setting is run on the same scans."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from icpbench.attacks.ensemble import VALLEY_LINE_STEPS
from icpbench.cli import app


@pytest.fixture(scope="module")
def member_ab(load_script):
    return load_script("member_ab")


def test_a_member_alone_reproduces_its_board_and_runs_the_changed_setting(member_ab, tmp_path):
    board = tmp_path / "board"
    res = CliRunner().invoke(app, [
        "leaderboard", "--samples", "2", "--dataset", "synthetic", "--dataset-param", "n_scan=600",
        "--dataset-param", "n_map=6000", "--budgets", "0.5", "--ensemble-param", "queries=2",
        "--ensemble-param", "pgd_steps=1", "--ensemble-param", "sector_iterations=1",
        "--ensemble-param", "spoof_queries=3", "--ensemble-param", "valley_queries=2",
        "--variants", "p2point", "--quiet", "--out", str(board)])
    assert res.exit_code == 0, res.output
    out = tmp_path / "ab.csv"
    table = member_ab.main(["--board", str(board), "--variant", "p2point", "--member", "valley",
                            "--set", "line_steps=2", "--samples", "2", "--out", str(out)])
    rows = pd.read_csv(out)
    a, b = rows[rows.arm == "A"], rows[rows.arm == "B"]
    assert len(a) == len(b) == 2
    # arm A is the board's own valley: the same error on every scan
    np.testing.assert_allclose(a.err, a.board_err, rtol=1e-9)
    assert table.loc["A", "larger_share"] == 0.0
    # the estimate of the worst case is never below the board's other members nor arm B
    assert (table.worst_estimate >= table.member_mean - 1e-12).all()
    assert np.isclose(table.loc["A", "worst_estimate"], table.loc["A", "board_worst"])
    assert (b.seconds > 0).all() and np.isfinite(b.err).all()
    # --start adds later scans: the second scan alone gives the same rows as in the full A/B
    later = tmp_path / "ab-later.csv"
    member_ab.main(["--board", str(board), "--variant", "p2point", "--member", "valley",
                    "--set", "line_steps=2", "--samples", "1", "--start", "1", "--out", str(later)])
    second = pd.read_csv(later)
    assert len(second) == 2 and set(second.sample_id) == {rows.sample_id.iloc[-1]}
    full = rows.set_index(["arm", "sample_id"]).err
    np.testing.assert_allclose(second.set_index(["arm", "sample_id"]).err,
                               full.loc[list(second.set_index(["arm", "sample_id"]).index)],
                               rtol=1e-12)
    manifest = json.loads(out.with_suffix(".json").read_text())
    assert manifest["settings"]["A"]["line_steps"] == VALLEY_LINE_STEPS
    assert manifest["settings"]["B"]["line_steps"] == 2
    # a board recorded before the ensemble had valley_line_steps ran valley on 8 steps
    run_manifest = board / "runs" / "p2point" / "manifest.json"
    m = json.loads(run_manifest.read_text())
    del m["attacks"]["ensemble"]["valley_line_steps"]
    run_manifest.write_text(json.dumps(m))
    setup, _, _ = member_ab.plan(board, "p2point", "valley", {}, 2)
    assert setup["settings"]["A"]["line_steps"] == 8
    assert "commit" in manifest["git"]
    with pytest.raises(SystemExit, match="--member"):
        member_ab.plan(board, "p2point", "search", {}, 2)
    with pytest.raises(SystemExit, match="unknown --variant"):
        member_ab.plan(board, "bogus", "valley", {}, 2)
