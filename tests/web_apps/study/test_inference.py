"""A study's numbers by participant (`web_apps.study.inference`), on synthetic studies whose effects are known."""

import numpy as np
import pytest

pytest.importorskip("statsmodels", reason="the study's mixed model is statsmodels'")
from web_apps.study.inference import Observation, fit_mixed_model, holm, participant_interval, sign_test  # noqa: E402


def synthetic_study(participants: int, effect: float, rng: np.random.Generator, conditions=("team", "cook"),
                    kitchen_effect: float = 2.0, skill_spread: float = 1.5) -> list[Observation]:
    """Each participant plays every condition twice on two kitchens, rotated: deliveries = 3 + `effect`
    beside the first condition + `kitchen_effect` on kitchen b + the participant's skill + noise."""
    observations = []
    for person in range(participants):
        skill = rng.normal(0, skill_spread)
        shift = person % len(conditions)  # each condition as often at each position
        order = list(conditions[shift:]) + list(conditions[:shift])
        kitchens = ["a", "b"] if (person // 2) % 2 == 0 else ["b", "a"]
        for position in range(2 * len(conditions)):
            condition, kitchen = order[position % len(conditions)], kitchens[position // len(conditions)]
            deliveries = (3 + effect * (condition == conditions[0]) + kitchen_effect * (kitchen == "b") + skill
                          + rng.normal(0, 0.7))
            observations.append(Observation(person, condition, kitchen, position, deliveries))
    return observations


def test_the_interval_resamples_participants_not_games():
    # One participant with many games counts once: the mean is of the participants' means.
    games = [Observation(0, "team", "a", i, 10.0) for i in range(20)] + [Observation(1, "team", "a", 0, 0.0)]
    mean, low, high, participants = participant_interval(games, "team")
    assert (mean, participants) == (5.0, 2) and low <= 5.0 <= high and high - low == pytest.approx(10.0)
    assert participant_interval([Observation(0, "cook", "a", 0, 3.0)], "cook")[1:3] != (3.0, 3.0)  # n < 2: none


def test_the_mixed_model_recovers_the_condition_effect_past_participants_and_kitchens():
    rng = np.random.default_rng(0)
    primary, *others = fit_mixed_model(synthetic_study(40, 1.0, rng, ("team", "cook", "zoo")),
                                       ["team", "cook", "zoo"], ("team", "cook"))
    assert (primary.first, primary.second) == ("team", "cook") and primary.low <= 1.0 <= primary.high
    assert primary.low > 0 and primary.p < 0.05  # the kitchens' 2.0 and the participants' skill are held apart
    assert [(other.first, other.second) for other in others] == [("cook", "zoo"), ("team", "zoo")]
    cook_zoo = others[0]  # no effect between these two
    assert cook_zoo.low <= 0.0 <= cook_zoo.high and cook_zoo.p_holm >= cook_zoo.p
    assert fit_mixed_model(synthetic_study(1, 1.0, rng), ["team", "cook"], ("team", "cook")) == []  # too few
    confounded = [Observation(o.participant, o.condition, "a" if o.condition == "team" else "b", o.position,
                              o.deliveries) for o in synthetic_study(20, 1.0, rng)]  # every team game on kitchen a
    assert fit_mixed_model(confounded, ["team", "cook"], ("team", "cook")) == []


def test_under_no_effect_the_primary_contrast_is_called_at_about_alpha():
    rng = np.random.default_rng(1)
    calls = [fit_mixed_model(synthetic_study(12, 0.0, rng), ["team", "cook"], ("team", "cook"))[0].p < 0.05
             for _ in range(60)]
    assert np.mean(calls) <= 0.12  # alpha 0.05; a games-as-people test would call far more often here


def test_holm_and_the_sign_test():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert np.isnan(holm([float("nan"), 0.2])[0]) and holm([float("nan"), 0.2])[1] == pytest.approx(0.2)
    assert sign_test(6, 0) == pytest.approx(2 / 2**6) and sign_test(3, 3) == pytest.approx(1.0)
    assert np.isnan(sign_test(0, 0))
