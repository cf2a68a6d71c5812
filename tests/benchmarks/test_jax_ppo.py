"""The pure-JAX reference PPO (`benchmarks/jax_ppo.py`) runs, is seeded, and computes what our trainer computes:
the same GAE as `trainers.ppo.advantages.compute_advantages`, and the same losses, gradients and Adam steps as our
ClipPPOLoss loop on the same weights and minibatch."""

import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tiny import TINY

from torch_kitchen.keys import ADVANTAGE, LOG_PROB, VALUE, VALUE_TARGET
from torch_kitchen.models import make_actor_critic
from trainers.config.compose import load_config
from trainers.ppo.advantages import compute_advantages, shaping_weight_at
from trainers.ppo.step import total_loss
from trainers.ppo.team import make_algorithm, make_loss

# benchmarks/ is a folder of scripts, not a package: load the module from its file.
_spec = importlib.util.spec_from_file_location(
    "jax_ppo", Path(__file__).resolve().parents[2] / "benchmarks" / "jax_ppo.py"
)
jax_ppo = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = jax_ppo  # flax's dataclasses look their module up there
_spec.loader.exec_module(jax_ppo)

# The shared tiny run (16-step episodes: every update ends one per kitchen), 2 updates, shaping annealed.
TINY_JAX = [*TINY, "total_steps=128", "ppo.shaping_weight=1", "ppo.shaping_anneal_steps=1000"]


def tiny_config(*overrides):
    return load_config(None, [*TINY_JAX, *overrides])


def test_the_reference_runs_with_finite_metrics_and_is_seeded():
    config = tiny_config()
    steps_per_second, metrics = jax_ppo.run_reference(config, seed=0)
    assert steps_per_second > 0
    assert all(values.shape == (2,) for values in metrics.values())
    assert all(np.isfinite(values).all() for values in metrics.values())
    np.testing.assert_array_equal(metrics["charts/env_steps"], [64, 128])
    np.testing.assert_array_equal(metrics["charts/episodes"], [4, 4])
    assert (metrics["charts/episode_deliveries"] >= 0).all()
    np.testing.assert_allclose(metrics["charts/learning_rate"], [config.ppo.lr, config.ppo.lr / 2])
    np.testing.assert_allclose(metrics["charts/shaping_weight"], [shaping_weight_at(config, 64),
                                                                  shaping_weight_at(config, 128)])
    assert (metrics["losses/entropy"] > 1.7).all()  # near log(6): small output gain, two updates

    train = jax.jit(jax_ppo.make_train(config))
    again = train(jax.random.PRNGKey(0))
    for key, values in metrics.items():
        np.testing.assert_array_equal(np.asarray(again[key]), values, err_msg=key)
    other = train(jax.random.PRNGKey(1))
    assert not np.array_equal(np.asarray(other["losses/value"]), metrics["losses/value"])


def test_the_reference_refuses_what_it_does_not_implement():
    with pytest.raises(ValueError, match="mlp architecture only"):
        jax_ppo.make_train(tiny_config("architecture=gnn"))


def test_gae_equals_our_trainers():
    generator = torch.Generator().manual_seed(0)
    kitchens, steps, weight = 3, 12, 0.7
    reward = 20.0 * (torch.rand(kitchens, steps, 2, 1, generator=generator) < 0.1)
    shaped = 3.0 * (torch.rand(kitchens, steps, 2, 1, generator=generator) < 0.2)
    value = torch.randn(kitchens, steps, 2, 1, generator=generator)
    done = torch.rand(kitchens, steps, 1, generator=generator) < 0.2
    done[0, -1], done[1, -1] = True, False  # a time limit on the last step, and a bootstrap
    after = torch.randn(kitchens, 2, 1, generator=generator)
    batch = TensorDict(
        {
            "agents": TensorDict({"state_value": value}, batch_size=(kitchens, steps, 2)),
            "next": TensorDict(
                {
                    "agents": TensorDict({"reward": reward, "shaped_reward": shaped}, batch_size=(kitchens, steps, 2)),
                    "done": done,
                },
                batch_size=(kitchens, steps),
            ),
        },
        batch_size=(kitchens, steps),
    )

    def critic(observed):  # the value of the observation after the batch's last step
        return observed.set(VALUE, after)

    compute_advantages(batch, critic, tiny_config(), weight)

    def time_major(tensor):  # [B, T, 2, 1] -> [T, B, 2]
        return jnp.asarray(tensor.squeeze(-1).transpose(0, 1).numpy())

    advantage, target = jax_ppo.generalized_advantages(
        time_major(reward) + weight * time_major(shaped), time_major(value), jnp.asarray(done[..., 0].T.numpy()),
        jnp.asarray(after[..., 0].numpy()), 0.99, 0.95,
    )
    np.testing.assert_allclose(np.asarray(advantage), time_major(batch.get(ADVANTAGE)), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(target), time_major(batch.get(VALUE_TARGET)), rtol=1e-5, atol=1e-5)


def flax_params(network, attribute="data"):
    """Our torch network's four Linear layers as the reference's Torso params (kernel = weight transposed)."""
    # Copies: torch's optimizer updates the weights in place.
    tensors = [getattr(parameter, attribute).numpy().copy() for parameter in network.parameters()]
    layers = {
        f"Dense_{index}": {"kernel": np.swapaxes(weight, -1, -2), "bias": bias}
        for index, (weight, bias) in enumerate(zip(tensors[0::2], tensors[1::2]))
    }
    return {"params": layers}


def assert_trees_close(actual, expected, **tolerance):
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(actual), jax.tree_util.tree_leaves(expected)):
        np.testing.assert_allclose(np.asarray(a), b, err_msg=jax.tree_util.keystr(path), **tolerance)


@pytest.mark.parametrize("share_params", [True, False])
def test_loss_gradients_and_adam_steps_equal_our_trainers(share_params):
    torch.manual_seed(0)
    config = tiny_config("ppo.lr=1e-3", f"share_params={str(share_params).lower()}", "ppo.max_grad_norm=0.05")
    kitchens, steps = 2, 8
    actor_critic = make_actor_critic("mlp", (7, 7, 26), config.hidden, share_params)
    observation = torch.randint(0, 3, (kitchens, steps, 2, 7, 7, 26), dtype=torch.uint8)
    agents = TensorDict({"observation": observation}, batch_size=(kitchens, steps, 2))
    with torch.no_grad():
        acted = actor_critic.critic(actor_critic.actor(TensorDict({"agents": agents}, batch_size=(kitchens, steps))))
    # Collection-time log-probs and values away from the current ones, so both clips act on some samples.
    agents.set(LOG_PROB[1], acted.get(LOG_PROB) + 0.3 * torch.randn(kitchens, steps, 2))
    agents.set(VALUE[1], acted.get(VALUE) + 0.3 * torch.randn(kitchens, steps, 2, 1))
    agents.set("action", acted.get(("agents", "action")))
    agents.set(ADVANTAGE[1], torch.randn(kitchens, steps, 2, 1))
    agents.set(VALUE_TARGET[1], agents.get(VALUE[1]) + torch.randn(kitchens, steps, 2, 1))
    batch = TensorDict({"agents": agents}, batch_size=(kitchens, steps))

    networks = jax_ppo.make_actor_critic(config.hidden, share_params)
    params = {"actor": flax_params(actor_critic.actor), "critic": flax_params(actor_critic.critic)}
    def array(key, dtype=jnp.float32):
        value = agents.get(key)
        return jnp.asarray((value.squeeze(-1) if value.ndim == 4 else value).numpy(), dtype)  # [B, T, 2, 1] values

    minibatch = jax_ppo.Minibatch(array("observation", jnp.uint8), array("action", jnp.int32),
                                  array("action_log_prob"), array("state_value"), array("advantage"),
                                  array("value_target"))

    # Losses and gradients on the same weights and data; ours standardises the advantages as the trainer does,
    # before the loss (the reference inside its loss).
    algorithm = make_algorithm(config, actor_critic)
    loss_module = make_loss(config, actor_critic, algorithm)
    algorithm.process_minibatch(batch)
    losses = loss_module(batch)
    total_loss(losses).backward()
    (total, stats), grads = jax.value_and_grad(jax_ppo.ppo_loss, has_aux=True)(params, networks, minibatch, config)
    for ours, name in [("loss_objective", "losses/policy"), ("loss_critic", "losses/value"),
                       ("loss_entropy", "losses/entropy_loss"), ("clip_fraction", "losses/clip_fraction"),
                       ("value_clip_fraction", "losses/value_clip_fraction")]:
        np.testing.assert_allclose(float(stats[name]), losses[ours].item(), rtol=1e-5, atol=1e-7, err_msg=name)
    assert 0 < float(stats["losses/clip_fraction"]) < 1 and 0 < float(stats["losses/value_clip_fraction"]) < 1
    assert_trees_close(grads, {"actor": flax_params(actor_critic.actor, "grad"),
                               "critic": flax_params(actor_critic.critic, "grad")}, rtol=1e-4, atol=1e-6)

    # A few steps of our trainer's inner loop (clip the gradient norm, then Adam) against the reference's.
    parameters = list(loss_module.parameters())
    optimizer = torch.optim.Adam(parameters, lr=config.ppo.lr, eps=config.ppo.adam_eps)
    jax_optimizer = jax_ppo.make_optimizer(config)
    opt_state = jax_optimizer.init(params)
    for _ in range(3):
        optimizer.zero_grad()
        total_loss(loss_module(batch)).backward()
        norm = torch.nn.utils.clip_grad_norm_(parameters, config.ppo.max_grad_norm)
        optimizer.step()
        params, opt_state, stats = jax_ppo.minibatch_step(params, opt_state, networks, jax_optimizer, minibatch,
                                                          config)
        np.testing.assert_allclose(float(stats["losses/grad_norm"]), float(norm), rtol=1e-5)
    assert float(norm) > config.ppo.max_grad_norm  # the clip acted
    assert_trees_close(params, {"actor": flax_params(actor_critic.actor), "critic": flax_params(actor_critic.critic)},
                       rtol=1e-4, atol=1e-6)


def test_every_benchmark_setting_is_a_config_both_trainers_load():
    for setting in jax_ppo.SETTINGS:
        config = load_config(None, jax_ppo.setting_overrides(setting))
        assert config.num_envs == jax_ppo.SETTINGS[setting]["num_envs"], setting
    assert load_config(None, jax_ppo.setting_overrides("protocol")).runtime.teams == 6
