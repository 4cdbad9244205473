"""scripts/compare_to_normal.py: "% larger than normal" over converged pairs and over all runs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd

_SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "compare_to_normal.py"


def _module():
    spec = importlib.util.spec_from_file_location("compare_to_normal", _SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _rows(attack, errs, conv):
    pairs = enumerate(zip(errs, conv, strict=True))
    return [{"sample_id": f"s{i}", "attack": attack, "target": "p2plane", "seed": 0,
             "budget": 5.0, "trans_err_xy": e,
             "converged": c, "attack_time_s": 0.5} for i, (e, c) in pairs]


def test_shares_over_converged_pairs_and_all_runs(tmp_path):
    normal = pd.DataFrame(_rows("normal", [5.0, 5.0, 5.0, 5.0], [True, True, True, False]))
    run = tmp_path / "cand"
    run.mkdir()
    # s0 larger (pair), s1 tie (pair, not larger), s2 smaller but ours not converged, s3 larger
    pd.DataFrame(_rows("generator", [6.0, 5.0, 4.0, 9.0], [True, True, False, True])).to_csv(
        run / "results.csv", index=False)
    (line,) = _module().compare(run, normal)
    assert "converged 3/4" in line and "pairs 2" in line
    assert "% > normal 50.0 (all runs 50.0)" in line
    assert "mean converged 6.67 m" in line and "mean all 6.00 m" in line
