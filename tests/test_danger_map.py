"""Danger maps from results: per-location errors, AUC, pass rank correlation, files."""

import numpy as np
import pandas as pd
import pytest

from icpbench.analysis.danger_map import (
    auc,
    location_errors,
    pass_rank_correlation,
    write_maps,
)
from icpbench.core.errors import InputError
from icpbench.harness.monitor_report import ANY_ALARM


def _results(n_loc=12):
    rng = np.random.default_rng(0)
    rows = []
    for loc in range(n_loc):
        stretch = "open" if loc % 2 else "dense"
        base = 2.0 if stretch == "open" else 0.8
        for p in (1, 2):
            for attack, scale in (("generator", 1.0), ("sector", 0.9)):
                e = base + 0.05 * loc + rng.normal(0, 0.01)
                rows.append({"sample_id": f"s{loc}-{p}", "attack": attack, "target": "p2plane",
                             "budget": 1.0, "seed": 0, "status": "ok", "converged": True,
                             "rho_x": scale * e, "rho_y": 0.1, "trans_err_xy": scale * e,
                             "meta.frame": loc, "meta.pass": p, "meta.x": 10.0 * loc,
                             "meta.y": 0.0, "meta.stretch": stretch})
    return pd.DataFrame(rows)


def test_auc_matches_definition():
    assert auc([2, 3, 4], [0, 1]) == 1.0
    assert auc([0, 1], [2, 3]) == 0.0
    assert auc([1, 1], [1, 1]) == 0.5


def test_rank_correlation_and_summary(tmp_path):
    df = _results()
    loc = location_errors(df, "generator", 1.0)
    rho, n = pass_rank_correlation(loc)
    assert n == 12 and rho > 0.99
    s = write_maps(df, "generator", 1.0, tmp_path, compare="sector")
    assert s["generator"]["auc_open_vs_dense"] == 1.0
    assert s["generator"]["locations"] == 12 and s["generator"]["passes"] == 2
    assert s["comparison"]["share_ours_larger"] == 1.0 and s["comparison"]["median"] > 0
    for f in s["files"]:
        assert (tmp_path / f).stat().st_size > 0
    assert (tmp_path / "summary.json").exists()


def test_missing_route_metadata_or_attack_raises():
    df = _results()
    with pytest.raises(InputError, match="no rows for attack"):
        location_errors(df, "pgd", 1.0)
    with pytest.raises(InputError, match="route metadata"):
        location_errors(df.drop(columns=["meta.frame"]), "generator", 1.0)


def test_with_monitors_the_undetected_map_is_drawn_beside_the_unmonitored_one(tmp_path):
    """A run with monitors: per row the undetected error is the error where no monitor fired
    and 0 where one did (or the pose is not finite); its map and mean join the summary."""
    df = _results()
    alarm = (df["meta.frame"] % 3 == 0).astype(float)  # every third place caught
    df = df.assign(**{ANY_ALARM: alarm})
    df.loc[df.index[1], "trans_err_xy"] = np.nan  # a diverged pose counts as caught
    loc = location_errors(df, "generator", 1.0)
    caught = (loc["detected"] > 0) | ~np.isfinite(loc["trans_err_xy"])
    assert (loc.loc[caught, "undetected_err"] == 0).all()
    np.testing.assert_array_equal(loc.loc[~caught, "undetected_err"],
                                  loc.loc[~caught, "trans_err_xy"])
    s = write_maps(df, "generator", 1.0, tmp_path)
    assert "generator_undetected_map.png" in s["files"]
    assert (tmp_path / "generator_undetected_map.png").stat().st_size > 0
    assert s["generator"]["detected_pct"] == pytest.approx(100 * alarm[df.attack == "generator"]
                                                           .mean())
    assert 0 < s["generator"]["mean_undetected"] < s["generator"]["mean_trans_err_xy"]
    plain = write_maps(_results(), "generator", 1.0, tmp_path / "plain")
    assert "mean_undetected" not in plain["generator"]
    assert not any("undetected" in f for f in plain["files"])


def test_map_takes_monitors_through_the_layer(tmp_path):
    from typer.testing import CliRunner

    from icpbench.cli import app

    res = CliRunner().invoke(app, ["map", "--dataset", "synthetic", "--attack", "uniform",
                                   "--monitor-aware", "--out", str(tmp_path / "m"), "--quiet"])
    assert res.exit_code == 2 and "--monitor-aware needs --monitors" in res.output, res.output
    res = CliRunner().invoke(app, ["map", "--monitors", "bogus", "--out", str(tmp_path / "m")])
    assert res.exit_code == 2 and "unknown monitor 'bogus'" in res.output, res.output
    assert not (tmp_path / "m").exists()  # refused before its folder is made
