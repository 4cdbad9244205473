"""The harness on `objects` (budgets 0.02 and 0.05, c = 0.15, d_max = 0.3): the uniform
shift is recovered as an error equal to the budget, the clean scan sits at the noise floor, and the
displacement audit equals the budget where it should."""

import pytest

from icpbench.harness.report import table1_frame
from icpbench.harness.results import load_results
from icpbench.harness.runner import RunConfig, run


@pytest.fixture(scope="module")
def df(tmp_path_factory):
    out = tmp_path_factory.mktemp("objects-run")
    cfg = RunConfig(dataset="objects", attacks=["none", "uniform", "normal", "sector"],
                    targets=["p2plane"], budgets=[0.02, 0.05], samples=10, batch_size=5)
    run(cfg, out, progress=False)
    return load_results(out)


def test_uniform_error_is_the_budget(df):
    for b in (0.02, 0.05):
        u = df[(df["attack"] == "uniform") & (df["budget"] == b) & df["converged"]]
        assert len(u) >= 7
        assert abs(u["trans_err_xy"].mean() - b) < 0.10 * b, u["trans_err_xy"].mean()


def test_clean_scan_at_noise_floor(df):
    n = df[(df["attack"] == "none") & df["converged"]]
    assert len(n) >= 7
    assert n["trans_err_xy"].mean() < 0.01  # noise std 0.025 averages out over 2,048 points


def test_displacement_audit_equals_budget(df):
    for a in ("uniform", "normal"):
        for b in (0.02, 0.05):
            r = df[(df["attack"] == a) & (df["budget"] == b)]
            assert (r["disp_max"] - b).abs().max() < 1e-6
            assert (r["disp_mean"] - b).abs().max() < 1e-6
            assert (r["frac_over_budget"] == 0).all()
    s = df[df["attack"] == "sector"]
    assert ((s["disp_max"] - s["budget"]).abs() < 1e-6).all()
    assert (df[df["attack"] == "none"]["disp_max"] == 0).all()
    assert df[df["attack"] == "sector"]["extra.analytic_xy"].notna().all()


def test_table_shows_four_decimals_for_object_budgets(df):
    frame = table1_frame(df, reference="normal")
    cell = frame[frame["Method"] == "Uniform"]["λ=0.05 Trans Pose Error [m]"].iloc[0]
    mean = cell.split(" ± ")[0]
    assert len(mean) == 6 and abs(float(mean) - 0.05) < 0.005, cell
