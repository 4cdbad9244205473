"""Integrity monitors in ``icpbench run``: calibrated per target on clean train-split scans, every
row records each monitor's score and alarm, the table reports the detection rate and the
undetected error, and ``--monitor-aware`` makes the query attacks maximise the undetected error."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core.errors import InputError
from icpbench.harness.monitor_report import undetected_frame
from icpbench.harness.results import load_results
from icpbench.harness.run_monitors import ALARM, SCORE
from icpbench.harness.runner import RunConfig, run

cli = CliRunner()
SYN = dict(dataset="synthetic", targets=["p2point"], budgets=[1.0], samples=4, batch_size=2,
           dataset_params={"n_samples": 12, "n_scan": 300, "n_map": 3000},
           monitors=["inliers", "residual", "odometry"], false_alarm_rate=0.2,
           calibration_samples=10)


@pytest.fixture(scope="module")
def naive(tmp_path_factory):
    out = tmp_path_factory.mktemp("naive")
    run(RunConfig(**SYN, attacks=["none", "uniform", "search"],
                  attack_params={"search": {"queries": 6}}), out, progress=False)
    return out


def test_the_monitors_are_calibrated_per_target_on_the_train_split_and_recorded(naive):
    cal = json.loads((naive / "manifest.json").read_text())["monitors"]
    assert set(cal) == {"p2point"} and set(cal["p2point"]) == set(SYN["monitors"])
    for rec in cal["p2point"].values():
        assert rec["n"] == 10 and rec["false_alarm_rate"] == 0.2
        assert rec["observed_rate"] <= 0.2 and np.isfinite(rec["threshold"])


def test_every_row_records_each_monitors_score_and_alarm_against_its_threshold(naive):
    df = load_results(naive)
    th = {m: r["threshold"] for m, r in
          json.loads((naive / "manifest.json").read_text())["monitors"]["p2point"].items()}
    for m, t in th.items():
        score = df["extra." + SCORE + m].astype(float)
        alarm = df["extra." + ALARM + m].astype(float)
        assert ((score > t).astype(float) == alarm).all(), m
    fired = np.column_stack([df["extra." + ALARM + m].astype(float) for m in th]).max(axis=1)
    assert (df["extra." + ALARM + "any"].astype(float).to_numpy() == fired).all()


def test_the_undetected_error_is_the_error_where_no_monitor_fired_and_never_above_it(naive):
    df = load_results(naive)
    t = undetected_frame(df, "p2point").set_index("attack")
    for attack, g in df.groupby("attack"):
        alarm = g["extra." + ALARM + "any"].astype(float).to_numpy() > 0
        err = g["trans_err_xy"].astype(float).to_numpy()
        want = np.where(alarm, 0.0, err).mean()
        assert t.loc[attack, "undetected_mean_m"] == pytest.approx(want)
        assert t.loc[attack, "detected_pct"] == pytest.approx(100 * alarm.mean())
        assert t.loc[attack, "undetected_mean_m"] <= t.loc[attack, "error_mean_m"] + 1e-12


def test_the_table_shows_the_monitors_section(naive):
    res = cli.invoke(app, ["table", str(naive), "--reference", "uniform"])
    assert res.exit_code == 0, res.output
    assert "Monitors (inliers, odometry, residual) on p2point" in res.output
    assert "Clean false alarms on the evaluated split (4 rows of attack none)" in res.output


def test_a_resumed_run_keeps_its_calibration(naive, tmp_path):
    import shutil

    copy = tmp_path / "r"
    shutil.copytree(naive, copy)
    before = json.loads((copy / "manifest.json").read_text())["monitors"]
    run(RunConfig(**SYN, attacks=["none", "uniform", "search"],
                  attack_params={"search": {"queries": 6}}), copy, progress=False)
    assert json.loads((copy / "manifest.json").read_text())["monitors"] == before


def test_a_monitor_aware_search_returns_only_unflagged_scans_where_the_clean_scan_passes(
        naive, tmp_path):
    """The search starts from the clean scan's neighbourhood and keeps the largest *undetected*
    error: where the clean scan raises no alarm, its result raises none either, and its mean
    undetected error is at least the naive search's."""
    out = tmp_path / "aware"
    run(RunConfig(**{**SYN, "monitor_aware": True}, attacks=["none", "search"],
                  attack_params={"search": {"queries": 6}}), out, progress=False)
    df = load_results(out)
    key = ["sample_id"]
    clean = df[df.attack == "none"].set_index(key)["extra." + ALARM + "any"].astype(float)
    found = df[df.attack == "search"].set_index(key)["extra." + ALARM + "any"].astype(float)
    passes = clean[clean == 0].index
    assert len(passes) > 0
    assert (found.loc[passes] == 0).all(), found.loc[passes]
    aware = undetected_frame(df, "p2point").set_index("attack").loc["search", "undetected_mean_m"]
    plain = undetected_frame(load_results(naive), "p2point").set_index("attack").loc[
        "search", "undetected_mean_m"]
    assert aware >= plain - 1e-9


@pytest.mark.parametrize(("kw", "needle"), [
    ({"monitors": [], "monitor_aware": True}, "--monitor-aware needs --monitors"),
    ({"monitor_params": {"degeneracy": {"threshold": 10.0}}},
     "settings given for monitor(s) 'degeneracy' that are not in this run"),
    ({"monitors": ["bogus"]}, "unknown monitor 'bogus'"),
    ({"false_alarm_rate": 0.7}, "--false-alarm-rate must be a number > 0 and <= 0.5"),
])
def test_bad_monitor_settings_are_refused_before_anything_runs(tmp_path, kw, needle):
    with pytest.raises(InputError) as exc:
        run(RunConfig(**{**SYN, **kw}, attacks=["none"]), tmp_path / "o", progress=False)
    assert needle in str(exc.value)
    assert not (tmp_path / "o").exists()


def test_too_few_calibration_scans_for_the_rate_are_refused(tmp_path):
    with pytest.raises(InputError, match="needs at least 100 clean scans"):
        run(RunConfig(**{**SYN, "false_alarm_rate": 0.01}, attacks=["none"]), tmp_path / "o",
            progress=False)


def test_a_board_with_monitors_shows_detection_and_the_undetected_worst_case(tmp_path):
    from icpbench.harness.leaderboard import LeaderboardConfig, run_leaderboard

    cfg = LeaderboardConfig(dataset="synthetic", samples=2, budgets=[1.0],
                            dataset_params={"n_samples": 100, "n_scan": 300, "n_map": 3000},
                            variants=["p2point"], monitors=["inliers", "residual"],
                            ensemble={"spoof_queries": 3, "valley_queries": 3, "queries": 3,
                                      "pgd_steps": 1})
    board = run_leaderboard(cfg, tmp_path / "b", progress=False)
    row = board.iloc[0]
    assert 0.0 <= row.detected_share <= 1.0
    assert 0.0 <= row.undetected_mean <= row.worst_mean + 1e-12
    df = load_results(tmp_path / "b" / "runs" / "p2point")
    e = df[df.attack == "ensemble"]
    alarm = e["extra." + ALARM + "any"].astype(float).to_numpy() > 0
    assert row.detected_share == pytest.approx(alarm.mean())
    assert row.undetected_mean == pytest.approx(
        np.where(alarm, 0.0, e.trans_err_xy.astype(float)).mean())
    md = (tmp_path / "b" / "leaderboard.md").read_text()
    assert "| detected | undetected [m] |" in md and "the attacks ignore them" in md


def test_a_heldout_calibration_uses_the_evaluated_splits_later_scans_and_never_overlaps(
        tmp_path, monkeypatch):
    from icpbench.harness import run_monitors

    seen = []
    real = run_monitors._calibration_scans

    def spy(cfg):
        out = real(cfg)
        seen.append(out[:2])
        return out

    monkeypatch.setattr(run_monitors, "_calibration_scans", spy)
    cfg = {**SYN, "calibration_split": "heldout", "calibration_samples": 8}
    run(RunConfig(**cfg, attacks=["none"]), tmp_path / "r", progress=False)
    (source, first), = seen
    assert source.split == "test" and first == SYN["samples"]  # the scans after the evaluated 4
    manifest = json.loads((tmp_path / "r" / "manifest.json").read_text())
    assert manifest["config"]["calibration_split"] == "heldout" and manifest["monitors"]
    with pytest.raises(InputError, match="samples: stored 4, now 6"):  # would overlap
        run(RunConfig(**{**cfg, "samples": 6}, attacks=["none"]), tmp_path / "r", progress=False)
    with pytest.raises(InputError, match="or lower --samples"):  # 2 held-out scans left
        run(RunConfig(**{**cfg, "samples": 10}, attacks=["none"]), tmp_path / "o", progress=False)
    with pytest.raises(InputError, match="'heldout' needs samples"):
        RunConfig(**{**cfg, "samples": None}, attacks=["none"]).validate()
