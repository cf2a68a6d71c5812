"""How many participants a study needs (`web_apps.study.power`): power by simulation against the closed form."""


import numpy as np
import pytest

pytest.importorskip("statsmodels", reason="the study's mixed model is statsmodels'")
from statsmodels.stats.power import TTestPower  # noqa: E402
from tiny_study import study_config  # noqa: E402

from web_apps.study.config import load_study  # noqa: E402
from web_apps.study.power import Model, fit_model, power_curve  # noqa: E402


def test_the_simulated_power_agrees_with_the_paired_t_tests_closed_form(tmp_path):
    # Each participant plays each of two conditions once on one kitchen: the mixed model's contrast is then the
    # paired difference, whose power the noncentral t distribution gives.
    config = load_study(study_config(tmp_path, kitchens=["cramped_room_7x7"], games_per_participant=2), check=False)
    first, second = config.primary_contrast
    model = Model(intercept=3.0, conditions={first: 0.5, second: 0.0}, kitchens={}, participant_sd=1.5, game_sd=1.0)
    simulated = power_curve(model, config, sizes=(16, 64), studies=60, seed=0)
    closed = TTestPower().power(effect_size=0.5 / np.sqrt(2), nobs=64, alpha=0.05)
    # 60 studies: a standard error of at most 0.065; at 24 participants the model's z test ran hot (0.49 against 0.38)
    assert simulated[64] == pytest.approx(closed, abs=0.13), (simulated[64], closed)
    assert simulated[64] > simulated[16]


def test_a_model_fitted_to_a_studys_games_gives_back_what_made_them(tmp_path):
    config = load_study(study_config(tmp_path, games_per_participant=4), check=False)
    first, second = config.primary_contrast
    truth = Model(intercept=3.0, conditions={first: 1.0, second: 0.0},
                  kitchens={config.kitchens[0]: 0.0, config.kitchens[1]: 2.0}, participant_sd=1.5, game_sd=0.5)
    fitted = fit_model(truth.draw(config, 80, np.random.default_rng(1)), config)
    assert fitted.conditions[first] - fitted.conditions[second] == pytest.approx(1.0, abs=0.2)
    assert fitted.participant_sd == pytest.approx(1.5, abs=0.4) and fitted.game_sd == pytest.approx(0.5, abs=0.15)
    kitchen_gap = fitted.kitchens[config.kitchens[1]] - fitted.kitchens[config.kitchens[0]]
    assert kitchen_gap == pytest.approx(2.0, abs=0.3)
