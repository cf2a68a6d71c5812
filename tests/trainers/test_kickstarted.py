"""Kickstarted IPPO: IPPO with the scripted cook's policy as a target all through training
(`algorithm=kickstarted_ippo`)."""

import pytest
from test_ppo import read_metrics, tiny_config

from torch_kitchen.partners.conventions import Convention, fingerprints
from trainers.algorithms import check_algorithm
from trainers.algorithms.kickstarted import KickstartedSettings, teacher_weight
from trainers.checkpoint import load_checkpoint
from trainers.config import ConfigError
from trainers.ppo.loop import train
from trainers.train_command import main as train_main

FAST = ["ppo.lr=0.01", "ppo.anneal_lr=false"]  # large steps, so that two updates move the policy visibly


def test_the_teacher_weight_is_constant_or_falls_linearly_to_zero():
    constant = KickstartedSettings(teacher_coef=2.0)
    assert [teacher_weight(constant, steps) for steps in (0, 10**9)] == [2.0, 2.0]
    annealed = KickstartedSettings(teacher_coef=2.0, teacher_anneal_steps=100)
    assert [teacher_weight(annealed, steps) for steps in (0, 25, 100, 400)] == [2.0, 1.5, 0.0, 0.0]


def test_a_large_teacher_weight_brings_the_policy_to_the_cook_and_none_leaves_it(tmp_path):
    """One update of 8 epochs on a tiny batch: with the teacher term the policy fits the cook's choices on the
    states it trains on (the cross-entropy logged over the update's minibatches), without it it stays near
    uniform (log 6 = 1.79)."""
    logged = {}
    for coef in (0.0, 30.0):
        run = train(tiny_config(tmp_path, "algorithm=kickstarted_ippo", f"algorithm_config.teacher_coef={coef}",
                                f"name=coef{coef:g}", "ppo.epochs=8", *FAST, updates=1))
        metrics = read_metrics(run)
        [(_, logged[coef])] = metrics["charts/teacher_cross_entropy"]
        assert metrics["charts/teacher_weight"] == [(64.0, coef)]
    assert logged[0.0] > 1.6
    assert logged[30.0] < logged[0.0] - 0.4


def test_a_resumed_run_keeps_the_teacher_weight_schedule(tmp_path):
    settings = ["algorithm=kickstarted_ippo", "algorithm_config.teacher_anneal_steps=128", *FAST]
    whole = train(tiny_config(tmp_path, *settings, "name=whole", updates=3))
    config = tiny_config(tmp_path, *settings, "name=halves", updates=3)
    run = train(config, on_update=lambda update, metrics: update == 1)  # stopped after one update
    assert train_main(["--resume", str(run)]) == 0
    assert load_checkpoint(run)["algorithm"] == {"env_steps": 192}
    assert load_checkpoint(run)["met"] == fingerprints([Convention()])  # its teacher, the scripted cook, recorded
    weights = [weight for _, weight in read_metrics(run)["charts/teacher_weight"]]
    assert weights == [weight for _, weight in read_metrics(whole)["charts/teacher_weight"]] == [1.0, 0.5, 0.0]


@pytest.mark.parametrize("overrides, message", [
    (["algorithm_config.teacher_coef=-1"], r"^algorithm_config.teacher_coef must be at least 0, got -1.0$"),
    (["algorithm_config.teacher_anneal_steps=-5"], r"^algorithm_config.teacher_anneal_steps must be at least 0, "
                                                    r"got -5$"),
])
def test_bad_kickstarted_settings_are_one_line(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        check_algorithm(tiny_config(tmp_path, "algorithm=kickstarted_ippo", *overrides))


def test_a_recurrent_model_is_refused_with_one_line(tmp_path):
    config = tiny_config(tmp_path, "algorithm=kickstarted_ippo", "architecture=mlp_lstm")
    with pytest.raises(ConfigError, match=r"^algorithm=kickstarted_ippo compares the policy with the cook at stored "
                                          r"steps.*not 'mlp_lstm'$"):
        train(config)
