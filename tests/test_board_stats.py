"""How sure a board is: paired bootstrap intervals of means and ranks, and Kendall's tau."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from icpbench.core.errors import InputError
from icpbench.harness.board_stats import (
    bootstrap_ranks,
    kendall_agreement,
    kendall_interval,
    paired_ratios,
)


def test_paired_resampling_keeps_a_uniformly_worse_variant_behind():
    """B is A plus 0.1 m on every scan: every paired resample ranks A first, however noisy A is;
    C equals A in law but not per scan, so their ranks are not told apart."""
    rng = np.random.default_rng(1)
    a = rng.uniform(1.0, 5.0, 48)
    c = rng.permutation(a)
    ab = bootstrap_ranks(pd.DataFrame({"A": a, "B": a + 0.1}), n_boot=500)
    assert ab.rank_lo.tolist() == [1, 2] and ab.rank_hi.tolist() == [1, 2]  # always behind A
    ac = bootstrap_ranks(pd.DataFrame({"A": a, "C": c}), n_boot=500)
    assert ac.rank_lo.tolist() == [1, 1] and ac.rank_hi.tolist() == [2, 2]  # not told apart
    ci = bootstrap_ranks(pd.DataFrame({"A": a, "B": a + 0.1, "C": c}), n_boot=500)
    np.testing.assert_allclose(ci["mean"], [a.mean(), a.mean() + 0.1, a.mean()])
    assert (ci.mean_lo < ci["mean"]).all() and (ci["mean"] < ci.mean_hi).all()
    # the interval of the mean narrows like 1/sqrt(n): half the width with four times the scans
    wide = bootstrap_ranks(pd.DataFrame({"A": a[:12]}), n_boot=2000)
    narrow = bootstrap_ranks(pd.DataFrame({"A": np.tile(a[:12], 4)}), n_boot=2000)
    ratio = float((narrow.mean_hi - narrow.mean_lo).iloc[0] / (wide.mean_hi - wide.mean_lo).iloc[0])
    assert 0.4 < ratio < 0.6


def test_a_diverged_scan_is_left_out_and_a_variant_without_scans_ranks_last():
    errors = pd.DataFrame({"A": [1.0, np.nan, 3.0], "B": [np.nan] * 3, "C": [4.0, 4.0, 4.0]})
    ci = bootstrap_ranks(errors, n_boot=200)
    assert ci.loc["A", "mean"] == 2.0 and np.isnan(ci.loc["B", "mean"])
    assert ci.loc["B", "rank"] == 3 and ci.loc["B", "rank_lo"] >= 2.5  # ties A on all-NaN draws
    with pytest.raises(InputError):
        bootstrap_ranks(pd.DataFrame(), n_boot=10)
    with pytest.raises(InputError):
        bootstrap_ranks(errors, n_boot=0)


def test_kendall_agreement_over_common_variants():
    a = {"p2point": 2.5, "kiss": 2.2, "gicp": 18.0, "only-a": 1.0}
    assert kendall_agreement(a, {"p2point": 3.0, "kiss": 2.0, "gicp": 9.0})[::2] == (1.0, 3)
    tau, _, n = kendall_agreement(a, {"p2point": 1.0, "kiss": 2.0, "gicp": 3.0})
    assert n == 3 and tau == pytest.approx(1 / 3)  # one of three pairs swapped
    tau, p, n = kendall_agreement(a, {"kiss": 1.0, "x": 2.0})
    assert n == 1 and np.isnan(tau) and np.isnan(p)


def test_kendall_interval_is_sure_of_separated_rankings_and_wide_for_ties():
    rng = np.random.default_rng(3)
    cols = ["a", "b", "c", "d"]
    # four variants 1 m apart with 0.1 m noise: every resample keeps the order
    far = pd.DataFrame(np.arange(1.0, 5.0) + 0.1 * rng.standard_normal((48, 4)), columns=cols)
    other = pd.DataFrame(np.arange(1.0, 5.0) + 0.1 * rng.standard_normal((30, 4)), columns=cols)
    assert kendall_interval(far, other) == (1.0, 1.0)
    assert kendall_interval(far, other[cols[::-1]].set_axis(cols, axis=1)) == (-1.0, -1.0)
    # the same means, 2 m of noise: the rankings of resamples disagree, the interval is wide
    near = pd.DataFrame(np.arange(1.0, 5.0) * 0.05 + 2 * rng.standard_normal((48, 4)), columns=cols)
    lo, hi = kendall_interval(near, near.copy(), seed=1)
    assert lo <= -0.3 and hi >= 0.6
    # only the variants both boards hold count; NaN below two; a board without scans is refused
    assert kendall_interval(far.assign(x=9.0), other) == (1.0, 1.0)
    assert all(np.isnan(kendall_interval(far[["a"]], other[["a", "b"]])))
    with pytest.raises(InputError):
        kendall_interval(far.iloc[:0], other)
    with pytest.raises(InputError):
        kendall_interval(far, other, n_boot=0)


def test_paired_ratios_pair_scans_and_their_interval_holds_the_ratio():
    rng = np.random.default_rng(3)
    scans = [f"s{i}" for i in range(40)]
    b = pd.DataFrame({"x": rng.gamma(2.0, 2.0, 40), "y": rng.gamma(2.0, 1.0, 40)}, index=scans)
    # a: x 10% larger on every scan (a sure ratio of 1.1), y with heavy noise; listed in
    # another order, with two scans b lacks and one variant b lacks
    a = pd.DataFrame({"y": b.y * rng.uniform(0.2, 1.8, 40), "x": 1.1 * b.x, "z": 1.0},
                     index=scans)[::-1]
    a = pd.concat([a, pd.DataFrame({"x": [99.0, 99.0], "y": 1.0, "z": 1.0}, index=["n1", "n2"])])
    r = paired_ratios(a, b, n_boot=500)
    assert list(r.index) == ["y", "x"] and (r.scans == 40).all()
    np.testing.assert_allclose(r.loc["x", ["ratio", "ratio_lo", "ratio_hi"]], 1.1, rtol=1e-12)
    assert r.loc["x", "larger"] == 1.0 and r.loc["x", "smaller"] == 0.0
    y = r.loc["y"]
    assert np.isclose(y.ratio, a.loc[scans, "y"].mean() / b.y.mean())
    assert y.ratio_lo < y.ratio < y.ratio_hi and y.ratio_hi - y.ratio_lo > 0.1
    assert np.isclose(y.larger + y.smaller, 1.0)
    # boards of different scans (two domains) pair nothing
    assert paired_ratios(a.rename(index=lambda s: "o" + s), b).empty
    with pytest.raises(InputError, match="n_boot"):
        paired_ratios(a, b, n_boot=0)
