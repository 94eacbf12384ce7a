"""Intervals and p-values: Wilson's for a share, resampling (scipy.stats) for the rest.

A share of n units (pairs judged rightly, videos, timely onsets) gets the Wilson score
interval (`wilson`): right at small n and at 0% or 100%, where the bootstrap has nothing to
resample from (every resample of 4 pairs out of 4 judged rightly is 100%: "100 [100, 100]").
Other statistics get 95% percentile bootstrap intervals over units (pairs, or videos where a
line is measured per video), drawn from a generator seeded by `seed`: the same inputs give the
same interval. The percentile method, not BCa: an accuracy of 100% has a degenerate bootstrap
distribution, on which BCa is undefined.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import stats

__all__ = ["interval", "wilson", "values_interval", "pairwise_win", "chance_p"]

_CONFIDENCE = 0.95


def interval(statistic: Callable[[np.ndarray], float], units: int, rounds: int = 1000,
             seed: int = 0) -> tuple[float, float]:
    """The 95% interval of statistic(a resample of range(units) with replacement)."""
    if units == 0:
        return float("nan"), float("nan")
    if units == 1:      # every resample is the one unit
        value = float(statistic(np.zeros(1, dtype=int)))
        return value, value
    found = stats.bootstrap((np.arange(units),), statistic, n_resamples=rounds, vectorized=False,
                            method="percentile", confidence_level=_CONFIDENCE, rng=np.random.default_rng(seed))
    return float(found.confidence_interval.low), float(found.confidence_interval.high)


def wilson(successes: float, count: int) -> tuple[float, float]:
    """The 95% Wilson score interval of the share successes / count (a tie may count one
    half, so `successes` need not be whole): never of zero width for count >= 1, inside [0, 1]."""
    if count == 0:
        return float("nan"), float("nan")
    z = stats.norm.ppf(0.5 + _CONFIDENCE / 2)
    share, spread = successes / count, z * z / count
    centre = (share + spread / 2) / (1 + spread)
    half = z / (1 + spread) * np.sqrt(share * (1 - share) / count + spread / (4 * count))
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def values_interval(values, statistic: Callable[[np.ndarray], float] = np.mean, rounds: int = 1000,
                    seed: int = 0) -> tuple[float, float]:
    """The 95% interval of a statistic of per-unit values (one value per video or pair)."""
    values = np.asarray(values, dtype=float)
    return interval(lambda chosen: statistic(values[chosen]), len(values), rounds, seed)


def pairwise_win(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """1 where a > b, 0.5 where equal, 0 where below."""
    return (a > b) + 0.5 * (a == b)


def chance_p(first: np.ndarray, second: np.ndarray, rounds: int = 1000, seed: int = 0) -> float:
    """Two-sided p-value that the share of pairs with second > first (ties one half) differs
    from 50%: a permutation test that swaps the two members of each pair, which leaves that
    share at 50% on average when the order of the members carries no signal. Exact when
    2^pairs <= rounds."""
    if len(first) == 0:
        return float("nan")
    if len(first) == 1:     # its two orders are all there is: never beyond chance
        return 1.0

    def share(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
        return np.mean(pairwise_win(b, a), axis=axis)

    found = stats.permutation_test((np.asarray(first, float), np.asarray(second, float)), share,
                                   permutation_type="samples", vectorized=True, n_resamples=rounds,
                                   alternative="two-sided", rng=np.random.default_rng(seed))
    return float(found.pvalue)
