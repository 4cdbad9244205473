"""The budget curve of a large-budget ensemble run: the right points, means and ratios."""

import numpy as np
import pandas as pd
import pytest

from icpbench.analysis.budget_curve import budget_curve
from icpbench.attacks.ensemble import MEMBERS, column
from icpbench.core.errors import InputError


def _rows(trace: bool = True) -> pd.DataFrame:
    base = {"attack": "ensemble", "target": "p2point", "budget": 1.0}
    scans = []
    for i, (members, at20, at50, final) in enumerate([(1.2, 1.5, 1.6, 1.8), (1.0, 1.1, 1.3, 1.4)]):
        r = {**base, "sample_id": f"s{i}", "trans_err_xy": final}
        for m in MEMBERS:  # the search runs last
            r[f"extra.{column(m)}"] = final if m == "search" else members - 0.1 * (m != "pgd")
        r[f"extra.{column('uniform')}"] = 1.0
        if trace:
            r["extra.search_best_at_20"], r["extra.search_best_at_50"] = at20, at50
        scans.append(r)
    scans.append({**base, "attack": "none", "sample_id": "s0", "trans_err_xy": 0.1})
    return pd.DataFrame(scans)


def test_curve_points_means_and_ratios():
    c = budget_curve(_rows(), search_queries=100)
    assert c.queries.tolist() == [0, 20, 50, 100]
    np.testing.assert_allclose(c["mean"], [1.1, 1.3, 1.45, 1.6])  # q = 0: best fixed member (pgd)
    np.testing.assert_allclose(c.over_uniform, c["mean"] / 1.0)
    assert (c.scans == 2).all() and (c.target == "p2point").all()


def test_no_trace_is_a_clear_error():
    with pytest.raises(InputError, match="no search trace"):
        budget_curve(_rows(trace=False), search_queries=20)
    with pytest.raises(InputError, match="no ensemble rows"):
        budget_curve(_rows().query("attack == 'none'"), search_queries=20)


def test_a_member_that_did_not_run_stays_off_the_curve():
    rows = _rows().drop(columns=[f"extra.{column('valley')}"])  # e.g. --ensemble-param members=
    pd.testing.assert_frame_equal(budget_curve(rows, search_queries=100),
                                  budget_curve(_rows(), search_queries=100))
    rows = _rows()
    rows.loc[rows.attack == "ensemble", f"extra.{column('valley')}"] = 1.5  # before the search
    c = budget_curve(rows, search_queries=100)
    np.testing.assert_allclose(c["mean"].iloc[0], 1.5)
