"""``icpbench leaderboard``: a small board runs end to end, parses, ranks and resumes."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.types import Registration
from icpbench.harness.leaderboard import (
    LeaderboardConfig,
    Variant,
    run_leaderboard,
    split_variant_labels,
)
from icpbench.harness.protocol import STANDARD_VERSION
from icpbench.harness.results import load_results
from icpbench.targets.base import Target
from icpbench.targets.icp import icp_config

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
    # each member's own time is part of the attack's: together at most the whole, each > 0
    sec = board[[f"sec_{m}" for m in ("uniform", "sector-adaptive", "pgd", "spoof", "valley")]]
    assert (sec.to_numpy() > 0).all()
    assert (board[[c for c in board if c.startswith("sec_")]].fillna(0).sum(axis=1)
            <= board.attack_s + 1e-6).all()
    spent = re.search(r"^\| p2point \| [^|]+ \| [^|]+ \| \d+ \((\d+\.\d) s\) \|", md, flags=re.M)
    assert spent is not None, md  # the uniform member's cell: wins (seconds)
    assert spent.group(1) == f"{board[board.variant == 'p2point'].sec_uniform.mean():.1f}"
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
    md = (out / "leaderboard.md").read_text()
    # the interval of tau resamples each board's scans: against itself it is at most 1 wide
    m = re.search(r"Kendall's tau = 1\.00 \(95% bootstrap interval (-?[\d.]+) to (-?[\d.]+), "
                  r"each board's scans resampled\) over 3 variants", md)
    assert m is not None, md
    assert -1.0 <= float(m[1]) <= float(m[2]) == 1.0
    assert (out / "comparison.png").stat().st_size > 10_000  # the two boards against each other
    # the same scans: variant by variant, each ratio 1 with an interval of width 0
    cmp = pd.read_csv(out / "comparison.csv").set_index("variant")
    assert set(cmp.index) == set(board.variant)
    np.testing.assert_allclose(cmp[["ratio", "ratio_lo", "ratio_hi"]].to_numpy(), 1.0)
    assert (cmp.larger == 0).all() and (cmp.smaller == 0).all() and (cmp.scans == 2).all()
    assert "| ratio (95% CI) |" in md and "| 1.000 (1.00-1.00) | 0% | 0% |" in md
    # a board copied without its runs still gives tau, and says why it has no interval
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("leaderboard.csv", "manifest.json"):
        (bare / name).write_bytes((out / name).read_bytes())
    res = runner.invoke(app, [*ARGS, "--out", str(out), "--compare-with", str(bare)])
    assert res.exit_code == 0, res.output
    md = (out / "leaderboard.md").read_text()
    assert "Kendall's tau = 1.00 (no interval: " in md and "is missing" in md
    assert "ratio (95% CI)" not in md  # no runs there: no scans to pair
    # a board of some standard variants says which ones it leaves out, in the text and manifest
    assert "8 of the 11 standard ones are not on it: `p2plane (no kernel)`" in md
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["standard_variants_missing"]) == 8
    assert "kiss-icp" not in manifest["standard_variants_missing"]
    # the commits that made each variant's rows, not only the one that wrote the board
    assert set(manifest["rows_made_by"]) == set(board.variant)
    assert all(c == [manifest["git"]["commit"] + ("+dirty" if manifest["git"]["dirty"] else "")]
               for c in manifest["rows_made_by"].values())
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


def test_a_new_protocol_version_carries_over_only_the_runs_it_would_compute_again(tmp_path):
    """A board of an earlier version whose ensemble recorded no ``valley_kernel_model`` (v2):
    p2point's rows stay under the new version and are copied, KISS-ICP's (a Geman-McClure
    kernel) are computed again; the board records and names what it carried over. A board of
    another protocol than its version gives nothing."""
    old, new = tmp_path / "old", tmp_path / "new"
    args = ["leaderboard", "--samples", "1", "--dataset", "synthetic", "--dataset-param",
            "n_scan=600", "--dataset-param", "n_map=6000", "--budgets", "0.5", "--ensemble-param",
            "members=uniform", "--variants", "p2point,kiss-icp", "--quiet"]
    assert runner.invoke(app, [*args, "--out", str(old)]).exit_code == 0
    board = json.loads((old / "manifest.json").read_text())
    board["protocol"]["version"] = -1
    (old / "manifest.json").write_text(json.dumps(board))
    for slug in ("p2point", "kiss-icp"):  # as the earlier version recorded them
        m = json.loads((old / "runs" / slug / "manifest.json").read_text())
        del m["attacks"]["ensemble"]["valley_kernel_model"]
        (old / "runs" / slug / "manifest.json").write_text(json.dumps(m))
    res = runner.invoke(app, [*args, "--out", str(new), "--carry-over", str(old)])
    assert res.exit_code == 0, res.output
    assert ((new / "runs" / "p2point" / "results.csv").read_text()
            == (old / "runs" / "p2point" / "results.csv").read_text())
    kept = json.loads((new / "runs" / "p2point" / "manifest.json").read_text())
    assert kept == json.loads((old / "runs" / "p2point" / "manifest.json").read_text())
    made = json.loads((new / "runs" / "kiss-icp" / "manifest.json").read_text())
    assert [e["rows_from"] for e in made["provenance"]] == [0]  # computed under this version
    assert made["attacks"]["ensemble"]["valley_kernel_model"] == "geman-mcclure"
    manifest = json.loads((new / "manifest.json").read_text())
    assert list(manifest["carried_over"]) == ["p2point"]
    assert manifest["carried_over"]["p2point"]["protocol"]["version"] == -1
    md = (new / "leaderboard.md").read_text()
    assert "Carried over" in md and "p2point (v-1" in md
    # a rewrite without the option keeps the record
    assert runner.invoke(app, [*args, "--out", str(new)]).exit_code == 0
    assert list(json.loads((new / "manifest.json").read_text())["carried_over"]) == ["p2point"]
    # ... and so does a command that ranks only another variant
    only_kiss = [a if a != "p2point,kiss-icp" else "kiss-icp" for a in args]
    assert runner.invoke(app, [*only_kiss, "--out", str(new)]).exit_code == 0
    assert list(json.loads((new / "manifest.json").read_text())["carried_over"]) == ["p2point"]
    # a carried-over run deleted and computed again, by a command of its own, is no longer
    # carried over on the next rewrite
    shutil.rmtree(new / "runs" / "p2point")
    only_p2point = [a if a != "p2point,kiss-icp" else "p2point" for a in args]
    assert runner.invoke(app, [*only_p2point, "--out", str(new)]).exit_code == 0
    assert json.loads((new / "manifest.json").read_text())["carried_over"] == {}
    assert runner.invoke(app, [*args, "--out", str(new)]).exit_code == 0
    assert json.loads((new / "manifest.json").read_text())["carried_over"] == {}
    assert "Carried over" not in (new / "leaderboard.md").read_text()
    # another protocol (here another budget) is refused before anything is copied
    res = runner.invoke(app, [*[a if a != "0.5" else "0.4" for a in args],
                              "--out", str(tmp_path / "other"), "--carry-over", str(old)])
    assert res.exit_code != 0 and "budgets: stored [0.5]" in res.output
    assert not (tmp_path / "other" / "runs").exists()


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

    out = tmp_path / "r"
    args = ["run", "--dataset", "synthetic", "--dataset-param", "n_scan=600", "--dataset-param",
            "n_map=6000", "--attacks", "uniform,ensemble", "--attack-param",
            "ensemble.members=uniform", "--targets", "p2point", "--budgets", "0.5", "--samples", "2",
            "--surrogate", "self", "--out", str(out), "--quiet"]
    assert runner.invoke(app, args).exit_code == 0
    before = load_results(out)
    monkeypatch.setattr(ensemble.EnsembleAttack.__init__, "__kwdefaults__",
                        {**ensemble.EnsembleAttack.__init__.__kwdefaults__, "patience": 3})
    res = runner.invoke(app, args)
    assert res.exit_code != 0
    assert "ensemble.patience on p2point: stored 8, now 3" in res.output and "--redo" in res.output
    res = runner.invoke(app, [*args, "--redo", "normal"])
    assert res.exit_code != 0 and "--redo normal: not among the run's attacks" in res.output
    # --redo: the ensemble's rows are removed and computed again, `uniform`'s are kept as they were
    res = runner.invoke(app, [*args, "--redo", "ensemble"])
    assert res.exit_code == 0, res.output
    after = load_results(out)
    assert len(after) == len(before) == 4 and (after.attack == "ensemble").sum() == 2
    key = ["sample_id", "attack"]
    pd.testing.assert_frame_equal(
        after[after.attack == "uniform"].sort_values(key).reset_index(drop=True),
        before[before.attack == "uniform"].sort_values(key).reset_index(drop=True))
    lines = (out / "results.csv").read_text().splitlines()[1:]
    assert [ln.split(",")[1] for ln in lines] == ["uniform", "uniform", "ensemble", "ensemble"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["attacks"]["ensemble"]["patience"] == 3
    prov = manifest["provenance"]
    assert [e["rows_from"] for e in prov] == [0, 2] and prov[-1]["redone"] == ["ensemble"]


@pytest.mark.parametrize("target", ["p2point", "kiss-icp"])
def test_a_changed_default_that_acts_the_same_on_the_target_keeps_the_rows(tmp_path, target):
    """Protocol v3 records ``valley_kernel_model`` (v2 recorded none, i.e. Cauchy's plan). On a
    target without a Geman-McClure kernel both compute the same rows: the run resumes and keeps
    them; on KISS-ICP they differ, and the resume is refused naming the setting and the target."""
    out = tmp_path / "r"
    args = ["run", "--dataset", "synthetic", "--dataset-param", "n_scan=600", "--dataset-param",
            "n_map=6000", "--attacks", "ensemble", "--attack-param", "ensemble.members=uniform",
            "--targets", target, "--budgets", "0.5", "--samples", "2", "--surrogate", "self",
            "--out", str(out), "--quiet"]
    assert runner.invoke(app, args).exit_code == 0
    before = (out / "results.csv").read_text()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["attacks"]["ensemble"].pop("valley_kernel_model") == "geman-mcclure"
    (out / "manifest.json").write_text(json.dumps(manifest))  # as protocol v2 recorded it
    res = runner.invoke(app, [*args, "--samples", "3"])
    if target == "kiss-icp":
        assert res.exit_code != 0
        assert ("ensemble.valley_kernel_model on kiss-icp: stored 'cauchy', now 'geman-mcclure'"
                in res.output), res.output
        return
    assert res.exit_code == 0, res.output
    after = (out / "results.csv").read_text()
    assert after.startswith(before) and len(after.splitlines()) == len(before.splitlines()) + 1
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["attacks"]["ensemble"]["valley_kernel_model"] == "geman-mcclure"
    assert [e["rows_from"] for e in manifest["provenance"]] == [0, 2]


# -- a board ranks only what was measured, and says what was not -------------------------------

class _PlannedICP(Target):
    """An ICP that, scan by scan, raises, returns a NaN pose or keeps its initial pose (a finite
    estimate), as :attr:`plan` says: the k-th sample it prepares a map for follows ``plan[k]``
    (the runner prepares each sample's map once, in sample order)."""

    name: ClassVar[str] = "planned-icp"
    description: ClassVar[str] = "raises, returns NaN or keeps T_init, per scan (tests)"
    differentiable: ClassVar[bool] = False
    plan: ClassVar[list[str]] = ["ok"]

    def __init__(self, preset: str = "lidar", **overrides: Any) -> None:
        self.config = icp_config(preset, **overrides)
        self._prepared = 0

    def prepare(self, map_points: np.ndarray, map_normals: np.ndarray) -> str:
        k, self._prepared = self._prepared, self._prepared + 1
        return type(self).plan[k % len(type(self).plan)]

    def register(self, scans: torch.Tensor, maps: Sequence[str], T_init: torch.Tensor
                 ) -> Registration:
        if "raise" in maps:
            raise RuntimeError("solver exploded")
        T = T_init.detach().to(torch.float64).clone()
        T[[k for k, m in enumerate(maps) if m == "nan"]] = float("nan")
        B = len(maps)
        return Registration(T=T, converged=torch.ones(B, dtype=torch.bool),
                            iterations=torch.ones(B, dtype=torch.long),
                            inlier_fraction=torch.ones(B, dtype=torch.float64), status=["ok"] * B)


class _SteadyICP(_PlannedICP):
    """Keeps its initial pose on every scan (a finite estimate; the board's other variant)."""

    name: ClassVar[str] = "steady-icp"
    plan: ClassVar[list[str]] = ["ok"]


@pytest.fixture
def planned_targets():
    registry.targets.register("planned-icp", _PlannedICP)
    registry.targets.register("steady-icp", _SteadyICP)
    try:
        yield _PlannedICP
    finally:
        _PlannedICP.plan = ["ok"]
        registry.targets.unregister("planned-icp")
        registry.targets.unregister("steady-icp")


SMALL = ["leaderboard", "--samples", "2", "--dataset", "synthetic", "--dataset-param", "n_scan=600",
         "--dataset-param", "n_map=6000", "--budgets", "0.5", "--ensemble-param",
         "members=uniform,search", "--ensemble-param", "queries=2", "--quiet"]


def test_a_target_that_fails_every_scan_is_not_ranked_and_the_command_says_so(tmp_path,
                                                                               planned_targets):
    """Before: a target raising on every scan was ranked (0% held, "diverged"), exit 0, no word;
    one returning NaN poses crashed the board with a traceback."""
    for plan, reason in ((["raise"], "every registration failed: RuntimeError: solver exploded"),
                         (["nan"], "every registration gave a non-finite pose")):
        planned_targets.plan = plan
        out = tmp_path / plan[0]
        res = runner.invoke(app, [*SMALL, "--variants", "p2point", "--add-target", "planned-icp",
                                  "--out", str(out)])
        assert res.exit_code == 2, res.output
        assert "Traceback" not in res.output
        assert f"error: variant 'planned-icp' is not ranked: {reason}" in res.stderr
        board = pd.read_csv(out / "leaderboard.csv")
        assert list(board.variant) == ["p2point"]  # ranked: only what was measured
        md = (out / "leaderboard.md").read_text()
        assert f"Not ranked: planned-icp: {reason}" in md
        assert not re.search(r"^\| \d+ \| [^|]+ \| planned-icp \|", md, flags=re.M)
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["skipped"]["planned-icp"].startswith(reason)


def test_a_variant_with_some_failed_scans_is_ranked_on_the_scans_measured(tmp_path,
                                                                          planned_targets):
    planned_targets.plan = ["raise", "ok"]  # batch size 1: each scan on its own
    cfg = LeaderboardConfig(dataset="synthetic", dataset_params={"n_scan": 600, "n_map": 6000},
                            samples=2, budgets=[0.5], variants=[], batch_size=1,
                            extra_targets=["planned-icp", "steady-icp"],
                            ensemble={"members": "uniform,search", "queries": 2})
    board = run_leaderboard(cfg, tmp_path / "b", progress=False)
    r = board.set_index("variant").loc["planned-icp"]
    assert (r.scans, r.failed, r.diverged) == (2, 1, 0)
    rows = load_results(tmp_path / "b" / "runs" / "planned-icp")
    ok = rows[(rows.attack == "ensemble") & (rows.status != "error")]
    assert len(ok) == 1 and r.worst_mean == pytest.approx(float(ok.trans_err_xy.iloc[0]))
    assert r.held_share in (0.0, 1.0)  # a share of the one scan measured
    md = (tmp_path / "b" / "leaderboard.md").read_text()
    assert "planned-icp λ=0.5: 1 failed, 0 diverged of 2" in md
    assert "Not ranked" not in md


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(plan=st.lists(st.sampled_from(["raise", "nan", "ok"]), min_size=1, max_size=3))
def test_a_variant_is_ranked_only_on_what_it_measured(plan, planned_targets):
    """Any mix of raising, NaN and working scans: error and non-finite rows, the failures counted
    on the board, and no rank for a variant that measured nothing (its reason stated)."""
    planned_targets.plan = plan
    cfg = LeaderboardConfig(dataset="synthetic", dataset_params={"n_scan": 600, "n_map": 6000},
                            samples=len(plan), budgets=[0.5], variants=[], batch_size=1,
                            extra_targets=["planned-icp", "steady-icp"],
                            ensemble={"members": "uniform,search", "queries": 2})
    with tempfile.TemporaryDirectory() as tmp:
        board = run_leaderboard(cfg, Path(tmp), progress=False)
        rows = load_results(Path(tmp) / "runs" / "planned-icp")
        md = (Path(tmp) / "leaderboard.md").read_text()
    for attack in ("none", "ensemble"):
        status = rows[rows.attack == attack].sort_values("sample_id").status.tolist()
        assert [s == "error" for s in status] == [p == "raise" for p in plan]
        assert [s == "nonfinite" for s in status] == [p == "nan" for p in plan]
    assert "steady-icp" in set(board.variant)
    if "ok" in plan:
        r = board.set_index("variant").loc["planned-icp"]
        assert (r.scans, r.failed, r.diverged) == (len(plan), plan.count("raise"),
                                                   plan.count("nan"))
        assert np.isfinite(r.worst_mean) and np.isfinite(r["rank"])
        if r.failed or r.diverged:
            assert f"planned-icp λ=0.5: {r.failed} failed, {r.diverged} diverged" in md
    else:
        assert "planned-icp" not in set(board.variant)
        why = board.attrs["not_ranked"]["planned-icp"]
        assert why.startswith("every registration failed" if set(plan) == {"raise"} else
                              "every registration gave a non-finite pose" if set(plan) == {"nan"}
                              else "no registration gave a finite pose")
        assert f"Not ranked: planned-icp: {why}" in md


def test_an_extra_attack_that_never_ran_is_said_not_to_have_run(tmp_path):
    """Before: `--extra-attacks generator` without a checkpoint showed "+ generator 0"."""
    out = tmp_path / "b"
    res = runner.invoke(app, [*SMALL, "--samples", "1", "--variants", "p2point",
                              "--extra-attacks", "generator", "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "error: extra attack generator did not run on variant 'p2point': CheckpointError: no " \
           "shipped generator checkpoint" in res.stderr
    md = (out / "leaderboard.md").read_text()
    assert "| did not run |" in md and "`generator` did not run" in md
    assert "the same command tries it again" in md
    board = pd.read_csv(out / "leaderboard.csv")
    assert board.won_extra_generator.isna().all()  # not "0 wins"


def test_a_gradient_extra_attack_on_a_target_without_gradients_skips_the_variant(
        tmp_path, planned_targets):
    """Before: the board stopped, advising `--surrogate p2plane`, an option it does not have."""
    out = tmp_path / "b"
    res = runner.invoke(app, [*SMALL, "--samples", "1", "--variants", "p2point",
                              "--add-target", "planned-icp", "--extra-attacks", "pgd",
                              "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "--surrogate p2plane" not in res.output
    assert "warning: variant 'planned-icp' is not ranked: extra attack(s) pgd need gradients" \
        in res.stderr
    md = (out / "leaderboard.md").read_text()
    assert "Not ranked: planned-icp: extra attack(s) pgd need gradients" in md
    assert "rank a target that has a replica" in md
    assert list(pd.read_csv(out / "leaderboard.csv").variant) == ["p2point"]
    assert not (out / "runs" / "planned-icp").exists()  # skipped before any row


def test_an_unknown_variant_is_named_alone(tmp_path):
    res = runner.invoke(app, [*SMALL, "--variants", "p2point,bogus", "--out", str(tmp_path / "b")])
    assert res.exit_code == 2
    assert "unknown leaderboard variant(s) 'bogus'; valid: p2plane (Cauchy)" in res.output
    assert "p2point,bogus" not in res.output
    assert split_variant_labels(" p2point , p2plane (Cauchy),,") == ["p2point", "p2plane (Cauchy)"]
    # a label with commas is kept whole only when it is a known one
    assert split_variant_labels("x,a,b,c", known=["a,b"]) == ["x", "a,b", "c"]


def test_ctrl_c_on_a_board_counts_the_rows_saved_in_its_runs_and_resumes(tmp_path, monkeypatch):
    """Before: "interrupted before any result was saved" although a variant had finished."""
    import icpbench.harness.leaderboard as lb

    real = lb.run_grid
    calls = []

    def second_variant_interrupted(rc, out_dir, **kw):
        calls.append(out_dir)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(rc, out_dir, **kw)

    monkeypatch.setattr(lb, "run_grid", second_variant_interrupted)
    out = tmp_path / "b"
    args = [*SMALL, "--samples", "1", "--variants", "p2point,p2plane (Cauchy)", "--out",
            str(out)]
    res = runner.invoke(app, args)
    assert res.exit_code == 130 and "Traceback" not in res.output
    n = len(pd.read_csv(out / "runs" / "p2point" / "results.csv"))
    assert n > 0
    assert f"interrupted: {n} result row(s) are saved in {out / 'runs'}; re-run the same " \
           "command to resume" in res.stderr
    assert "before any result was saved" not in res.output
    monkeypatch.setattr(lb, "run_grid", real)
    before = (out / "runs" / "p2point" / "results.csv").read_text()
    res = runner.invoke(app, args)  # resumes: the finished variant is not computed again
    assert res.exit_code == 0, res.output
    assert (out / "runs" / "p2point" / "results.csv").read_text() == before
