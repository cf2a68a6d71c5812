"""Aggregates over seeds with their intervals, as rliable defines them (Agarwal et al., 2021, "Deep RL at the edge of
the statistical precipice"), and the verdict a claim takes from an interval.

Scores are a matrix [runs, tasks]: a run is a seed (a team), a task what it was scored on (a layout, a held-out level
set, a partner). The interval is rliable's stratified bootstrap: each resample draws the runs again with replacement,
independently within each task, and takes the aggregate (the mean, or the interquartile mean over every run and
task); the percentile interval of the resamples' aggregates. Two conditions' runs are independent seeds, so a
difference between them resamples each condition's runs on its own (rliable's `StratifiedIndependentBootstrap`).

A claim holds when its whole interval lies on the claimed side of the threshold, does not hold when the whole
interval lies on the other side, and is inconclusive otherwise.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy import stats

RESAMPLES = 20_000
CONFIDENCE = 0.95
HOLDS, DOES_NOT_HOLD, INCONCLUSIVE = "holds", "does not hold", "inconclusive"


def mean(scores: np.ndarray) -> np.ndarray:
    """The mean over runs and tasks of scores [..., runs, tasks] -> [...]."""
    return scores.mean(axis=(-2, -1))


def interquartile_mean(values: np.ndarray, axis: int = -1) -> np.ndarray:
    """The mean of the middle half of the values along `axis` (a quarter cut off at either end)."""
    return stats.trim_mean(values, 0.25, axis=axis)


def iqm(scores: np.ndarray) -> np.ndarray:
    """The interquartile mean over runs and tasks (rliable's `aggregate_iqm`): [..., runs, tasks] -> [...]."""
    return interquartile_mean(scores.reshape(*scores.shape[:-2], -1))


class Estimate(NamedTuple):
    """An aggregate and its interval."""

    value: float
    low: float
    high: float

    def __str__(self) -> str:
        return f"{self.value:.2f} [{self.low:.2f}, {self.high:.2f}]"


def stratified_resamples(scores: np.ndarray, resamples: int, rng: np.random.Generator) -> np.ndarray:
    """[resamples, runs, tasks]: each resample's runs drawn again with replacement, independently within each task."""
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2 or 0 in scores.shape:
        raise ValueError(f"scores must be a matrix [runs, tasks] with at least one of each, got shape {scores.shape}")
    runs, tasks = scores.shape
    drawn = rng.integers(0, runs, size=(resamples, runs, tasks))
    return scores[drawn, np.arange(tasks)]


def interval(scores: np.ndarray, aggregate: Callable[[np.ndarray], np.ndarray] = iqm, resamples: int = RESAMPLES,
             confidence: float = CONFIDENCE, seed: int = 0) -> Estimate:
    """The aggregate of scores [runs, tasks] with its stratified bootstrap percentile interval."""
    resampled = aggregate(stratified_resamples(scores, resamples, np.random.default_rng(seed)))
    return Estimate(float(aggregate(np.asarray(scores, dtype=np.float64))), *percentiles(resampled, confidence))


def difference(first: np.ndarray, second: np.ndarray, aggregate: Callable[[np.ndarray], np.ndarray] = mean,
               resamples: int = RESAMPLES, confidence: float = CONFIDENCE, seed: int = 0) -> Estimate:
    """aggregate(first) - aggregate(second), two conditions' scores [runs, tasks] on the same tasks (their runs may
    differ in number), with the interval of the difference, each condition's runs resampled on their own."""
    first, second = np.asarray(first, dtype=np.float64), np.asarray(second, dtype=np.float64)
    if first.shape[1:] != second.shape[1:]:
        raise ValueError(f"the two conditions must be scored on the same tasks: {first.shape} and {second.shape}")
    rng = np.random.default_rng(seed)
    resampled = (aggregate(stratified_resamples(first, resamples, rng))
                 - aggregate(stratified_resamples(second, resamples, rng)))
    return Estimate(float(aggregate(first) - aggregate(second)), *percentiles(resampled, confidence))


def percentiles(values: np.ndarray, confidence: float) -> tuple[float, float]:
    tail = 100 * (1 - confidence) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def verdict(estimate: Estimate, threshold: float = 0.0, above: bool = True) -> str:
    """A claim that the quantity lies above `threshold` (`above`, else below): "holds" where the whole interval lies
    on that side, "does not hold" where it lies wholly on the other side, "inconclusive" otherwise."""
    low, high = (estimate.low - threshold, estimate.high - threshold) if above else (
        threshold - estimate.high, threshold - estimate.low)
    return HOLDS if low > 0 else DOES_NOT_HOLD if high < 0 else INCONCLUSIVE
