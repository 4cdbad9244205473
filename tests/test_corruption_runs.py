"""Corruptions in the runner: their rows beside the attack rows (severity in the budget column,
marked in ``extra``), resumable, applied in the sensor's true frame, and tabulated apart from
Table 1."""

from collections.abc import Mapping
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.core.types import Batch, Sample
from icpbench.corruptions.base import Corruption
from icpbench.harness.corruption_report import corruption_mask, split_rows
from icpbench.harness.corruption_units import SEVERITY_KEY, CorruptionAttack
from icpbench.harness.results import load_results
from icpbench.harness.runner import RunConfig, run


def _cfg(**kw):
    base = dict(dataset="synthetic", attacks=["none"], budgets=[0.5], samples=3, batch_size=2,
                corruptions=["fog", "occluder"], severities=[1, 5])
    return RunConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    out = tmp_path_factory.mktemp("corrupted")
    run(_cfg(), out, progress=False)
    return out


def test_rows_carry_the_severity_and_are_told_apart(grid):
    df = load_results(grid)
    mask = corruption_mask(df)
    assert set(df.loc[~mask, "attack"]) == {"none"}
    assert set(df.loc[~mask, "budget"]) == {0.5}
    corr = df[mask]
    assert set(corr["attack"]) == {"fog", "occluder"}
    assert set(corr["budget"]) == {1.0, 5.0}
    assert (corr[f"extra.{SEVERITY_KEY}"] == corr["budget"]).all()
    assert len(corr) == 3 * 2 * 2 and len(df) == 3 + 12
    # the physics grades: severity 5 fog replaces far more points than severity 1
    share = corr.groupby(["attack", "budget"])["extra.corruption_share_replaced"].mean()
    assert share[("fog", 5.0)] > 10 * share[("fog", 1.0)]
    assert (corr["status"] != "error").all()
    # unexpanded frames are recognised too
    raw = load_results(grid, expand=False)
    assert corruption_mask(raw).sum() == 12
    attacks, corrupted = split_rows(raw)
    assert len(attacks) == 3 and len(corrupted) == 12


def test_resume_adds_only_the_missing_rows(grid, tmp_path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(grid, out)
    before = load_results(out)
    run(_cfg(samples=4), out, progress=False)
    after = load_results(out)
    assert len(after) == len(before) + 1 + 4  # one new scan: none + 2 corruptions x 2 severities
    keep = ["sample_id", "attack", "budget", "trans_err_xy", "extra"]
    old = after[after["sample_id"].isin(before["sample_id"])][keep].sort_values(keep[:3])
    assert old.reset_index(drop=True).equals(before[keep].sort_values(keep[:3]).reset_index(drop=True))
    with pytest.raises(InputError, match="different configuration"):
        run(_cfg(severities=[1, 3]), out, progress=False)


class _Halve(Corruption):
    """Moves every point halfway to the sensor (deterministic)."""

    name = "halve"
    description = "test"
    LEVELS = {s: {} for s in (1, 2, 3, 4, 5)}
    random = False

    def _corrupt(self, scan: np.ndarray, level: Mapping[str, Any], rng: np.random.Generator):
        return scan / 2, np.ones(len(scan), bool), {}


def test_corruption_acts_in_the_sensors_true_frame():
    rng = np.random.default_rng(1)
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.array([[c, -s, 0, 0.4], [s, c, 0, -0.2], [0, 0, 1, 0.1], [0, 0, 0, 1.0]])
    scan = rng.uniform(-20, 20, (50, 3))
    normals = np.tile([0.0, 0.0, 1.0], (50, 1))
    sample = Sample("s/0", scan.astype(np.float32), scan.astype(np.float32),
                    normals.astype(np.float32), T_gt=T)
    out = CorruptionAttack(_Halve()).run(Batch.from_samples([sample]), 2.0, generator=0)
    sensor = scan.astype(np.float32).astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    expected = (sensor / 2 - T[:3, 3]) @ T[:3, :3]  # halved about the sensor, moved back
    assert np.allclose(out.scans[0].numpy(), expected, atol=1e-9)
    # halving about the scan frame's origin instead would differ by half the offset
    assert not np.allclose(out.scans[0].numpy(), scan / 2, atol=0.05)
    assert float(out.extra[SEVERITY_KEY][0]) == 2.0
    assert float(out.extra["corruption_share_replaced"][0]) == 1.0
    with pytest.raises(InputError, match="severity"):
        CorruptionAttack(_Halve()).run(Batch.from_samples([sample]), 2.5)


def test_bad_corruption_settings_are_refused(monkeypatch):
    with pytest.raises(InputError, match="unknown corruption"):
        _cfg(corruptions=["bogus"]).validate()
    for bad in ([0], [6], [2.0], ["3"], []):
        with pytest.raises(InputError, match="severities"):
            _cfg(severities=bad).validate()
    with pytest.raises(InputError, match="has none"):
        _cfg(dataset="objects").validate()
    assert _cfg(corruptions=["all"], severities=[3, 1, 3]).validate().severities == [1, 3]
    assert set(_cfg(corruptions=["all"]).validate().corruptions) >= {"fog", "snow", "beam-loss"}
    monkeypatch.setattr(registry.corruptions, "resolve", lambda names: ["none"])
    with pytest.raises(InputError, match="share their name"):
        _cfg().validate()


def test_table_keeps_table1_and_adds_the_corruption_table(grid):
    res = CliRunner().invoke(app, ["table", str(grid)])
    assert res.exit_code == 0, res.output
    table1, corr = res.output.split("Corruptions:")
    assert "Original" in table1 and "fog" not in table1 and "severity" not in table1
    assert "| fog" in corr and "| occluder" in corr and "severity 5" in corr
    csv = CliRunner().invoke(app, ["table", str(grid), "--format", "csv"])
    assert csv.exit_code == 0 and "fog" not in csv.output and "Original" in csv.output


def test_run_prints_table1_then_the_corruption_table(tmp_path):
    out = tmp_path / "only"
    res = CliRunner().invoke(app, ["run", "--dataset", "synthetic", "--attacks", "none",
                                   "--budgets", "0.5", "--samples", "2", "--corruptions", "snow",
                                   "--severities", "2", "--quiet", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "| snow" in res.output and "severity 2" in res.output
    assert res.output.index("Table 1") < res.output.index("Corruptions:")
