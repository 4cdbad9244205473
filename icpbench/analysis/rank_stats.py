"""Rank statistics with bootstrap intervals: Spearman's correlation and the ROC AUC.

Both resample the *places* (rows) with replacement, ``n_boot`` times from one seeded generator, and
report the percentile interval (2.5 %, 97.5 %) of the statistic over the resamples (Efron and
Tibshirani, "An Introduction to the Bootstrap", 1993, ch. 13). A resample on which the statistic
is undefined (all scores tied, or one class missing) is left out; the count of those that remain is
returned with the interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from icpbench.analysis.danger_map import auc
from icpbench.core.errors import InputError

#: Resamples of the bootstrap (default).
N_BOOT = 1000


@dataclass(frozen=True)
class Estimate:
    """A statistic, its bootstrap 95 % percentile interval and the sample it came from.

    Attributes:
        value: the statistic on all places (NaN when undefined).
        lo, hi: the 2.5 % and 97.5 % percentiles over the bootstrap resamples (NaN when none).
        n: number of places.
        n_boot: resamples on which the statistic was defined.
    """

    value: float
    lo: float
    hi: float
    n: int
    n_boot: int

    def as_dict(self) -> dict[str, float | int]:
        """Plain values for JSON."""
        return {"value": self.value, "ci95": [self.lo, self.hi], "n": self.n, "n_boot": self.n_boot}


def _pairs(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise InputError(f"two (n,) arrays of the same length are needed, got {x.shape} and {y.shape}")
    keep = ~(np.isnan(x) | np.isnan(y))  # +-inf is a valid rank (a diverged run, a singular matrix)
    return x[keep], y[keep]


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    if x.size < 3 or np.all(x == x[0]) or np.all(y == y[0]):
        return float("nan")
    return float(stats.spearmanr(x, y).statistic)


def _interval(values: list[float]) -> tuple[float, float, int]:
    v = np.asarray([s for s in values if np.isfinite(s)])
    if v.size == 0:
        return float("nan"), float("nan"), 0
    lo, hi = np.percentile(v, [2.5, 97.5])
    return float(lo), float(hi), int(v.size)


def spearman_ci(x: np.ndarray, y: np.ndarray, n_boot: int = N_BOOT, seed: int = 0) -> Estimate:
    """Spearman's rank correlation of ``x`` and ``y`` (n,) with a bootstrap 95 % interval.

    Places where either value is NaN are dropped; ``inf`` ranks as the largest value.
    """
    x, y = _pairs(x, y)
    rng = np.random.default_rng(seed)
    boot = [_spearman(x[i], y[i]) for i in (rng.integers(0, x.size, x.size) for _ in range(n_boot))]
    lo, hi, kept = _interval(boot)
    return Estimate(_spearman(x, y), lo, hi, n=int(x.size), n_boot=kept)


def _auc(score: np.ndarray, label: np.ndarray) -> float:
    return auc(score[label], score[~label])


def auc_ci(score: np.ndarray, label: np.ndarray, n_boot: int = N_BOOT, seed: int = 0) -> Estimate:
    """ROC AUC of ``score`` (n,) for the boolean ``label`` (n,): P(score of a positive > score of a
    negative) + half the ties (the Mann-Whitney U statistic over n_pos * n_neg), with a bootstrap
    95 % interval. Larger scores are meant to flag positives; 0.5 = no better than chance."""
    s = np.asarray(score, dtype=np.float64)
    lab = np.asarray(label, dtype=bool)
    if s.shape != lab.shape or s.ndim != 1:
        raise InputError(f"score and label must be (n,) arrays of one length, got {s.shape} and "
                         f"{lab.shape}")
    keep = ~np.isnan(s)
    s, lab = s[keep], lab[keep]
    # Mann-Whitney on +-inf: replace them by values just beyond the finite ones (ranks unchanged)
    finite = s[np.isfinite(s)]
    if finite.size:
        span = float(finite.max() - finite.min()) + 1.0
        s = np.where(s == np.inf, finite.max() + span, np.where(s == -np.inf, finite.min() - span, s))
    rng = np.random.default_rng(seed)
    boot = [_auc(s[i], lab[i]) for i in (rng.integers(0, s.size, s.size) for _ in range(n_boot))]
    lo, hi, kept = _interval(boot)
    return Estimate(_auc(s, lab), lo, hi, n=int(s.size), n_boot=kept)
