"""Anchored IPPO: PPO with a KL penalty toward the policy a run started from (`algorithm=anchored_ippo`)."""

import copy

import pytest
import torch
from tensordict import TensorDict
from test_ppo import read_metrics, tiny_config
from tiny import infinite_observations

from torch_kitchen.keys import OBSERVATION
from torch_kitchen.models import make_actor_critic
from trainers.algorithms.anchored import action_log_probs, policy_kl
from trainers.checkpoint import load_checkpoint
from trainers.config import ConfigError
from trainers.evaluation import load_team
from trainers.ppo.loop import train
from trainers.train_command import main as train_main

FAST = ["ppo.lr=0.01", "ppo.anneal_lr=false"]  # large steps, so that two updates move the policy visibly


def kl_from(start, actor, observation) -> float:
    batch = TensorDict({OBSERVATION: observation}, batch_size=[len(observation)])
    with torch.no_grad():
        return float(policy_kl(actor, action_log_probs(start, batch), batch))


def test_policy_kl_is_zero_against_itself_and_the_divergence_of_the_two_distributions():
    observation = infinite_observations(8, seed=3)
    actor = make_actor_critic("ego_mlp", hidden=16).actor
    other = copy.deepcopy(actor)
    with torch.no_grad():
        for parameter in other.parameters():
            parameter.add_(0.3 * torch.randn_like(parameter))
    assert kl_from(actor, copy.deepcopy(actor), observation) == pytest.approx(0.0, abs=1e-7)
    batch = TensorDict({OBSERVATION: observation}, batch_size=[8])
    with torch.no_grad():
        p = torch.log_softmax(actor.get_dist(batch.clone()).logits, -1)
        q = torch.log_softmax(other.get_dist(batch.clone()).logits, -1)
    expected = float((p.exp() * (p - q)).sum(-1).mean())
    assert kl_from(other, actor, observation) == pytest.approx(expected, rel=1e-5)
    assert expected > 0.01


@pytest.fixture(scope="module")
def start(tmp_path_factory):
    """A tiny team to start from."""
    return train(tiny_config(tmp_path_factory.mktemp("start"), "name=start", updates=1))


def test_a_large_anchor_keeps_the_policy_near_its_start_and_none_lets_it_move(tmp_path, start):
    observation = infinite_observations(16, seed=5)
    initial = load_team(start).actor_critic.actor
    moved, logged = {}, {}
    for coef in (0.0, 100.0):
        run = train(tiny_config(tmp_path, "algorithm=anchored_ippo", f"algorithm_config.anchor_coef={coef}",
                                f"init_from={start}", f"name=coef{coef:g}", *FAST))
        moved[coef] = kl_from(initial, load_team(run).actor_critic.actor, observation)
        logged[coef] = [kl for _, kl in read_metrics(run)["charts/anchor_kl"]]  # by update, over its minibatches
        assert len(logged[coef]) == 2 and min(logged[coef]) >= 0
    assert moved[100.0] < moved[0.0] / 3
    assert logged[100.0][-1] < logged[0.0][-1]


def test_a_resumed_run_keeps_the_anchor_it_started_from(tmp_path, start):
    config = tiny_config(tmp_path, "algorithm=anchored_ippo", f"init_from={start}", *FAST, updates=2)
    run = train(config, on_update=lambda update, metrics: update == 1)  # stopped after one update
    assert train_main(["--resume", str(run)]) == 0
    state = load_checkpoint(run)
    assert state["update"] == 2
    initial = load_checkpoint(start)["actor"]
    anchor = state["algorithm"]["anchor"]
    assert anchor.keys() == initial.keys()
    for name in initial:
        torch.testing.assert_close(anchor[name], initial[name], rtol=0, atol=0)
    assert any(not torch.equal(state["actor"][name], initial[name]) for name in initial)


@pytest.mark.parametrize("overrides, message", [
    (["algorithm=anchored_ippo"], r"^algorithm=anchored_ippo keeps the policy near the one it starts from: set "
                                  r"init_from"),
    (["algorithm=anchored_ippo", "init_from=runs/x", "algorithm_config.anchor_coef=-1"],
     r"^algorithm_config.anchor_coef must be at least 0, got -1.0$"),
])
def test_bad_anchored_settings_are_one_line(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        from trainers.algorithms import check_algorithm

        check_algorithm(tiny_config(tmp_path, *overrides))


def test_a_recurrent_model_is_refused_with_one_line(tmp_path, start):
    config = tiny_config(tmp_path, "algorithm=anchored_ippo", f"init_from={start}", "architecture=mlp_lstm")
    with pytest.raises(ConfigError, match=r"^algorithm=anchored_ippo compares the policy with its start at stored "
                                          r"steps.*not 'mlp_lstm'$"):
        train(config)
