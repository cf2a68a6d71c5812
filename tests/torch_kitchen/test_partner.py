"""E3T's partner side: the mixture's action frequencies, the context's contents (no label leakage), and the
partner predictor learning a scripted partner but not a random one."""

import pytest
import torch
from scripted_cook import TWO_BOOTHS, scripted_team
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs.utils import check_env_specs

from jax_env import NUM_ACTIONS, STAY
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.acting import sampling_actor
from torch_kitchen.models.e3t_partner import NO_ACTION, PartnerContext, PartnerMixture, PartnerSeats
from torch_kitchen.models.partner_predictor import split_partner_predictor
from trainers.algorithms.e3t import partner_prediction_loss

EPSILON = 0.3


def fixed_actor(action: int):
    """A policy that always picks `action`."""
    logits = torch.full((NUM_ACTIONS,), -1e9)
    logits[action] = 0.0
    module = TensorDictModule(lambda obs: logits.expand(*obs.shape[:-3], NUM_ACTIONS).clone(),
                              in_keys=[("agents", "observation")], out_keys=[("agents", "logits")])
    return sampling_actor(module)


def mixed_rollout(partner=None, num_envs=64, steps=64, max_steps=16):
    torch.manual_seed(0)
    env = with_transforms(KitchenEnv(num_envs, levels="cramped_room_7x7", max_steps=max_steps), [PartnerSeats(1)])
    policy = TensorDictSequential(fixed_actor(STAY), PartnerMixture(EPSILON, partner))
    with torch.no_grad():
        return env.rollout(steps, policy, break_when_any_done=False)


@pytest.mark.parametrize("partner_action", [None, 0])
def test_the_mixed_agent_acts_from_the_mixture_and_records_its_log_prob(partner_action):
    """The ego always plays the fixed policy; the mixed agent plays it with 1 - eps (+ eps/6 from uniform)."""
    partner = None if partner_action is None else fixed_actor(partner_action)
    expected_action = STAY if partner is None else partner_action
    data = mixed_rollout(partner)
    mixed, action = data["agents", "mixed"], data["agents", "action"]
    assert (mixed.sum(-1) == 1).all()  # one mixed agent per kitchen and step
    assert (action[~mixed] == STAY).all()
    partner_actions = action[mixed]
    frequencies = torch.bincount(partner_actions, minlength=NUM_ACTIONS).float() / partner_actions.numel()
    expected = torch.full((NUM_ACTIONS,), EPSILON / NUM_ACTIONS)
    expected[expected_action] += 1 - EPSILON
    # 4096 draws: a standard error under 0.007 for every frequency.
    torch.testing.assert_close(frequencies, expected, atol=0.025, rtol=0)
    # Recorded log-probs: the ego's policy for the ego, the mixture for the mixed agent.
    log_prob = data["agents", "action_log_prob"]
    assert (log_prob[~mixed] == 0).all()
    mixture = torch.where(partner_actions == expected_action, 1 - EPSILON + EPSILON / NUM_ACTIONS,
                          EPSILON / NUM_ACTIONS)
    torch.testing.assert_close(log_prob[mixed], mixture.log())


def test_the_mixed_agent_is_drawn_per_kitchen_per_episode():
    data = mixed_rollout(num_envs=64, steps=64, max_steps=16)
    seat = data["agents", "mixed"][..., 1].long()  # [B, T]: 1 where agent 1 is mixed
    episodes = seat.reshape(64, 4, 16)
    assert (episodes == episodes[..., :1]).all()  # constant within an episode
    per_episode = episodes[..., 0].float()
    assert 0.4 < per_episode.mean() < 0.6  # 256 episodes, both agents about equally often
    assert (per_episode.std(1) > 0).any()  # redrawn between a kitchen's episodes


def expected_context(actions, observations, is_first, length):
    """For every kitchen, step and agent, the k previous (own observation, partner action) pairs of the same
    episode, written out with plain loops over the rollout's history."""
    num_envs, steps = actions.shape[:2]
    context_actions = torch.full((num_envs, steps, 2, length), NO_ACTION)
    context_obs = torch.zeros((num_envs, steps, 2, length, *observations.shape[-3:]), dtype=observations.dtype)
    for b in range(num_envs):
        start = 0
        for t in range(steps):
            if is_first[b, t]:
                start = t
            for slot, past in enumerate(range(t - length, t)):
                if past >= start:
                    for agent in range(2):
                        context_actions[b, t, agent, slot] = actions[b, past, 1 - agent]
                        context_obs[b, t, agent, slot] = observations[b, past, agent]
    return context_actions, context_obs


def test_the_context_holds_the_previous_steps_of_the_episode_and_never_the_current_action():
    length, max_steps = 5, 7
    torch.manual_seed(0)
    env = with_transforms(KitchenEnv(3, levels="infinite", max_steps=max_steps), [PartnerContext(length)])
    data = env.rollout(20, break_when_any_done=False)  # random actions
    actions, observations = data["agents", "action"], data["agents", "observation"]
    is_first = torch.zeros(actions.shape[:2], dtype=torch.bool)
    is_first[:, 0] = True
    is_first[:, 1:] = data["next", "done"][:, :-1, 0]
    context_actions, context_obs = expected_context(actions, observations, is_first, length)
    assert torch.equal(data["agents", "context_action"], context_actions)
    assert torch.equal(data["agents", "context_observation"], context_obs)
    # The newest entry is the previous step's partner action (or padding), never this step's.
    newest = data["agents", "context_action"][:, :, :, -1]
    assert torch.equal(newest[~is_first], actions.flip(-1)[:, :-1][~is_first[:, 1:]])


def rollout_with_context(actor, levels, num_envs, steps, seed):
    torch.manual_seed(seed)
    env = with_transforms(KitchenEnv(num_envs, levels=levels, max_steps=64, seed=seed), [PartnerContext(5)])
    with torch.no_grad():
        return env.rollout(steps, actor, break_when_any_done=False)


def train_predictor(training, fresh, iterations=150):
    """Trains an E3T MLP's partner predictor on `training`; its accuracy on `fresh` data."""
    torch.manual_seed(0)
    obs_shape = tuple(training["agents", "observation"].shape[-3:])
    predictor, _ = split_partner_predictor(make_actor_critic("e3t_mlp", obs_shape, hidden=32).actor)
    optimizer = torch.optim.Adam(predictor.parameters(), lr=3e-3)
    for _ in range(iterations):
        loss, _ = partner_prediction_loss(predictor, training)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        return float(partner_prediction_loss(predictor, fresh)[1])


def test_the_predictor_learns_a_scripted_partner():
    cooks = scripted_team((0, 1)).actor
    training, fresh = (rollout_with_context(cooks, TWO_BOOTHS, 8, 64, seed) for seed in (0, 1))
    partner_action = fresh["agents", "action"].flip(-1)
    majority = torch.bincount(partner_action.flatten()).max() / partner_action.numel()
    accuracy = train_predictor(training, fresh)
    assert accuracy > majority + 0.2, (accuracy, float(majority))


def test_the_predictor_cannot_beat_chance_on_a_random_partner():
    """With the predicted action in its context, the predictor would copy it; without, a uniformly random partner
    is unpredictable."""
    random_actor = sampling_actor(TensorDictModule(
        lambda obs: torch.zeros(*obs.shape[:-3], NUM_ACTIONS), in_keys=[("agents", "observation")],
        out_keys=[("agents", "logits")],
    ))  # fmt: skip
    training, fresh = (rollout_with_context(random_actor, TWO_BOOTHS, 8, 64, seed) for seed in (0, 1))
    # 1024 fresh predictions: chance is 1/6 with a standard error of 0.012.
    assert train_predictor(training, fresh) < 1 / NUM_ACTIONS + 0.06
    # The control: a context whose newest entry is the action being predicted is learned at once.
    leaky_training, leaky_fresh = (with_leakage(data) for data in (training, fresh))
    assert train_predictor(leaky_training, leaky_fresh) > 0.9


def with_leakage(data):
    """A copy of `data` whose contexts end with the partner's action at the current step."""
    leaky = data.clone()
    context = leaky["agents", "context_action"]
    leaky["agents", "context_action"] = torch.cat([context[..., 1:], data["agents", "action"].flip(-1)[..., None]], -1)
    return leaky


@pytest.mark.parametrize("architecture, share_params", [("e3t_mlp", True), ("e3t_gnn", False)])
def test_sequence_logits_equal_the_step_by_step_predictions(architecture, share_params):
    """Over a batch that starts mid-episode and crosses episode ends, one encoding per observation gives what
    the predictor computed at every step from its context."""
    torch.manual_seed(0)
    actor_critic = make_actor_critic(architecture, hidden=16, share_params=share_params)
    env = with_transforms(KitchenEnv(3, levels="infinite", max_steps=6), actor_critic.env_transforms())
    with torch.no_grad():
        data = env.rollout(20, actor_critic.actor, break_when_any_done=False)[:, 4:]  # from mid-episode
        predictor, _ = split_partner_predictor(actor_critic.actor)
        sequence = predictor.sequence_logits(data)
    torch.testing.assert_close(sequence, data["agents", "partner_logits"])


def test_the_partner_transforms_declare_what_they_write():
    env = with_transforms(KitchenEnv(2, levels="infinite", max_steps=4), [PartnerContext(5), PartnerSeats(0)])
    check_env_specs(env, seed=0)
    agents = env.observation_spec["agents"]
    assert agents["context_observation"].shape == (2, 2, 5, 7, 7, 26)
    assert agents["context_action"].shape == (2, 2, 5) and agents["mixed"].dtype == torch.bool
