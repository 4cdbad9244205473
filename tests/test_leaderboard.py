"""``icpbench leaderboard``: a small board runs end to end, parses, ranks and resumes."""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core.errors import InputError
from icpbench.harness.leaderboard import LeaderboardConfig, Variant
from icpbench.harness.protocol import STANDARD_VERSION

runner = CliRunner()
ARGS = ["leaderboard", "--samples", "2", "--dataset", "synthetic", "--dataset-param", "n_scan=600",
        "--dataset-param", "n_map=6000", "--budgets", "0.5,1", "--ensemble-param", "queries=2",
        "--ensemble-param", "pgd_steps=1", "--ensemble-param", "sector_iterations=1",
        "--ensemble-param", "spoof_queries=2", "--ensemble-param", "valley_queries=2",
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
    ranked = re.findall(r"^\| (\d+) \| [^|]+ \| ([^|]+) \|", md, flags=re.M)
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
    # bootstrap intervals of the mean and the rank; a board agrees with itself (tau = 1)
    assert (board.worst_lo <= board.worst_mean + 1e-9).all()
    assert (board.worst_mean <= board.worst_hi + 1e-9).all()
    assert ((1 <= board.rank_lo) & (board.rank_hi <= 3)).all()
    assert "rank 95% CI" in md and "95% CI [m]" in md
    res = runner.invoke(app, [*ARGS, "--out", str(out), "--compare-with", str(out)])
    assert res.exit_code == 0, res.output
    assert "Kendall's tau = 1.00 over 3 variants" in (out / "leaderboard.md").read_text()
    res = runner.invoke(app, [*ARGS, "--out", str(out), "--compare-with", str(tmp_path)])
    assert res.exit_code != 0 and "no board there" in res.output


def test_an_added_attack_raises_the_worst_case_and_computes_only_its_own_rows(tmp_path):
    out = tmp_path / "board"
    args = ["leaderboard", "--samples", "2", "--dataset", "synthetic", "--dataset-param",
            "n_scan=600", "--dataset-param", "n_map=6000", "--budgets", "0.5", "--ensemble-param",
            "queries=2", "--ensemble-param", "pgd_steps=1", "--ensemble-param",
            "sector_iterations=1", "--ensemble-param", "members=uniform,sector-adaptive,pgd,search",
            "--variants", "p2point", "--extra-attacks", "", "--quiet", "--out", str(out)]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    before = pd.read_csv(out / "leaderboard.csv")
    rows = pd.read_csv(out / "runs" / "p2point" / "results.csv")
    res = runner.invoke(app, [*args, "--extra-attacks", "spoof,uniform"])  # uniform: no queries
    assert res.exit_code == 0, res.output
    after = pd.read_csv(out / "leaderboard.csv")
    grown = pd.read_csv(out / "runs" / "p2point" / "results.csv")
    # the ensemble's rows are kept as they were; only the spoof rows were computed
    pd.testing.assert_frame_equal(
        grown[~grown.attack.isin(["spoof", "uniform"])].reset_index(drop=True), rows)
    sp = grown[grown.attack == "spoof"].set_index("sample_id").trans_err_xy
    ens = rows[rows.attack == "ensemble"].set_index("sample_id").trans_err_xy
    np.testing.assert_allclose(after.worst_mean, np.maximum(sp, ens.loc[sp.index]).mean(),
                               rtol=1e-5)  # the CSV keeps 6 digits
    np.testing.assert_allclose(after.ensemble_mean, before.worst_mean)
    assert (after.worst_mean >= before.worst_mean).all()
    won = after[[c for c in after if c.startswith("won_")]].sum(axis=1)
    assert (won == after.scans).all() and int(after.won_extra_spoof.iloc[0]) == int((sp > ens).sum())
    assert float(after.worst_mean.iloc[0]) > float(before.worst_mean.iloc[0])  # spoof won a scan
    assert int(after.won_extra_uniform.iloc[0]) == 0  # the ensemble's own uniform member ties it
    assert float(after.queries.iloc[0]) > float(before.queries.iloc[0])
    md = (out / "leaderboard.md").read_text()
    assert "`spoof`" in md and "+ spoof" in md and "ensemble [m]" in md
    # a second extra attack that beats the first: each scan still counts one winner
    res = runner.invoke(app, [*args, "--extra-attacks", "spoof,uniform,valley"])
    assert res.exit_code == 0, res.output
    both = pd.read_csv(out / "leaderboard.csv")
    va = pd.read_csv(out / "runs" / "p2point" / "results.csv")
    va = va[va.attack == "valley"].set_index("sample_id").trans_err_xy.loc[sp.index]
    worst = np.maximum(np.maximum(sp, ens.loc[sp.index]), va)
    np.testing.assert_allclose(both.worst_mean, worst.mean(), rtol=1e-5)
    won = both[[c for c in both if c.startswith("won_")]].sum(axis=1)
    assert (won == both.scans).all()
    assert int(both.won_extra_valley.iloc[0]) == int((va > np.maximum(sp, ens.loc[sp.index])).sum())


def test_unknown_variant_or_target_is_refused_with_the_valid_names():
    with pytest.raises(InputError, match="valid: p2plane"):
        LeaderboardConfig(variants=["p2plane (quantum)"]).resolve()
    with pytest.raises(InputError):
        LeaderboardConfig(extra_targets=["no-such-icp"]).resolve()
    for bad in (["no-such-attack"], ["ensemble"], ["spoof", "spoof"]):
        with pytest.raises(InputError):
            LeaderboardConfig(extra_attacks=bad).resolve()
    assert Variant("a/b (c)", "p2plane").slug == "a-b-c"


def test_a_board_is_resumed_only_under_its_own_protocol_and_never_over_a_run(tmp_path):
    """A changed ensemble setting (or any protocol field) is refused with what differs, before
    anything is computed; so is a board over an `icpbench run` folder or a board recorded without
    a protocol; the same settings resume."""
    out = tmp_path / "board"
    args = ["leaderboard", "--samples", "1", "--dataset", "synthetic", "--dataset-param",
            "n_scan=600", "--dataset-param", "n_map=6000", "--budgets", "0.5", "--ensemble-param",
            "members=uniform,search", "--ensemble-param", "queries=2", "--variants", "p2point",
            "--quiet", "--out", str(out)]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["kind"] == "leaderboard" and manifest["protocol"]["name"] == "custom"
    assert manifest["protocol"]["ensemble"] == {"members": "uniform,search", "queries": 2}
    rows = (out / "runs" / "p2point" / "results.csv").read_text()
    res = runner.invoke(app, [*args[:-2], "--ensemble-param", "queries=3", "--out", str(out)])
    assert res.exit_code != 0
    assert "another protocol" in res.output and "ensemble: stored" in res.output
    assert (out / "runs" / "p2point" / "results.csv").read_text() == rows  # nothing computed
    res = runner.invoke(app, args)  # the same settings resume
    assert res.exit_code == 0, res.output
    # a run folder is not a board's
    run_dir = tmp_path / "run"
    res = runner.invoke(app, ["run", "--dataset", "synthetic", "--dataset-param", "n_scan=600",
                              "--dataset-param", "n_map=6000", "--attacks", "uniform",
                              "--targets", "p2point", "--budgets", "0.5", "--samples", "1",
                              "--out", str(run_dir), "--quiet"])
    assert res.exit_code == 0, res.output
    before = (run_dir / "manifest.json").read_text()
    res = runner.invoke(app, [*args[:-1], str(run_dir)])
    assert res.exit_code != 0 and "icpbench run" in res.output
    assert (run_dir / "manifest.json").read_text() == before
    # a board recorded before protocols existed
    old = tmp_path / "old"
    old.mkdir()
    (old / "manifest.json").write_text(json.dumps({"config": {}, "variants": []}))
    res = runner.invoke(app, [*args[:-1], str(old)])
    assert res.exit_code != 0 and "records none" in res.output


def test_the_standard_protocol_is_the_default_and_names_its_domains():
    cfg = LeaderboardConfig()
    p = cfg.protocol()
    assert (p.name, p.version, p.domain) == ("standard", STANDARD_VERSION, "town")
    assert p.samples == 48 and p.budgets == (1.0,) and p.ensemble == {}
    assert cfg.extra_attacks == []  # every attack that won a scan is an ensemble member
    unseen = LeaderboardConfig.for_domain("unseen").protocol()
    assert unseen.domain == "unseen" and unseen.dataset_params["sensor"] == "hdl64"
    assert LeaderboardConfig(samples=4).protocol().name == "custom"
    with pytest.raises(InputError, match="standard domains: town, unseen"):
        LeaderboardConfig.for_domain("mars")


def test_a_run_resumed_after_an_attacks_default_changed_is_refused(tmp_path, monkeypatch):
    """The command is the same but a default of the code changed (here the ensemble's search
    patience): the stored rows were made with other settings, so the run is refused."""
    from icpbench.attacks import ensemble

    args = ["run", "--dataset", "synthetic", "--dataset-param", "n_scan=600", "--dataset-param",
            "n_map=6000", "--attacks", "ensemble", "--attack-param", "ensemble.members=uniform",
            "--targets", "p2point", "--budgets", "0.5", "--samples", "1", "--surrogate", "self",
            "--out", str(tmp_path / "r"), "--quiet"]
    assert runner.invoke(app, args).exit_code == 0
    monkeypatch.setattr(ensemble.EnsembleAttack.__init__, "__kwdefaults__",
                        {**ensemble.EnsembleAttack.__init__.__kwdefaults__, "patience": 3})
    res = runner.invoke(app, args)
    assert res.exit_code != 0
    assert "ensemble.patience: stored 8, now 3" in res.output
