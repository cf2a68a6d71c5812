"""A pure-JAX PPO trainer in the PureJaxRL style: the yardstick our TorchRL trainer's speed is measured against.

Not part of the library and not meant to train teams: it exists so that `benchmarks/train.py reference` can run
our trainer (`trainers.ppo.loop.train`) and this one in the same process, on the same kitchens, network and batch,
and report how far our pipeline (TorchRL collector, DLPack crossings, Python loop) is from a whole run compiled
into one XLA program. Everything, rollout and PPO epochs included, is one `jax.lax.scan` over updates.

It reproduces our IPPO's semantics, read off `trainers/ppo/loop.py`, `trainers/config/` and TorchRL's
`ClipPPOLoss` (with the options `make_loss` gives it), so that the ratio measures the pipeline, not the algorithm:

- both agents' transitions are trained; one network for both agents (`share_params`) or one per agent (stacked
  parameters, vmapped over the agent axis, like TorchRL's `MultiAgentNetBase`);
- actor and critic are separate torsos of OUR "mlp" architecture (`torch_kitchen/models/`): flatten the
  uint8 observation H*W*26 as float -> 3 x (Linear(h) + ReLU) -> Linear(6 logits | 1 value), orthogonal init
  with gains sqrt(2) (hidden), 0.01 (policy), 1.0 (value), zero biases. JaxMARL's own IPPO for Overcooked has
  2 x 64 tanh layers; we match our network, not theirs;
- training reward = sparse + w * shaped, w from `trainers.ppo.advantages.shaping_weight_at` at the env steps after the
  update's batch; GAE(gamma, lambda) with the time limit as a terminal state (no bootstrap across it);
- `epochs` passes x `minibatches` minibatches of whole kitchens (a fresh permutation per epoch); the advantage
  standardised per minibatch over kitchens, steps and agents (mean, unbiased std clamped at 1e-6);
- ClipPPOLoss with `clip_value=True`: -min(r A, clip(r, 1 - eps, 1 + eps) A), value loss
  value_coef * max((target - v)^2, (target - v_clipped)^2) with v_clipped = v_old + clip(v - v_old, -eps, eps)
  (squared error without a 1/2), entropy loss -entropy_coef * entropy, each a mean over every element;
- the gradient clipped to max_grad_norm as `torch.nn.utils.clip_grad_norm_` does (scale by max / (norm + 1e-6)
  when above), then Adam(lr, eps=adam_eps), lr per update from `trainers.ppo.loop.learning_rate_at`.

`tests/benchmarks/test_jax_ppo.py` checks the GAE against `compute_advantages`, and the losses, gradients and
clipped Adam steps against ClipPPOLoss on the same weights. Known differences, none in the work done per step:
the random streams (initial weights, actions, kitchens) are JAX's, not torch's; only `architecture=mlp` and
`algorithm=ippo` are implemented. On the CPU the compiled run uses XLA's own thread pool (as the JAX env inside
our trainer does), not torch's threads.

    python benchmarks/jax_ppo.py [--setting jaxmarl|ik] [--updates 3] [key=value ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import torch

from jax_env import DELIVERY_REWARD, NUM_ACTIONS, Overcooked
from torch_kitchen.env import jax_device_for
from trainers.config import TrainConfig
from trainers.config.compose import load_config
from trainers.ppo.advantages import shaping_weight_at
from trainers.ppo.loop import learning_rate_at

# The two settings of `benchmarks/train.py reference`, as config overrides (the rest are TrainConfig defaults).
SETTINGS = {
    # JaxMARL's IPPO for Overcooked: native-size coord_ring, 16 kitchens x 128 steps, shaped reward annealed.
    "jaxmarl": {
        "levels": "coord_ring", "num_envs": 16, "rollout_steps": 128, "hidden": 64, "max_steps": 400,
        "ppo.epochs": 4, "ppo.minibatches": 4, "ppo.shaping_weight": 1.0, "ppo.shaping_anneal_steps": 2_500_000,
        "ppo.lr": 2.5e-4, "share_params": True,
    },
    # The paper's Infinite Kitchen shape: 32 kitchens x 256 steps, hidden 256, sparse reward.
    "ik": {
        "levels": "infinite", "num_envs": 32, "rollout_steps": 256, "hidden": 256, "max_steps": 256,
        "ppo.shaping_weight": 0.0, "share_params": True,
    },
}  # fmt: skip
# The paper's protocol: 6 teams (seeds) of the IK shape in one process.
SETTINGS["protocol"] = {**SETTINGS["ik"], "runtime.teams": 6}
SETTINGS["protocol_gnn"] = {**SETTINGS["protocol"], "architecture": "gnn"}  # ours only: the yardstick has no GNN
SETTINGS["protocol_sk"] = {**SETTINGS["protocol"], "share_params": False}  # the SK configs' networks, one per agent
# A dry run's: every path of a benchmark in seconds (benchmarks/gpu_checks.sh with SIZE=tiny).
SETTINGS["tiny"] = {**SETTINGS["jaxmarl"], "levels": "cramped_room", "num_envs": 4, "rollout_steps": 16, "hidden": 16,
                    "ppo.epochs": 1, "ppo.minibatches": 2, "max_steps": 16, "runtime.teams": 2}

# Torch's `clip_grad_norm_` divides by norm + 1e-6 (optax's `clip_by_global_norm` does not add it).
GRAD_NORM_EPS = 1e-6
# TorchRL's `_standardize` clamps the std at torch.finfo(float32).resolution.
ADVANTAGE_STD_MIN = 1e-6


def setting_overrides(setting: str) -> list[str]:
    """The `key=value` overrides of a named setting (`SETTINGS`)."""
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}, expected one of {', '.join(SETTINGS)}")
    return [f"{key}={value}" for key, value in SETTINGS[setting].items()]


# ------------------------------------------------------------------------------------------------ networks
class Torso(nn.Module):
    """One agent's network as our "mlp": uint8 [..., H, W, C] -> float32 [..., out_features]."""

    hidden: int
    out_features: int
    out_gain: float

    @nn.compact
    def __call__(self, observation: jax.Array) -> jax.Array:
        x = observation.reshape(*observation.shape[:-3], -1).astype(jnp.float32)
        for _ in range(3):  # the encoder's Linear, then the head's two hidden Linears
            x = nn.relu(linear(self.hidden, math.sqrt(2))(x))
        return linear(self.out_features, self.out_gain)(x)


def linear(features: int, gain: float) -> nn.Dense:
    """A Linear layer initialised as ours: orthogonal weights with `gain`, zero biases."""
    return nn.Dense(features, kernel_init=nn.initializers.orthogonal(gain), bias_init=nn.initializers.zeros)


class ActorCritic(NamedTuple):
    """Separate actor and critic torsos over both agents. Params: {"actor": ..., "critic": ...}; with one
    network per agent every leaf has a leading agent axis of 2."""

    actor: Torso
    critic: Torso
    share_params: bool

    def init(self, rng: jax.Array, obs_shape: tuple[int, int, int]) -> dict:
        observation = jnp.zeros(obs_shape, jnp.uint8)
        params = {}
        for name, rng_net in zip(("actor", "critic"), jax.random.split(rng)):
            net = getattr(self, name)
            if self.share_params:
                params[name] = net.init(rng_net, observation)
            else:
                params[name] = jax.vmap(net.init, in_axes=(0, None))(jax.random.split(rng_net), observation)
        return params

    def _apply(self, net: Torso, params, observation: jax.Array) -> jax.Array:
        if self.share_params:
            return net.apply(params, observation)
        # Agent i's parameters on agent i's observation: [..., 2, H, W, C] -> [..., 2, out].
        return jax.vmap(net.apply, in_axes=(0, -4), out_axes=-2)(params, observation)

    def logits(self, params: dict, observation: jax.Array) -> jax.Array:
        """uint8 [..., 2, H, W, C] -> float32 [..., 2, 6]."""
        return self._apply(self.actor, params["actor"], observation)

    def value(self, params: dict, observation: jax.Array) -> jax.Array:
        """uint8 [..., 2, H, W, C] -> float32 [..., 2]."""
        return self._apply(self.critic, params["critic"], observation)[..., 0]


def make_actor_critic(hidden: int, share_params: bool) -> ActorCritic:
    return ActorCritic(Torso(hidden, NUM_ACTIONS, 0.01), Torso(hidden, 1, 1.0), share_params)


# ------------------------------------------------------------------------------------------ rollout data
class Transition(NamedTuple):
    """One step of every kitchen, B kitchens; the rollout's scan stacks them to [T, B, ...]."""

    observation: jax.Array  # uint8 [B, 2, H, W, 26], the one acted on
    action: jax.Array  # int32 [B, 2]
    log_prob: jax.Array  # float32 [B, 2]
    value: jax.Array  # float32 [B, 2]
    reward: jax.Array  # float32 [B, 2], sparse (DELIVERY_REWARD per soup)
    shaped_reward: jax.Array  # float32 [B, 2], unweighted
    done: jax.Array  # bool [B], the time limit
    episode_deliveries: jax.Array  # float32 [B], the episode's soups where done, else 0


class Minibatch(NamedTuple):
    """What the PPO loss reads; any leading dims ([T, b] in training), agents [..., 2]."""

    observation: jax.Array  # uint8 [..., 2, H, W, 26]
    action: jax.Array  # int32 [..., 2]
    log_prob: jax.Array  # float32 [..., 2], at collection
    value: jax.Array  # float32 [..., 2], at collection
    advantage: jax.Array  # float32 [..., 2], not yet standardised
    target: jax.Array  # float32 [..., 2]


# ----------------------------------------------------------------------------------------------- GAE, loss
def generalized_advantages(reward: jax.Array, value: jax.Array, done: jax.Array, last_value: jax.Array,
                           gamma: float, gae_lambda: float) -> tuple[jax.Array, jax.Array]:
    """GAE over time-major data: reward, value float [T, B, 2], done bool [T, B], last_value [B, 2] (the value of
    the observation after the last step) -> (advantage, value target) [T, B, 2].

    A done step is terminal: neither its next value nor later advantages flow back across it, as in
    `trainers.ppo.advantages.compute_advantages` (TorchRL's GAE with done = terminated = the time limit).
    """
    next_value = jnp.concatenate([value[1:], last_value[None]], axis=0)
    not_done = 1.0 - done[..., None].astype(jnp.float32)  # [T, B, 1]: the same flag for both agents
    delta = reward + gamma * not_done * next_value - value

    def backwards(later_advantage, step):
        delta_t, not_done_t = step
        advantage = delta_t + gamma * gae_lambda * not_done_t * later_advantage
        return advantage, advantage

    _, advantage = jax.lax.scan(backwards, jnp.zeros_like(last_value), (delta, not_done), reverse=True)
    return advantage, advantage + value


def standardize(advantage: jax.Array) -> jax.Array:
    """Pooled over every element (kitchens, steps, agents), as ClipPPOLoss with normalize_advantage does."""
    return (advantage - advantage.mean()) / jnp.maximum(advantage.std(ddof=1), ADVANTAGE_STD_MIN)


def ppo_loss(params: dict, networks: ActorCritic, batch: Minibatch, config: TrainConfig
             ) -> tuple[jax.Array, dict[str, jax.Array]]:
    """ClipPPOLoss's total (policy + critic + entropy terms) and its logged parts, named as our trainer logs them."""
    eps = config.ppo.clip_epsilon
    logits = networks.logits(params, batch.observation)
    log_probs = jax.nn.log_softmax(logits)
    log_prob = jnp.take_along_axis(log_probs, batch.action[..., None], axis=-1)[..., 0]
    advantage = standardize(batch.advantage)
    log_ratio = log_prob - batch.log_prob
    # TorchRL clips the log-ratio to [log(1 - eps), log(1 + eps)]: the same as clipping the ratio.
    clipped_log_ratio = jnp.clip(log_ratio, math.log1p(-eps), math.log1p(eps))
    gain = jnp.minimum(jnp.exp(log_ratio) * advantage, jnp.exp(clipped_log_ratio) * advantage)
    policy_loss = -gain.mean()
    entropy = -(jnp.exp(log_probs) * log_probs).sum(-1).mean()
    entropy_loss = -config.ppo.entropy_coef * entropy

    value = networks.value(params, batch.observation)
    value_change = value - batch.value
    clipped_value = batch.value + jnp.clip(value_change, -eps, eps)
    value_error = jnp.maximum((batch.target - value) ** 2, (batch.target - clipped_value) ** 2)
    value_loss = config.ppo.value_coef * value_error.mean()

    total = policy_loss + value_loss + entropy_loss
    stats = {
        "losses/policy": policy_loss,
        "losses/value": value_loss,
        "losses/entropy_loss": entropy_loss,
        "losses/entropy": entropy,
        "losses/approx_kl": (batch.log_prob - log_prob).mean(),
        "losses/clip_fraction": (clipped_log_ratio != log_ratio).mean(),
        "losses/value_clip_fraction": (jnp.abs(value_change) > eps).mean(),
    }
    return total, stats


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """Adam(lr, eps=adam_eps) whose learning rate can be set per update (`with_learning_rate`)."""
    return optax.inject_hyperparams(optax.adam)(learning_rate=config.ppo.lr, eps=config.ppo.adam_eps)


def with_learning_rate(opt_state, learning_rate: jax.Array):
    """`opt_state` of `make_optimizer` with another learning rate for the steps to come."""
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": learning_rate})


def minibatch_step(params: dict, opt_state, networks: ActorCritic, optimizer: optax.GradientTransformation,
                   batch: Minibatch, config: TrainConfig) -> tuple[dict, object, dict[str, jax.Array]]:
    """One gradient step as our trainer's inner loop: loss, gradient clipped to max_grad_norm, Adam."""
    (_, stats), grads = jax.value_and_grad(ppo_loss, has_aux=True)(params, networks, batch, config)
    grad_norm = optax.tree.norm(grads)
    scale = jnp.minimum(1.0, config.ppo.max_grad_norm / (grad_norm + GRAD_NORM_EPS))
    grads = jax.tree_util.tree_map(lambda grad: grad * scale, grads)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, {**stats, "losses/grad_norm": grad_norm}


# --------------------------------------------------------------------------------------------------- train
def schedules(config: TrainConfig) -> dict[str, np.ndarray]:
    """Per update (float32 [num_updates]): the learning rate and the shaping weight, by our trainer's formulas."""
    updates = range(1, config.num_updates + 1)
    lr = [learning_rate_at(config, update) for update in updates]
    shaping = [shaping_weight_at(config, update * config.frames_per_batch) for update in updates]
    return {"learning_rate": np.asarray(lr, np.float32), "shaping_weight": np.asarray(shaping, np.float32)}


def check_supported(config: TrainConfig) -> None:
    if config.architecture != "mlp" or config.algorithm != "ippo":
        raise ValueError(
            f"the JAX reference implements IPPO with the mlp architecture only, got algorithm={config.algorithm}, "
            f"architecture={config.architecture}"
        )
    if config.num_envs % config.ppo.minibatches:
        raise ValueError(f"minibatches ({config.ppo.minibatches}) must divide num_envs ({config.num_envs})")
    if config.planned_steps >= 2**31:
        raise ValueError("the reference counts env steps in int32: keep total_steps below 2**31")


def rollout_step(env: Overcooked, networks, carry):
    """One step of every kitchen with actions sampled from the policy."""
    params, observation, states, deliveries, rng = carry
    rng, rng_action, rng_step = jax.random.split(rng, 3)
    logits = networks.logits(params, observation)
    action = jax.random.categorical(rng_action, logits)  # int32 [B, 2]
    log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], axis=-1)[..., 0]
    value = networks.value(params, observation)
    next_observation, states, reward, done, info = env.step_batch(rng_step, states, action)
    # Soups delivered this episode, as KitchenEnv counts them: the sparse reward is DELIVERY_REWARD per soup.
    deliveries = deliveries + (reward[:, 0] / DELIVERY_REWARD).astype(jnp.int32)
    transition = Transition(observation, action, log_prob, value, reward, info["shaped_reward"], done,
                            jnp.where(done, deliveries, 0).astype(jnp.float32))
    deliveries = jnp.where(done, 0, deliveries)
    return (params, next_observation, states, deliveries, rng), transition


def ppo_epoch(networks, optimizer, config: TrainConfig, carry):
    """One pass over the batch in minibatches of whole kitchens, shuffled."""
    params, opt_state, data, rng = carry
    num_envs, minibatches = config.num_envs, config.ppo.minibatches
    rng, rng_perm = jax.random.split(rng)
    kitchens = jax.random.permutation(rng_perm, num_envs).reshape(minibatches, num_envs // minibatches)

    def minibatch(carry, indices):
        params, opt_state = carry
        batch = jax.tree_util.tree_map(lambda x: jnp.take(x, indices, axis=1), data)  # [T, b, ...]
        params, opt_state, stats = minibatch_step(params, opt_state, networks, optimizer, batch, config)
        return (params, opt_state), stats

    (params, opt_state), stats = jax.lax.scan(minibatch, (params, opt_state), kitchens)
    return (params, opt_state, data, rng), stats


def update_metrics(stats: dict, transitions: Transition, target: jax.Array, env_steps: jax.Array, schedule: dict,
                   max_steps: int) -> dict[str, jax.Array]:
    """An update's metrics, named as our trainer logs them: the losses' means over every minibatch of every
    epoch, the steps, episodes and deliveries, the schedules, the explained variance."""
    episodes = transitions.done.sum()
    residual_variance = (target - transitions.value).var(ddof=1)
    return {
        **{key: value.mean() for key, value in stats.items()},
        "charts/env_steps": env_steps,
        "charts/episodes": episodes,
        "charts/episode_deliveries": jnp.where(
            episodes > 0, transitions.episode_deliveries.sum() / jnp.maximum(episodes, 1), jnp.nan
        ),
        "charts/episode_return": transitions.reward.mean() * max_steps,
        "charts/shaped_return": transitions.shaped_reward.mean() * max_steps,
        "charts/learning_rate": schedule["learning_rate"],
        "charts/shaping_weight": schedule["shaping_weight"],
        "losses/explained_variance": 1.0 - residual_variance / target.var(ddof=1),
    }


def make_train(config: TrainConfig) -> Callable[[jax.Array], dict[str, jax.Array]]:
    """`train(rng) -> metrics`: the whole run (config.num_updates updates of num_envs x rollout_steps steps), pure
    and jittable. Metrics: name -> [num_updates], named as our trainer logs them, plus "charts/env_steps" and
    "charts/episodes" (episodes ended in the update); "charts/episode_deliveries" is NaN where none ended."""
    check_supported(config)
    env = Overcooked(config.levels, max_steps=config.max_steps)
    networks = make_actor_critic(config.hidden, config.share_params)
    optimizer = make_optimizer(config)
    num_envs, steps = config.num_envs, config.rollout_steps
    per_update = {key: jnp.asarray(value) for key, value in schedules(config).items()}

    def rollout(carry, _):
        return rollout_step(env, networks, carry)

    def epoch(carry, _):
        return ppo_epoch(networks, optimizer, config, carry)

    def update(runner, schedule):
        """Collect num_envs x rollout_steps steps, then the PPO epochs: one update of our trainer."""
        params, opt_state, observation, states, deliveries, rng, env_steps = runner
        (_, observation, states, deliveries, rng), transitions = jax.lax.scan(
            rollout, (params, observation, states, deliveries, rng), None, length=steps
        )
        env_steps = env_steps + num_envs * steps
        reward = transitions.reward + schedule["shaping_weight"] * transitions.shaped_reward
        last_value = networks.value(params, observation)
        advantage, target = generalized_advantages(reward, transitions.value, transitions.done, last_value,
                                                   config.ppo.gamma, config.ppo.gae_lambda)
        data = Minibatch(transitions.observation, transitions.action, transitions.log_prob, transitions.value,
                         advantage, target)

        opt_state = with_learning_rate(opt_state, schedule["learning_rate"])
        rng, rng_epochs = jax.random.split(rng)
        (params, opt_state, _, _), stats = jax.lax.scan(
            epoch, (params, opt_state, data, rng_epochs), None, length=config.ppo.epochs
        )

        metrics = update_metrics(stats, transitions, target, env_steps, schedule, config.max_steps)
        return (params, opt_state, observation, states, deliveries, rng, env_steps), metrics

    def train(rng: jax.Array) -> dict[str, jax.Array]:
        rng, rng_init, rng_reset = jax.random.split(rng, 3)
        params = networks.init(rng_init, env.obs_shape)
        opt_state = optimizer.init(params)
        observation, states = env.reset_batch(rng_reset, num_envs)
        runner = (params, opt_state, observation, states, jnp.zeros(num_envs, jnp.int32), rng, jnp.int32(0))
        _, metrics = jax.lax.scan(update, runner, per_update)
        return metrics

    return train


def run_reference(config: TrainConfig | Sequence[str], seed: int | None = None, repeats: int = 1
                  ) -> tuple[float, dict[str, np.ndarray]]:
    """Compiles the run of `config` (a TrainConfig or its `key=value` overrides), then runs it timed.

    Returns (env steps per second of the compiled run, compilation excluded, the median of `repeats` runs of the
    same program; metrics name -> [num_updates]). Runs on the JAX device matching `config.runtime.device`; `seed`
    defaults to `config.seed`. With `config.runtime.teams` = K > 1 one timed run trains seeds seed .. seed + K - 1 one
    after the other through the same compiled program (steps/s count every team's; metrics are the last team's):
    on the CPU, vmapping the run over the seeds as PureJaxRL does hung inside XLA at the paper's shape.
    """
    if not isinstance(config, TrainConfig):
        config = load_config(None, list(config))
    device = jax_device_for(torch.device(config.runtime.device))
    first = config.seed if seed is None else seed
    keys = [jax.device_put(jax.random.PRNGKey(first + team), device) for team in range(config.runtime.teams)]
    seconds = []
    with jax.default_device(device):
        compiled = jax.jit(make_train(config)).lower(keys[0]).compile()
        for _ in range(repeats):
            start = time.perf_counter()
            for key in keys:
                metrics = jax.block_until_ready(compiled(key))
            seconds.append(time.perf_counter() - start)
    steps_per_second = config.runtime.teams * config.planned_steps / float(np.median(seconds))
    return steps_per_second, {key: np.asarray(value) for key, value in metrics.items()}


def pooled_deliveries(metrics: dict[str, np.ndarray], updates) -> float:
    """Mean deliveries of every episode that ended in `updates` (an index or mask into the per-update metrics);
    NaN where none ended."""
    episodes = metrics["charts/episodes"][updates]
    delivered = np.nan_to_num(metrics["charts/episode_deliveries"][updates]) * episodes
    return float(delivered.sum() / episodes.sum()) if episodes.sum() else float("nan")


def describe(steps_per_second: float, metrics: dict[str, np.ndarray], every: int = 1) -> str:
    """A table of every `every`-th update's main metrics (deliveries: the mean of the episodes that ended since the
    previous row), then the speed."""
    columns = {
        "env steps": ("charts/env_steps", "{:>11,.0f}"),
        "deliveries": ("charts/episode_deliveries", "{:>10.2f}"),
        "policy": ("losses/policy", "{:>8.4f}"),
        "value": ("losses/value", "{:>9.4f}"),
        "entropy": ("losses/entropy", "{:>7.3f}"),
        "grad norm": ("losses/grad_norm", "{:>9.3f}"),
    }
    lines = ["  ".join(f"{name:>{len(fmt.format(0.0))}s}" for name, (_, fmt) in columns.items())]
    updates, previous = len(metrics["charts/env_steps"]), 0
    for index in sorted({*range(0, updates, every), updates - 1}):
        row = {key: float(metrics[key][index]) for key, _ in columns.values()}
        row["charts/episode_deliveries"] = pooled_deliveries(metrics, slice(previous, index + 1))
        lines.append("  ".join(fmt.format(row[key]) for key, fmt in columns.values()))
        previous = index + 1
    lines.append(f"{steps_per_second:,.0f} env steps/s (compiled run, compilation excluded)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", choices=list(SETTINGS), default="jaxmarl")
    parser.add_argument("--updates", type=int, default=3)
    parser.add_argument("--every", type=int, default=1, help="print every n-th update")
    parser.add_argument("--repeats", type=int, default=1, help="timed runs of the compiled program (median)")
    parser.add_argument("overrides", nargs="*", help="config overrides, key=value, after the setting's")
    args = parser.parse_args(argv)
    config = load_config(None, [*setting_overrides(args.setting), *args.overrides])
    config = dataclasses.replace(config, total_steps=args.updates * config.frames_per_batch).check()
    print(describe(*run_reference(config, repeats=args.repeats), every=args.every))

if __name__ == "__main__":
    main()
