"""Aggregates over seeds and their intervals (`trainers.evaluation.intervals`): rliable's stratified bootstrap, and
the verdict a claim takes from an interval."""

import warnings

import numpy as np
import pytest

from trainers.evaluation.intervals import (
    DOES_NOT_HOLD,
    HOLDS,
    INCONCLUSIVE,
    Estimate,
    difference,
    interval,
    iqm,
    mean,
    stratified_resamples,
    verdict,
)

# Five seeds x three tasks, by hand: the tasks on different scales, one seed an outlier on the second task.
SCORES = np.array([[1.0, 4.0, 0.2],
                   [1.5, 3.0, 0.0],
                   [0.5, 9.0, 0.4],
                   [1.2, 3.5, 0.1],
                   [0.8, 4.5, 0.3]])


@pytest.mark.parametrize("aggregate", [iqm, mean], ids=["iqm", "mean"])
def test_the_stratified_interval_is_rliables_own(aggregate):
    rliable = pytest.importorskip("rliable.library")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # arch's note on its random_state argument, which rliable passes
        points, intervals = rliable.get_interval_estimates(
            {"scores": SCORES}, lambda scores: np.array([aggregate(scores)]), reps=4_000,
            random_state=np.random.RandomState(0))
    ours = interval(SCORES, aggregate, resamples=4_000)
    assert ours.value == pytest.approx(float(points["scores"][0]), abs=1e-12)
    low, high = intervals["scores"][:, 0]
    # Two Monte-Carlo estimates of the same percentiles, 4,000 resamples each (rliable calls the aggregate once per
    # resample): within 0.05 of each other, where the interval is about 0.6 (IQM) and 1.3 (mean) wide.
    assert (ours.low, ours.high) == pytest.approx((low, high), abs=0.05)
    assert ours.low < ours.value < ours.high


def test_each_task_is_resampled_from_its_own_runs_alone():
    resampled = stratified_resamples(SCORES, 500, np.random.default_rng(1))
    assert resampled.shape == (500, 5, 3)
    for task in range(3):
        assert set(np.unique(resampled[..., task])) <= set(SCORES[:, task])
    assert len(np.unique(resampled[:, :, 1].sum(1))) > 10  # the runs are drawn again, not kept


def test_a_difference_resamples_each_conditions_seeds_on_their_own():
    better = SCORES + 1.0
    shifted = difference(better, SCORES)
    assert shifted.value == pytest.approx(1.0) and shifted.low < 1.0 < shifted.high
    assert verdict(shifted) == HOLDS
    assert verdict(difference(SCORES, SCORES)) == INCONCLUSIVE
    fewer_seeds = difference(better[:3], SCORES)  # conditions with different numbers of seeds
    assert np.isfinite(fewer_seeds.low) and np.isfinite(fewer_seeds.high)
    with pytest.raises(ValueError, match="same tasks"):
        difference(SCORES[:, :2], SCORES)


def test_a_claim_holds_does_not_hold_or_is_inconclusive_by_where_its_interval_lies():
    above, across, below = Estimate(0.3, 0.1, 0.5), Estimate(0.1, -0.2, 0.4), Estimate(-0.3, -0.5, -0.1)
    assert [verdict(estimate) for estimate in (above, across, below)] == [HOLDS, INCONCLUSIVE, DOES_NOT_HOLD]
    assert [verdict(estimate, above=False) for estimate in (above, across, below)] == [
        DOES_NOT_HOLD, INCONCLUSIVE, HOLDS]
    assert verdict(Estimate(1.0, 0.92, 1.2), threshold=0.9) == HOLDS  # BR-Prox >= 0.9
    assert verdict(Estimate(1.0, 0.85, 1.2), threshold=0.9) == INCONCLUSIVE
    assert str(above) == "0.30 [0.10, 0.50]"


def test_scores_that_are_not_a_matrix_of_runs_by_tasks_are_refused():
    with pytest.raises(ValueError, match=r"matrix \[runs, tasks\]"):
        interval(np.ones(5))
    with pytest.raises(ValueError, match=r"matrix \[runs, tasks\]"):
        interval(np.ones((0, 3)))
