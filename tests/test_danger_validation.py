"""Danger validation: the rank statistics, the per-place table (realistic error = largest error over
corruptions) and one end-to-end validation on a small synthetic grid."""

import json

import numpy as np
import pandas as pd
import pytest

from icpbench.analysis.danger_validation import (
    ValidationSettings,
    error_table,
    quantity_columns,
    statistics,
    validate,
)
from icpbench.analysis.rank_stats import auc_ci, spearman_ci
from icpbench.core.errors import InputError


def test_spearman_and_auc_on_known_answers():
    x = np.arange(20.0)
    s = spearman_ci(x, x**3, n_boot=200)
    assert s.value == pytest.approx(1.0) and s.lo == pytest.approx(1.0) and s.n_boot == 200
    assert spearman_ci(x, -x, n_boot=50).value == pytest.approx(-1.0)
    label = x >= 15
    a = auc_ci(x, label, n_boot=200)
    assert a.value == 1.0 and a.lo == 1.0
    assert auc_ci(-x, label, n_boot=50).value == 0.0
    assert auc_ci(np.zeros(20), label, n_boot=50).value == 0.5  # all tied: chance
    # one misranked pair out of 5 x 15: AUC = 1 - 1/75
    y = x.copy()
    y[14], y[15] = y[15], y[14]
    assert auc_ci(y, label, n_boot=10).value == pytest.approx(1 - 1 / 75)
    # inf ranks highest (a singular Hessian's condition number), NaN is dropped
    z = np.where(label, np.inf, x)
    z[0] = np.nan
    a = auc_ci(z, label, n_boot=50)
    assert a.value == 1.0 and a.n == 19
    assert np.isnan(auc_ci(x, np.zeros(20, bool), n_boot=10).value)  # one class only
    with pytest.raises(InputError):
        spearman_ci(x, x[:5])


def _rows():
    """Three places: clean, attacks, and two corruptions at severities 1 and 3."""
    base = {"target": "p2plane", "seed": 0, "status": "ok", "extra.corruption_severity": np.nan}
    rows = []
    for i, (gen, fog3, snow3) in enumerate([(0.2, 0.1, 0.05), (1.5, 0.3, 2.0), (0.9, np.inf, 0.2)]):
        sid = f"p{i}"
        meta = {"meta.x": float(i), "meta.y": 0.0}
        rows.append({**base, **meta, "sample_id": sid, "attack": "none", "budget": 1.0,
                     "trans_err_xy": 0.01})
        rows.append({**base, **meta, "sample_id": sid, "attack": "generator", "budget": 1.0,
                     "trans_err_xy": gen})
        for name, e3 in (("fog", fog3), ("snow", snow3)):
            for sev, err in ((1, 0.02), (3, e3)):
                rows.append({**base, **meta, "sample_id": sid, "attack": name, "budget": float(sev),
                             "trans_err_xy": err, "extra.corruption_severity": float(sev),
                             "status": "nonfinite" if not np.isfinite(err) else "ok"})
    df = pd.DataFrame(rows)
    # a crashed corruption row does not count
    df.loc[(df["sample_id"] == "p0") & (df["attack"] == "snow") & (df["budget"] == 3.0),
           ["status", "trans_err_xy"]] = ["error", 9.0]
    return df


def test_error_table_takes_the_largest_error_over_corruptions():
    t = error_table(_rows(), ["generator"], [1, 3], 1.0)
    assert list(t.index) == ["p0", "p1", "p2"]
    assert t.loc["p0", "realistic_s3"] == pytest.approx(0.1)  # snow crashed: fog alone
    assert t.loc["p1", "realistic_s3"] == pytest.approx(2.0)
    assert t.loc["p1", "worst_corruption_s3"] == "snow"
    assert t.loc["p2", "realistic_s3"] == np.inf  # non-finite = failure
    assert t.loc["p2", "worst_corruption_s3"] == "fog"
    assert (t["realistic_s1"] == 0.02).all() and (t["clean_err"] == 0.01).all()
    assert list(t["worst_generator"]) == [0.2, 1.5, 0.9]
    with pytest.raises(InputError, match="sector-iter"):
        error_table(_rows(), ["sector-iter"], [3], 1.0)
    with pytest.raises(InputError, match="severity 5"):
        error_table(_rows(), ["generator"], [5], 1.0)


def test_statistics_orient_the_predictors():
    t = error_table(_rows(), ["generator"], [3], 1.0)
    t["hessian_min_eig"] = [30.0, 1.0, 2.0]  # small = dangerous: the failing places p1, p2
    for q in ("hessian_cond", "loc_trans_min", "loc_rot_min", "sector_xy"):
        t[q] = [1.0, 2.0, 3.0]
    st = statistics(t, quantity_columns(["generator"]), [3], 0.5, n_boot=20, seed=0)["3"]
    assert st["failures"] == 2 and st["places"] == 3
    assert st["quantities"]["hessian_min_eig"]["auc"]["value"] == 1.0
    assert st["quantities"]["worst_generator"]["auc"]["value"] == 1.0
    assert st["quantities"]["loc_trans_min"]["auc"]["value"] == 0.0  # negated: 1, 2, 3 -> p0 worst


def test_validate_end_to_end_on_a_small_grid(tmp_path):
    settings = ValidationSettings(dataset="synthetic", samples=3, attacks=["uniform"],
                                  corruptions=["fog", "crosstalk"], severities=[3, 5], budget_m=0.5,
                                  n_boot=20)
    summary = validate(settings, tmp_path, route="synthetic", command="test", progress=False)
    assert summary["places"] == 3 and set(summary["by_severity"]) == {"3", "5"}
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["by_severity"]["5"]["quantities"].keys() == quantity_columns(["uniform"]).keys()
    places = pd.read_csv(tmp_path / "places.csv", index_col="sample_id")
    assert places["worst_uniform"].between(0.3, 0.7).all()  # uniform moves the scan by λ
    assert places["hessian_min_eig"].gt(0).all()
    assert "## Severity 3 (headline)" in (tmp_path / "summary.md").read_text()
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["command"] == "test" and "commit" in manifest["git"]
    assert manifest["run_config"]["corruptions"] == ["fog", "crosstalk"]
    with pytest.raises(InputError, match="headline"):
        validate(ValidationSettings(severities=[1]), tmp_path / "x", progress=False)
