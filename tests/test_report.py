"""Table 1 arithmetic on hand-made results: mean ± std, '% Ours is Larger', ties, drops, pairing."""

import numpy as np
import pandas as pd
import pytest

from icpbench.core.errors import InputError
from icpbench.harness.report import (
    health_warnings,
    pct_reference_larger,
    render,
    table1,
    table1_cells,
    table1_frame,
    transfer_frame,
)


def _row(sample, attack, err, conv=True, budget=1.0, target="p2plane", seed=0):
    return {"sample_id": sample, "attack": attack, "target": target, "budget": budget,
            "seed": seed, "trans_err_xy": err, "converged": conv,
            "status": "ok" if conv else "not_converged"}


@pytest.fixture
def df():
    rows = [
        # generator (reference) vs normal: s1 larger, s2 tie, s3 smaller, s4 ref not converged,
        # s5 only normal (unpaired), s6 normal not converged.
        _row("s1", "generator", 2.0), _row("s1", "normal", 1.0),
        _row("s2", "generator", 1.5), _row("s2", "normal", 1.5),
        _row("s3", "generator", 1.0), _row("s3", "normal", 1.2),
        _row("s4", "generator", 9.0, conv=False), _row("s4", "normal", 1.1),
        _row("s5", "normal", 1.3),
        _row("s6", "generator", 3.0), _row("s6", "normal", 7.0, conv=False),
        # a different seed is a different pair
        _row("s1", "generator", 1.0, seed=1), _row("s1", "normal", 2.0, seed=1),
        _row("s1", "none", 0.1), _row("s2", "none", 0.3),
    ]
    return pd.DataFrame(rows)


def test_pct_reference_larger_counts_ties_drops_and_unpaired(df):
    pct, n = pct_reference_larger(df, "normal", "generator")
    # pairs: (s1,seed0) larger, (s2) tie, (s3) smaller, (s1,seed1) smaller -> 1 of 4
    assert n == 4
    assert pct == pytest.approx(25.0)


def test_pct_reference_larger_with_non_converged_runs(df):
    pct, n = pct_reference_larger(df, "normal", "generator", converged_only=False)
    # + s4 (ref 9.0 > 1.1, larger) and s6 (3.0 < 7.0, smaller): 2 of 6
    assert n == 6
    assert pct == pytest.approx(100 * 2 / 6)
    text = table1(df, "md")
    assert "% Ours is larger incl. non-converged runs" in text
    assert "Normal λ=1: 33.3% of 6" in text


def test_displacement_audit_footer(df):
    d = df.assign(disp_max=np.where(df["attack"] == "generator", 1.4, 1.0),
                  frac_over_budget=np.where(df["attack"] == "generator", 0.25, 0.0))
    d.loc[d["attack"] == "none", ["disp_max", "frac_over_budget"]] = 0.0
    text = table1(d, "md")
    lines = [ln for ln in text.splitlines() if ln.startswith("displacement audit")]
    assert len(lines) == 2  # generator and normal; the clean rows moved nothing
    assert any("max 1.4, 25.00% of points over λ" in ln for ln in lines)


def test_mean_std_over_converged_only(df):
    cells = table1_cells(df, reference="generator")
    c = cells[("normal", 1.0)]
    normal_ok = [1.0, 1.5, 1.2, 1.1, 1.3, 2.0]
    assert c.n == 6 and c.dropped == 1
    assert c.mean == pytest.approx(np.mean(normal_ok))
    assert c.std == pytest.approx(np.std(normal_ok))
    g = cells[("generator", 1.0)]
    assert g.n == 5 and g.dropped == 1 and g.pct_ref_larger is None


def test_table_rows_ordered_and_reference_last(df):
    frame = table1_frame(df)
    assert list(frame["Method"]) == ["Original", "Normal", "Ours"]
    assert frame.iloc[-1]["λ=1 % Ours is Larger"] == "-"
    assert frame.iloc[1]["λ=1 % Ours is Larger"] == "25.00%"
    assert frame.iloc[0]["λ=1 % Ours is Larger"] == "100.00%"
    assert frame.iloc[0]["λ=1 Trans Pose Error [m]"] == "0.20 ± 0.10"


def test_missing_reference_is_said_not_invented(df):
    frame = table1_frame(df[df["attack"] != "generator"])
    assert set(frame["λ=1 % Ours is Larger"]) == {"(generator not run)"}


def test_formats_parse_back(df):
    csv_text = render(table1_frame(df), "csv")
    back = pd.read_csv(pd.io.common.StringIO(csv_text))
    assert list(back["Method"]) == ["Original", "Normal", "Ours"]
    md = table1(df, "md")
    assert "| Method" in md and "n converged / dropped / pairs" in md
    tex = table1(df, "latex")
    assert "\\toprule" in tex and "% n converged" in tex
    with pytest.raises(InputError):
        render(table1_frame(df), "html")


def test_health_warning_over_ten_percent(df):
    w = health_warnings(df)
    assert any("generator on p2plane" in x for x in w)
    assert any("normal on p2plane" in x for x in w)
    assert not any("none on" in x for x in w)


def test_several_targets_need_choice_and_transfer_table(df):
    df2 = pd.concat([df, df.assign(target="open3d", trans_err_xy=df["trans_err_xy"] * 2)])
    with pytest.raises(InputError, match="several targets"):
        table1_frame(df2)
    tr = transfer_frame(df2, 1.0)
    assert list(tr.columns) == ["Attack", "p2plane", "open3d"]
    assert tr.iloc[0]["open3d"].startswith("0.40 ± 0.20")


def test_transfer_vs_baseline_difference_and_share():
    from icpbench.harness.report import transfer_vs_baseline

    rows = []
    for t, (pgd_errs, conv) in {"p2plane": ([3.0, 2.0, 0.5], True),
                                "kiss-icp": ([1.0, 1.0, 1.0], False)}.items():
        for i, e in enumerate(pgd_errs):
            rows += [_row(f"s{i}", "pgd", e, conv=conv if i == 0 else True, target=t),
                     _row(f"s{i}", "normal", 1.0 + 0.1 * i, target=t)]
    frame = transfer_vs_baseline(pd.DataFrame(rows))
    assert list(frame["Attack"]) == ["PGD (oracle) vs Normal"]
    # p2plane: means 1.833 vs 1.1 -> +0.73; pgd larger on s0, s1 -> 67% of 3
    assert frame.loc[0, "p2plane"] == "+0.73 m, 67% of 3"
    # kiss-icp: s0 not converged (left out of the mean, kept in the share): 1.0 vs 1.1 -> -0.10
    assert frame.loc[0, "kiss-icp"] == "-0.10 m, 0% of 3"
    with pytest.raises(InputError, match="baseline"):
        transfer_vs_baseline(pd.DataFrame(rows), baseline="uniform")
