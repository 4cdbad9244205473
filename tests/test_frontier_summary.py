"""scripts/frontier.py's summary: per-configuration means, ratios to PGD-30, missing folders skipped."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd
import pytest

_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "frontier.py"


@pytest.fixture(scope="module")
def frontier():
    spec = importlib.util.spec_from_file_location("frontier_script", _SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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


def test_refinement_families_differ_only_in_steps_and_surrogate_cap(frontier) -> None:
    """``generator+K`` ascends the 25-iteration surrogate, ``generator+K-icp100`` the 100-iteration
    evaluation ICP; both start from the default generator and name K steps."""
    for k in (1, 3, 10):
        attack, short = frontier.CONFIGS[f"generator+{k}"]
        attack100, full = frontier.CONFIGS[f"generator+{k}-icp100"]
        assert attack == attack100 == "generator"
        assert short == [f"generator.refine_steps={k}"]
        assert full == [*short, "generator.refine_icp_iterations=100"]
    assert frontier.FAMILIES["generator-refine100"][0] == "generator"
