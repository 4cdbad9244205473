"""Table 1 arithmetic on hand-made results: mean ± std, '% Ours is Larger', ties, drops, pairing,
the all-runs fallback and its mark, the counts table, the CSV columns and the unit per dataset."""

import io
import json
import re

import numpy as np
import pandas as pd
import pytest

from icpbench.core.errors import InputError
from icpbench.harness.report import (
    ALL_RUNS_MARK,
    EMPTY,
    Cell,
    all_pairs_frame,
    counts_frame,
    displacement_frame,
    error_figure,
    error_unit,
    health_warnings,
    pct_reference_larger,
    render,
    run_dataset,
    table1,
    table1_cells,
    table1_frame,
    table1_long,
    transfer_frame,
)
from icpbench.harness.worst_case import worst_rows


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
    shares = all_pairs_frame(df).set_index("Method")
    assert list(shares.index) == ["Original", "Normal"]  # the reference has no row
    assert shares.loc["Normal", "λ=1"] == "33.3% [10-70] of 6"  # 2 of 6, Wilson 9.7-70.0%
    assert re.search(r"\| Normal +\| 33.3% \[10-70\] of 6", text)
    assert "% Ours is larger over converged pairs (the table's %) with its 95% interval" in text
    assert re.search(r"\| Normal +\| 25.0% \[5-70\] of 4", text)  # 1 of 4


def test_displacement_audit_footer(df):
    d = df.assign(disp_max=np.where(df["attack"] == "generator", 1.4, 1.0),
                  frac_over_budget=np.where(df["attack"] == "generator", 0.25, 0.0))
    d.loc[d["attack"] == "none", ["disp_max", "frac_over_budget"]] = 0.0
    audit = displacement_frame(d)
    assert list(audit["Method"]) == ["Normal", "Ours"]  # the clean rows moved nothing
    assert list(audit["λ=1"]) == ["1 / 0.00%", "1.4 / 25.00%"]
    text = table1(d, "md")
    assert "Displacement audit: largest point displacement [m] / mean share" in text
    assert "| Ours     | 1.4 / 25.00% |" in text


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
    assert "| Method" in md and "Runs per cell: runs / converged / pairs" in md
    tex = table1(df, "latex")
    assert tex.startswith("\\begin{tabular}") and tex.count("\\begin{tabular}") == 4  # main, counts, 2 shares
    assert "Runs per cell: runs / converged / pairs" in tex and "% warning: normal" in tex
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


# -- the all-runs fallback, the counts table, the CSV columns and the unit ------------------------
@pytest.fixture
def sparse():
    """Cells the converged-runs rule cannot fill: few converged runs, no converged pair, a failed
    run, an attack run at one budget only."""
    r = []
    for i, e in enumerate([4.0, 5.0, 6.0, 7.0]):
        r += [_row(f"s{i}", "generator", e), _row(f"s{i}", "none", 0.1 * (i + 1))]
    r += [_row("s0", "uniform", 1.0)] + [_row(f"s{i}", "uniform", e, conv=False)
                                         for i, e in ((1, 2.0), (2, 3.0), (3, 8.0))]
    r += [_row(f"s{i}", "normal", e, conv=False) for i, e in enumerate([1.5, 9.0, 2.5])]
    r += [_row("s0", "pgd", 3.0), _row("s1", "pgd", 4.5)]
    r += [_row("s0", "generator", 10.0, budget=2.0), _row("s0", "none", 0.1, budget=2.0),
          _row("s1", "none", 0.3, budget=2.0), _row("s0", "uniform", 2.0, conv=False, budget=2.0),
          {**_row("s0", "normal", np.nan, conv=False, budget=2.0), "status": "failed"}]
    return pd.DataFrame(r)


def _marked(frame: pd.DataFrame) -> set[tuple[str, str]]:
    return {(m, col) for m, row in frame.set_index("Method").iterrows()
            for col, v in row.items() if v.endswith(ALL_RUNS_MARK)}


def test_fallback_figures_are_used_and_marked_exactly_where_the_rule_leaves_nothing(sparse):
    f = table1_frame(sparse).set_index("Method")
    assert list(f.index) == ["Original", "Uniform", "Normal", "PGD (oracle)", "Ours"]
    e1, p1 = "λ=1 Trans Pose Error [m]", "λ=1 % Ours is Larger"
    e2, p2 = "λ=2 Trans Pose Error [m]", "λ=2 % Ours is Larger"
    # the paper's rule where it has enough
    assert f.loc["Original", e1] == "0.25 ± 0.11" and f.loc["Original", p1] == "100.00%"
    assert f.loc["Ours", e1] == "5.50 ± 1.12" and f.loc["PGD (oracle)", p1] == "100.00%"
    # one converged uniform run of four: mean ± std over all four, marked; its one converged pair
    u = np.array([1.0, 2.0, 3.0, 8.0])
    assert f.loc["Uniform", e1] == f"{u.mean():.2f} ± {u.std():.2f} {ALL_RUNS_MARK}" == "3.50 ± 2.69 †"
    assert f.loc["Uniform", p1] == "100.00%"
    # normal never converged: all three runs, and all three pairs (4 > 1.5, 5 < 9, 6 > 2.5)
    n = np.array([1.5, 9.0, 2.5])
    assert f.loc["Normal", e1] == f"{n.mean():.2f} ± {n.std():.2f} †"
    assert f.loc["Normal", p1] == "66.67% †"
    # a single run: its value without a ±, marked only when it did not converge
    assert f.loc["Ours", e2] == "10.00"
    assert f.loc["Uniform", e2] == "2.00 †" and f.loc["Uniform", p2] == "100.00% †"
    # nothing finite (failed run, attack not run at λ=2)
    assert [f.loc[m, c] for m in ("Normal", "PGD (oracle)") for c in (e2, p2)] == [EMPTY] * 4
    assert _marked(f.reset_index()) == {("Uniform", e1), ("Normal", e1), ("Normal", p1),
                                        ("Uniform", e2), ("Uniform", p2)}


def test_marks_are_explained_once_and_absent_when_unused(sparse, df):
    text = table1(sparse, "md")
    foot = [ln for ln in text.splitlines() if ln.startswith(ALL_RUNS_MARK)]
    assert len(foot) == 1 and "over all runs" in foot[0]
    assert sum(ln.startswith(EMPTY) for ln in text.splitlines()) == 1
    assert not _marked(table1_frame(df))
    plain = table1(df, "md")
    assert ALL_RUNS_MARK not in plain and EMPTY not in plain
    tex = table1(sparse, "latex")
    assert "\n† over all runs" in tex and "no pair for the \\%" in tex


@pytest.mark.parametrize("fmt", ["md", "latex", "csv"])
def test_no_placeholder_or_zero_spread_cells(sparse, fmt):
    text = table1(sparse, fmt)
    for bad in ("n/a", "no pairs", "± 0.00", "nan ± nan"):
        assert bad not in text, bad
    one = Cell(mean=1.0, std=0.0, n=1, dropped=0, pct_ref_larger=None, n_pairs=0, runs=1,
               mean_all=1.0, std_all=0.0, n_finite=1)
    fig = error_figure(one)
    assert (fig.value, fig.std, fig.basis) == (1.0, None, "converged")


def test_counts_table_has_the_counts(sparse, df):
    c = counts_frame(sparse).set_index("Method")
    assert list(c.columns) == ["λ=1", "λ=2"]
    assert list(c["λ=1"]) == ["4 / 4 / 4", "4 / 1 / 1", "3 / 0 / 0", "2 / 2 / 2", "4 / 4 / -"]
    assert list(c["λ=2"]) == ["2 / 2 / 1", "1 / 0 / 0", "1 / 0 / 0", "0 / 0 / 0", "1 / 1 / -"]
    c = counts_frame(df).set_index("Method")["λ=1"]
    assert c.to_dict() == {"Original": "2 / 2 / 2", "Normal": "7 / 6 / 4", "Ours": "6 / 5 / -"}
    text = table1(df, "md")
    assert "Runs per cell: runs / converged / pairs" in text
    assert re.search(r"\| Normal +\| 7 / 6 / 4 \|", text)
    assert "converged / dropped" not in text  # no line of counts as text any more


def test_csv_parses_and_orders(sparse):
    back = pd.read_csv(io.StringIO(table1(sparse, "csv")))
    worst = back[back.attack == "worst"]
    assert list(worst["Method"]) == ["Worst of all attacks"] and back.index[-1] == worst.index[0]
    back = back[back.attack != "worst"]
    assert list(back["Method"]) == ["Original", "Uniform", "Normal", "PGD (oracle)", "Ours"]
    assert list(back["attack"]) == ["none", "uniform", "normal", "pgd", "generator"]
    assert back.loc[1, "λ=1 Trans Pose Error [m]"] == "3.50 ± 2.69 †"  # the shown text too
    assert list(back["λ=1 error_basis"]) == ["converged", "all", "all", "converged", "converged"]
    assert list(back["λ=1 converged"]) == [4, 1, 0, 2, 4]
    assert list(back["λ=1 runs"]) == [4, 4, 3, 2, 4]
    assert back["λ=1 mean"].to_numpy() == pytest.approx([0.25, 3.5, 13 / 3, 3.75, 5.5])
    by_error = back.sort_values("λ=1 mean", ascending=False)["attack"].tolist()
    assert by_error == ["generator", "normal", "pgd", "uniform", "none"]
    assert back["λ=1 pct_ours_larger"].iloc[:4].tolist() == pytest.approx([100, 100, 200 / 3, 100])
    assert back["λ=1 pct_basis"].tolist()[:4] == ["converged", "converged", "all", "converged"]
    assert pd.isna(back.loc[4, "λ=1 pct_ours_larger"])  # the reference's own row
    assert pd.isna(back.loc[4, "λ=2 std"]) and back.loc[4, "λ=2 mean"] == 10.0  # one run
    assert pd.isna(back.loc[2, "λ=2 mean"]) and pd.isna(back.loc[3, "λ=2 runs"])
    long = table1_long(sparse)
    assert len(long) == 9 and list(long.columns[:6]) == ["Method", "attack", "target", "budget",
                                                          "metric", "unit"]
    assert long.groupby("attack")["budget"].apply(list).to_dict()["none"] == [1.0, 2.0]


def test_worst_of_all_attacks_takes_the_per_scan_maximum_and_names_the_winner(sparse):
    """Per (sample, budget): the largest finite error over the attacks (never ``none``); a row
    over the budget does not count; the winner is named; a single attack gets no such row."""
    w = worst_rows(sparse).set_index(["sample_id", "budget"])
    att = sparse[sparse.attack != "none"]
    expect = att.groupby(["sample_id", "budget"]).trans_err_xy.max().dropna()
    np.testing.assert_allclose(w.trans_err_xy.loc[expect.index], expect)
    assert w.loc[("s1", 1.0), "winner"] == "normal" and w.loc[("s3", 1.0), "winner"] == "uniform"
    over = sparse.assign(frac_over_budget=np.where(sparse.attack == "normal", 0.1, 0.0))
    assert worst_rows(over).set_index(["sample_id", "budget"]).loc[("s1", 1.0), "winner"] == \
        "generator"  # 5.0: normal's 9.0 broke the budget
    assert worst_rows(sparse[sparse.attack.isin(["none", "uniform"])]).empty
    text = table1(sparse, "md")
    assert re.search(r"^\| Worst of all attacks +\| 5\.00 ± 1\.00 ", text, flags=re.M)  # converged
    assert "won by λ=1: generator 2, normal 1, uniform 1; λ=2: generator 1" in text
    # the worst of all includes Ours: its "% Ours is larger" is not a comparison (0% would mislead)
    assert re.search(r"^\| Worst of all attacks +\| 5\.00 ± 1\.00 +\| - ", text, flags=re.M)
    assert not re.search(r"^\| Worst of all attacks +\| [0-9.]+% \[", text, flags=re.M)


def _write_run(folder, frame, dataset):
    folder.mkdir()
    frame.assign(strict=False, meta="{}", extra="{}").to_csv(folder / "results.csv", index=False)
    if dataset is not None:
        (folder / "manifest.json").write_text(json.dumps({"config": {"dataset": dataset}}))


@pytest.mark.parametrize("dataset, unit", [("objects", "units"), ("meshes", "units"),
                                           ("lidar-sim", "m"), (None, "m")])
def test_unit_header_follows_the_runs_dataset(df, tmp_path, dataset, unit):
    from typer.testing import CliRunner

    from icpbench.cli import app

    assert error_unit("trans_err_xy", dataset) == unit and error_unit("rot_err", dataset) == "rad"
    _write_run(tmp_path / "run", df, dataset)
    assert run_dataset(tmp_path / "run") == dataset == run_dataset(tmp_path / "run" / "results.csv")
    cols = table1_frame(df, dataset=dataset).columns
    assert f"λ=1 Trans Pose Error [{unit}]" in cols
    for fmt, head in (("md", "| Method"), ("csv", "Method,")):
        res = CliRunner().invoke(app, ["table", str(tmp_path / "run"), "--format", fmt])
        assert res.exit_code == 0, res.output
        assert res.output.startswith(head) and f"Trans Pose Error [{unit}]" in res.output
        other = "[m]" if unit == "units" else "[units]"
        assert other not in res.output
