import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import InteractionType, TensorDictSequential, set_interaction_type
from torchrl.collectors import Collector
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss

from jax_env import GeneratorConfig
from torch_kitchen import models
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.graph import batched_edges, build_graph, graph_edges
from torch_kitchen.models import ARCHITECTURES, E3T_ARCHITECTURES, make_actor_critic, register_architecture

HIDDEN = 16
RECURRENT = [a for a in ARCHITECTURES if a.endswith("_lstm")]
STATE_KEYS = [("agents", f"{net}_{part}") for net in ("actor", "critic") for part in ("h", "c")]


@pytest.fixture(scope="module")
def envs():
    """Infinite Kitchen envs by batch size, made once: every KitchenEnv jit-compiles its own step."""
    envs = {n: KitchenEnv(num_envs=n, levels="infinite", max_steps=5, seed=n) for n in (1, 3)}
    envs["9x9"] = KitchenEnv(num_envs=3, levels="infinite", max_steps=5, generator=GeneratorConfig(size=9), seed=9)
    return envs


def _env(base, ac):
    return with_transforms(base, ac.env_transforms())


def _rollout(base, ac, steps):
    """[B, T] data from the env under the model's own policy (what a trainer learns from)."""
    torch.manual_seed(0)
    with torch.no_grad():
        return _env(base, ac).rollout(steps, ac.actor, break_when_any_done=False)


@pytest.mark.parametrize("num_envs", [1, 3])
@pytest.mark.parametrize("share_params", [True, False])
@pytest.mark.parametrize("architecture", ARCHITECTURES + E3T_ARCHITECTURES)
def test_forward_shapes_dtypes_and_log_probs(envs, architecture, share_params, num_envs):
    ac = make_actor_critic(architecture, hidden=HIDDEN, share_params=share_params)
    td = _env(envs[num_envs], ac).reset()
    td = ac.critic(ac.actor(td))
    logits, action = td["agents", "logits"], td["agents", "action"]
    assert logits.shape == (num_envs, 2, 6) and logits.dtype == torch.float32
    assert action.shape == (num_envs, 2) and action.dtype == torch.int64
    assert ((0 <= action) & (action < 6)).all()
    log_prob = td["agents", "action_log_prob"]
    assert log_prob.shape == (num_envs, 2) and log_prob.dtype == torch.float32
    torch.testing.assert_close(log_prob, torch.distributions.Categorical(logits=logits).log_prob(action))
    assert td["agents", "state_value"].shape == (num_envs, 2, 1)
    assert td["agents", "state_value"].dtype == torch.float32
    # Intermediate activations stay out of the rollouts.
    assert not any("embedding" in key[-1] or "memory" in key[-1] for key in td.keys(True, True))
    if ac.recurrent:
        for key in STATE_KEYS:
            assert td["next", *key].shape == (num_envs, 2, 1, HIDDEN)
            assert td["next", *key].abs().sum() > 0
    if architecture in E3T_ARCHITECTURES:
        prediction = td["agents", "partner_prediction"]
        assert prediction.shape == (num_envs, 2, 6) and not prediction.requires_grad
        torch.testing.assert_close(prediction.sum(-1), torch.ones(num_envs, 2))


@pytest.mark.parametrize("share_params", [True, False])
@pytest.mark.parametrize("architecture", ["mlp", "gnn"])
def test_the_acting_pass_writes_what_actor_then_critic_write(envs, architecture, share_params):
    """Bit for bit, sampled or deterministic, and after the weights change (it holds the same networks)."""
    ac = make_actor_critic(architecture, hidden=HIDDEN, share_params=share_params)
    networks = {id(p) for p in (*ac.actor.parameters(), *ac.critic.parameters())}
    assert ac.acting is not None and {id(p) for p in ac.acting.parameters()} == networks
    td = _env(envs[3], ac).reset()
    with torch.no_grad():
        for _ in range(2):
            for mode in (InteractionType.RANDOM, InteractionType.DETERMINISTIC):
                with set_interaction_type(mode):
                    torch.manual_seed(1)
                    fused = ac.acting_policy()(td.clone())
                    torch.manual_seed(1)
                    reference = ac.critic(ac.actor(td.clone()))
                assert set(fused.keys(True, True)) == set(reference.keys(True, True))
                for key in reference.keys(True, True):
                    assert torch.equal(fused[key], reference[key]), key
            for parameter in ac.actor.parameters():  # an optimizer's in-place step
                parameter.add_(torch.randn_like(parameter))
    with set_interaction_type(InteractionType.MEAN), pytest.raises(ValueError, match="no mean action"):
        ac.acting(td.clone())


@pytest.mark.parametrize("architecture", [*RECURRENT, *E3T_ARCHITECTURES])
def test_actor_then_critic_act_where_there_is_no_acting_pass(envs, architecture):
    ac = make_actor_critic(architecture, hidden=HIDDEN)
    assert ac.acting is None
    modules = list(ac.acting_policy().module)
    assert modules == [ac.actor, ac.critic]


@pytest.mark.parametrize("architecture", ARCHITECTURES + E3T_ARCHITECTURES)
def test_parameter_sharing(envs, architecture):
    shared = make_actor_critic(architecture, hidden=HIDDEN, share_params=True)
    separate = make_actor_critic(architecture, hidden=HIDDEN, share_params=False)
    for net in ("actor", "critic"):
        count = sum(p.numel() for p in getattr(shared, net).parameters())
        assert sum(p.numel() for p in getattr(separate, net).parameters()) == 2 * count
    # Separate torsos: no tensor is shared by actor and critic.
    assert not {id(p) for p in shared.actor.parameters()} & {id(p) for p in shared.critic.parameters()}

    td = _env(envs[3], shared).reset()
    obs = td["agents", "observation"]
    td["agents", "observation"] = obs[:, :1].expand_as(obs).clone()  # both agents see agent 0's view
    for ac, same in ((shared, True), (separate, False)):
        out = ac.critic(ac.actor(td.clone()))
        for key in (("agents", "logits"), ("agents", "state_value")):
            assert torch.allclose(out[key][:, 0], out[key][:, 1]) == same, (key, same)

    # Agent i's network sees only agent i's observation.
    other = td.clone()
    other["agents", "observation"][:, 1] = envs[3].reset()["agents", "observation"][:, 1].roll(1, dims=1)
    first, second = (separate.critic(separate.actor(t.clone())) for t in (td, other))
    torch.testing.assert_close(first["agents", "logits"][:, 0], second["agents", "logits"][:, 0])
    assert not torch.allclose(first["agents", "logits"][:, 1], second["agents", "logits"][:, 1])


def test_graph_of_a_small_kitchen_by_hand():
    # Two 2x3 kitchens, 4 channels. Graph 0: self on cell (1, 2) = node 5, partner on (0, 1) = node 1.
    # Graph 1: self on (0, 0) = node 0, partner on (1, 1) = node 4.
    obs = torch.zeros(2, 2, 3, 4)
    obs[..., 2] = torch.arange(12.0).view(2, 2, 3)
    obs[..., 3] = -torch.arange(12.0).view(2, 2, 3)
    obs[0, 1, 2, 0] = obs[0, 0, 1, 1] = 1
    obs[1, 0, 0, 0] = obs[1, 1, 1, 1] = 1
    x, edge_index = build_graph(obs)

    assert x.shape == (16, 4)
    cells = obs.reshape(2, 6, 4)
    torch.testing.assert_close(x[0:6], cells[0])
    torch.testing.assert_close(x[6], torch.tensor([1.0, 0, 5, -5]))  # self: the channels of cell 5
    torch.testing.assert_close(x[7], torch.tensor([0.0, 1, 1, -1]))  # partner: cell 1
    torch.testing.assert_close(x[8:14], cells[1])
    torch.testing.assert_close(x[14], torch.tensor([1.0, 0, 6, -6]))  # graph 1, self: its cell 0
    torch.testing.assert_close(x[15], torch.tensor([0.0, 1, 10, -10]))  # partner: its cell 4

    one = [
        [0, 1, 2, 3, 4, 5, 0, 1, 2, 3, 4, 5, 0, 1, 2, 3, 4, 5, 6, 7],
        [6, 6, 6, 6, 6, 6, 7, 7, 7, 7, 7, 7, 0, 1, 2, 3, 4, 5, 6, 7],
    ]
    assert graph_edges(2, 3).tolist() == one
    two = [row + [node + 8 for node in row] for row in one]
    assert edge_index.dtype == torch.int64 and edge_index.tolist() == two
    assert batched_edges(2, 3, 2, torch.device("cpu")) is edge_index  # built once per (H, W, N, device)


def _sequence_batch(envs, ac, steps=6):
    """[3, steps] real observations with an episode boundary inside env 0's sequence at t=3."""
    data = _rollout(envs[3], ac, steps)
    is_init = torch.zeros(3, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    is_init[0, 3] = True
    return data["agents", "observation"], is_init


def _step_by_step(ac, obs, is_init):
    """Run the model one step at a time (collection mode), carrying the state; returns the inputs it saw."""
    batch, steps = is_init.shape[:2]
    states = {key: torch.randn(batch, 2, 1, HIDDEN) for key in STATE_KEYS}  # overwritten: is_init at t=0
    inputs, outputs = [], []
    for t in range(steps):
        agents = TensorDict({"observation": obs[:, t], **{key[1]: v for key, v in states.items()}}, [batch, 2])
        td = TensorDict({"agents": agents, "is_init": is_init[:, t]}, [batch])
        inputs.append(td.clone())
        td = ac.critic(ac.actor(td))
        outputs.append(td)
        states = {key: td["next", *key] for key in STATE_KEYS}
    return torch.stack(inputs, 1), torch.stack(outputs, 1)


@pytest.mark.parametrize("share_params", [True, False])
@pytest.mark.parametrize("architecture", RECURRENT)
def test_recurrent_mode_equals_step_mode_and_resets_at_is_init(envs, architecture, share_params):
    ac = make_actor_critic(architecture, hidden=HIDDEN, share_params=share_params)
    obs, is_init = _sequence_batch(envs, ac)
    with torch.no_grad():
        inputs, stepped = _step_by_step(ac, obs, is_init)
        # (a) BPTT mode over the whole [B, T] batch, with the states the collector would have stored.
        for key in STATE_KEYS:
            inputs["next", *key] = stepped["next", *key]
        with set_recurrent_mode(True):
            sequence = ac.critic(ac.actor(inputs.clone()))
        for key in (("agents", "logits"), ("agents", "state_value")):
            torch.testing.assert_close(sequence[key], stepped[key], atol=1e-5, rtol=1e-4)
        for key in STATE_KEYS:  # the collected next states are kept, not replaced by LSTMModule's padding
            assert torch.equal(sequence["next", *key], stepped["next", *key])

        # (b) Other observations before the boundary change nothing after it (env 0); without a boundary the
        # state carries them on (env 1).
        changed = inputs.clone()
        changed["agents", "observation"][0, :3] = obs[2, :3]
        changed["agents", "observation"][1, :3] = obs[2, :3]
        with set_recurrent_mode(True):
            other = ac.critic(ac.actor(changed))
    for key in (("agents", "logits"), ("agents", "state_value")):
        torch.testing.assert_close(other[key][0, 3:], sequence[key][0, 3:])
        assert not torch.equal(other[key][0, :3], sequence[key][0, :3])
        assert not torch.equal(other[key][1, 3:], sequence[key][1, 3:])


@pytest.mark.parametrize(("architecture", "with_critic"), [("mlp_lstm", True), ("gnn_lstm", False)])
def test_collector_carries_the_state_and_zeroes_it_at_is_init(envs, architecture, with_critic):
    ac = make_actor_critic(architecture, hidden=HIDDEN, share_params=False)
    env = TransformedEnv(envs[3], Compose(*ac.env_transforms()))
    check_env_specs(env)
    # With the critic in the policy, its state is carried too (and values come for free).
    policy = TensorDictSequential(ac.actor, ac.critic) if with_critic else ac.actor
    collector = Collector(env, policy, frames_per_batch=3 * 12, total_frames=3 * 12)
    batch = next(iter(collector))
    collector.shutdown(close_env=False)

    assert batch.batch_size == (3, 12)
    is_init = batch["is_init"].squeeze(-1)
    assert is_init[:, [0, 5, 10]].all() and is_init.sum() == 9  # episodes of 5 steps
    for key in STATE_KEYS[: 4 if with_critic else 2]:
        state = batch[key]
        assert state.shape == (3, 12, 2, 1, HIDDEN)
        assert torch.equal((state == 0).flatten(2).all(-1), is_init)
        # Within an episode, step t+1 starts from the state step t ended with.
        carried = ~is_init[:, 1:]
        torch.testing.assert_close(state[:, 1:][carried], batch["next", *key][:, :-1][carried])


@pytest.mark.parametrize("share_params", [True, False])
@pytest.mark.parametrize("architecture", ARCHITECTURES)
def test_ppo_gradient_step(envs, architecture, share_params):
    _assert_ppo_step_moves_every_parameter(make_actor_critic(architecture, hidden=HIDDEN, share_params=share_params),
                                           envs[3])


@pytest.mark.parametrize("architecture", ARCHITECTURES)
def test_every_architecture_is_built_for_9x9_kitchens_and_learns_there(envs, architecture):
    ac = make_actor_critic(architecture, obs_shape=(9, 9, 26), hidden=HIDDEN)
    _assert_ppo_step_moves_every_parameter(ac, envs["9x9"])
    with pytest.raises(ValueError, match=r"9, 9, 26"):  # and refuses 7x7 observations
        ac.actor(envs[3].reset())


def _assert_ppo_step_moves_every_parameter(ac, base):
    data = _rollout(base, ac, 4)
    data["agents", "advantage"] = torch.randn(3, 4, 2, 1)
    data["agents", "value_target"] = torch.randn(3, 4, 2, 1)
    loss = ClipPPOLoss(ac.actor, ac.critic, clip_epsilon=0.2, entropy_coeff=0.01, critic_coeff=0.5)
    loss.set_keys(action=("agents", "action"), sample_log_prob=("agents", "action_log_prob"),
                  value=("agents", "state_value"), advantage=("agents", "advantage"),
                  value_target=("agents", "value_target"))
    with set_recurrent_mode(True):
        terms = loss(data)
    total = terms["loss_objective"] + terms["loss_critic"] + terms["loss_entropy"]
    assert torch.isfinite(total)
    total.backward()
    for name, parameter in [*ac.actor.named_parameters(), *ac.critic.named_parameters()]:
        assert parameter.grad is not None, name
        assert torch.isfinite(parameter.grad).all(), name
        assert parameter.grad.abs().sum() > 0, name


def test_wrong_observation_shape_is_a_clear_error():
    ac = make_actor_critic("gnn", hidden=HIDDEN)
    agents = TensorDict({"observation": torch.zeros(1, 2, 4, 5, 26, dtype=torch.uint8)}, [1, 2])
    with pytest.raises(ValueError, match=r"\[1, 2, 4, 5, 26\].*7, 7, 26.*7x7 kitchens needs 7x7 levels"):
        ac.actor(TensorDict({"agents": agents}, [1]))


def test_registry():
    with pytest.raises(ValueError, match="registered: mlp, mlp_lstm, gnn, gnn_lstm, ego_mlp, e3t_mlp, e3t_gnn"):
        make_actor_critic("transformer")
    with pytest.raises(ValueError, match="already registered"):
        register_architecture("mlp", lambda **kwargs: None)

    def narrow_mlp(obs_shape, hidden, share_params):
        return make_actor_critic("mlp", obs_shape, hidden=hidden // 2, share_params=share_params)

    register_architecture("narrow_mlp_for_tests", narrow_mlp)
    try:
        ac = make_actor_critic("narrow_mlp_for_tests", hidden=2 * HIDDEN)
    finally:
        models._REGISTRY.pop("narrow_mlp_for_tests")
    reference = make_actor_critic("mlp", hidden=HIDDEN)
    assert sum(p.numel() for p in ac.actor.parameters()) == sum(p.numel() for p in reference.actor.parameters())
