"""How sure a leaderboard is: bootstrap intervals of each variant's mean worst case and rank, and
the agreement of two boards' rankings.

A board's mean over 48 scans is an estimate; a reader needs to know which differences between
variants the scans support. The scans are resampled with replacement, *the same resample for
every variant* (the variants are measured on the same scans, so their errors are paired), ``n_boot``
times from one seeded generator; each resample gives every variant a mean and a rank, and the 2.5 /
97.5 % percentiles over the resamples are the intervals (Efron and Tibshirani, "An Introduction to
the Bootstrap", 1993, ch. 13; rank intervals as in Hall and Miller, "Using the bootstrap to
quantify the authority of an empirical ranking", Ann. Statist. 2009). Rank 1 is the most robust
(smallest mean worst case). Two boards (e.g. two data domains) agree as much as Kendall's tau of
their rankings over the variants both hold says (Kendall, "A new measure of rank correlation",
Biometrika 1938); the interval of tau resamples each board's own scans, independently (two domains
share no scan), and ranks the resampled means. Two boards of the *same* scans (one domain under two
protocol versions) compare variant by variant: the ratio of their mean worst cases with a paired
interval, the scans resampled together for both (:func:`paired_ratios`).

Units: errors in metres.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import numpy as np
import pandas as pd
from scipy import stats

from icpbench.core.errors import InputError

#: Resamples of the bootstrap (default).
N_BOOT = 1000


def bootstrap_ranks(errors: pd.DataFrame, n_boot: int = N_BOOT, seed: int = 0) -> pd.DataFrame:
    """Means and ranks of the variants with their bootstrap 95 % percentile intervals.

    Args:
        errors: scans x variants worst-case errors (metres); NaN where a scan has no finite error
            for a variant (diverged), which its mean leaves out.
        n_boot: resamples of the scans.
        seed: seed of the resampling.

    Returns:
        One row per variant (index: the columns of ``errors``): ``mean``, ``mean_lo``,
        ``mean_hi``, ``rank`` (on all scans; ties share the average rank), ``rank_lo``,
        ``rank_hi``.

    Raises:
        InputError: no scan or no variant, or ``n_boot`` < 1.
    """
    if errors.empty or errors.shape[1] == 0:
        raise InputError("bootstrap of a board: no scans or no variants")
    if int(n_boot) < 1:
        raise InputError(f"bootstrap of a board: n_boot must be >= 1, got {n_boot}")
    X = errors.to_numpy(dtype=float)
    S = X.shape[0]
    idx = np.random.default_rng(seed).integers(0, S, size=(int(n_boot), S))
    with warnings.catch_warnings():  # a variant with no finite scan has a NaN mean
        warnings.simplefilter("ignore", category=RuntimeWarning)
        means = np.nanmean(X[idx], axis=1)  # (n_boot, V)
        full = np.nanmean(X, axis=0)
    ranks = stats.rankdata(np.where(np.isfinite(means), means, np.inf), axis=1)
    rank_full = stats.rankdata(np.where(np.isfinite(full), full, np.inf))
    with warnings.catch_warnings():  # an all-NaN column has NaN percentiles
        warnings.simplefilter("ignore", category=RuntimeWarning)
        lo, hi = np.nanpercentile(means, [2.5, 97.5], axis=0)
    rlo, rhi = np.percentile(ranks, [2.5, 97.5], axis=0)
    return pd.DataFrame({"mean": full, "mean_lo": lo, "mean_hi": hi, "rank": rank_full,
                         "rank_lo": rlo, "rank_hi": rhi}, index=errors.columns)


def kendall_agreement(a: Mapping[str, float], b: Mapping[str, float]) -> tuple[float, float, int]:
    """Kendall's tau-b of two rankings given as variant -> score (e.g. the mean amplification of
    two boards), over the variants both hold with a finite score.

    Returns:
        ``(tau, p_value, n)``: tau in [-1, 1] (1: the same order), the two-sided p-value of no
        association, and the number of variants compared (tau and p are NaN below 2).
    """
    common = [v for v in a if v in b and np.isfinite(a[v]) and np.isfinite(b[v])]
    if len(common) < 2:
        return float("nan"), float("nan"), len(common)
    res = stats.kendalltau([a[v] for v in common], [b[v] for v in common])
    return float(res.statistic), float(res.pvalue), len(common)


def kendall_interval(a: pd.DataFrame, b: pd.DataFrame, n_boot: int = N_BOOT, seed: int = 0
                     ) -> tuple[float, float]:
    """Bootstrap 95 % percentile interval of Kendall's tau between two boards' rankings.

    Each resample draws each board's scans with replacement, independently (the boards may be
    measured on different scans: two domains), ranks the variants both boards hold by their
    resampled mean, and takes tau-b of the two rankings (:func:`kendall_agreement`).

    Args:
        a, b: scans x variants worst-case errors (metres; NaN: no finite error, left out of the
            mean) of the two boards, each at its ranking budget.
        n_boot: resamples.
        seed: seed of the resampling.

    Returns:
        ``(lo, hi)``: the 2.5 / 97.5 % percentiles of tau over the resamples where it is defined;
        NaN when the boards share fewer than 2 variants.

    Raises:
        InputError: ``n_boot`` < 1, or a board with no scan.
    """
    if int(n_boot) < 1:
        raise InputError(f"bootstrap of tau: n_boot must be >= 1, got {n_boot}")
    if a.empty or b.empty:
        raise InputError("bootstrap of tau: a board has no scans")
    common = [v for v in a.columns if v in b.columns]
    if len(common) < 2:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    X, Y = a[common].to_numpy(dtype=float), b[common].to_numpy(dtype=float)
    taus = np.full(int(n_boot), np.nan)
    with warnings.catch_warnings():  # an all-NaN resampled column, or a constant ranking
        warnings.simplefilter("ignore", category=RuntimeWarning)
        for k in range(int(n_boot)):
            mx = np.nanmean(X[rng.integers(0, X.shape[0], X.shape[0])], axis=0)
            my = np.nanmean(Y[rng.integers(0, Y.shape[0], Y.shape[0])], axis=0)
            taus[k] = kendall_agreement(dict(zip(common, mx, strict=True)),
                                        dict(zip(common, my, strict=True)))[0]
    taus = taus[np.isfinite(taus)]
    if taus.size == 0:
        return float("nan"), float("nan")
    lo, hi = np.percentile(taus, [2.5, 97.5])
    return float(lo), float(hi)


def paired_ratios(a: pd.DataFrame, b: pd.DataFrame, n_boot: int = N_BOOT, seed: int = 0
                  ) -> pd.DataFrame:
    """Per variant, the ratio of board ``a``'s mean worst case to board ``b``'s over the scans both
    hold, with a paired bootstrap 95 % percentile interval (each resample draws the common scans
    with replacement and uses the same draw for both boards, whose errors are paired by scan).

    Args:
        a, b: scans x variants worst-case errors (metres; index: scan ids; NaN: no finite error,
            left out of that board's mean).
        n_boot: resamples.
        seed: seed of the resampling.

    Returns:
        One row per variant both boards hold, in ``a``'s order: ``scans`` (common scans),
        ``mean_a``, ``mean_b`` (metres), ``ratio``, ``ratio_lo``, ``ratio_hi``, ``larger``
        (share of the common scans where ``a`` is larger by more than 1 mm), ``smaller``. Empty
        when the boards share no scan or no variant.

    Raises:
        InputError: ``n_boot`` < 1.
    """
    if int(n_boot) < 1:
        raise InputError(f"bootstrap of a ratio: n_boot must be >= 1, got {n_boot}")
    cols = ["scans", "mean_a", "mean_b", "ratio", "ratio_lo", "ratio_hi", "larger", "smaller"]
    scans = a.index.intersection(b.index)
    variants = [v for v in a.columns if v in b.columns]
    if len(scans) == 0 or not variants:
        return pd.DataFrame(columns=cols, dtype=float)
    X = a.loc[scans, variants].to_numpy(dtype=float)
    Y = b.loc[scans, variants].to_numpy(dtype=float)
    idx = np.random.default_rng(seed).integers(0, len(scans), size=(int(n_boot), len(scans)))
    with warnings.catch_warnings():  # an all-NaN (resampled) column has a NaN mean
        warnings.simplefilter("ignore", category=RuntimeWarning)
        mx, my = np.nanmean(X, axis=0), np.nanmean(Y, axis=0)
        boot = np.nanmean(X[idx], axis=1) / np.nanmean(Y[idx], axis=1)  # (n_boot, V)
        lo, hi = np.nanpercentile(boot, [2.5, 97.5], axis=0)
    both = np.isfinite(X) & np.isfinite(Y)
    return pd.DataFrame({
        "scans": float(len(scans)), "mean_a": mx, "mean_b": my, "ratio": mx / my,
        "ratio_lo": lo, "ratio_hi": hi,
        "larger": (both & (X > Y + 1e-3)).sum(axis=0) / len(scans),
        "smaller": (both & (X < Y - 1e-3)).sum(axis=0) / len(scans)}, index=variants)[cols]
