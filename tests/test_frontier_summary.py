"""scripts/frontier.py's summary: per-configuration means, ratios to PGD-30, missing folders skipped."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest


@pytest.fixture(scope="module")
def frontier(load_script):
    return load_script("frontier")


def _write(folder: Path, errs: dict[float, list[float]], conv: bool = True) -> None:
    rows = [{"budget": lam, "trans_err_xy": e, "converged": conv, "status": "ok",
             "attack_time_s": 0.5, "disp_max": lam}
            for lam, es in errs.items() for e in es]
    rows.append({"budget": 1.0, "trans_err_xy": 99.0, "converged": True, "status": "error",
                 "attack_time_s": 0.0, "disp_max": 0.0})  # failed units are left out
    folder.mkdir(parents=True)
    pd.DataFrame(rows).to_csv(folder / "results.csv", index=False)


def test_summary_ratios_and_missing_folders(tmp_path: Path, frontier) -> None:
    _write(tmp_path / "runs" / "pgd-30", {1.0: [2.0, 4.0], 4.0: [10.0, 30.0]})
    _write(tmp_path / "runs" / "sector", {1.0: [1.0, 2.0], 4.0: [5.0, 5.0]}, conv=False)
    res = frontier.summarise(tmp_path, list(frontier.CONFIGS)).set_index(["config", "budget_m"])
    assert set(res.index.get_level_values(0)) == {"pgd-30", "sector"}  # the rest: no folder
    assert res.loc[("pgd-30", 4.0), "err_all_m"] == pytest.approx(20.0)
    assert res.loc[("sector", 1.0), "vs_pgd30"] == pytest.approx(1.5 / 3.0)
    assert res.loc[("sector", 4.0), "vs_pgd30"] == pytest.approx(0.25)
    assert res.loc[("sector", 1.0), "converged"] == 0.0
    assert res.loc[("pgd-30", 1.0), "n"] == 2


def test_summary_of_nothing_is_empty(tmp_path: Path, frontier) -> None:
    assert frontier.summarise(tmp_path, list(frontier.CONFIGS)).empty


def test_configurations_are_data_and_reach_the_cli(frontier, tmp_path: Path) -> None:
    """The configurations come from the YAML file; every one names a registered attack and
    settings it accepts; nested settings reach the CLI in the flow style it reads; a bad entry is
    refused."""
    import yaml

    from icpbench.core import registry

    assert "pgd-30" in frontier.CONFIGS and frontier.CONFIGS["pgd-30"]["params"] == {"steps": 30}
    for name, c in frontier.CONFIGS.items():
        registry.attacks.check_params(c["attack"], c["params"])
        for arg in frontier.attack_args(c):
            key, value = arg.split("=", 1)
            assert key.split(".", 1)[0] == c["attack"], name
            assert yaml.safe_load(value) == c["params"][key.split(".", 1)[1]], name
    bad = tmp_path / "bad.yaml"
    bad.write_text("x: {params: {steps: 2}}\n")
    with pytest.raises(ValueError, match="needs 'attack'"):
        frontier.load_configs(bad)
