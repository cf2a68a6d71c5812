"""Rollouts inside one XLA program: the kitchens and the teams' acting passes stepped together by `jax.lax.scan`.

`KitchenCollector` steps the kitchens' JAX program once per step and runs the teams' torch networks in between, so
the host launches every step's work. Where every team's policy is an acting pass over chains of Flatten, Linear,
ReLU and agent-centred linear layers (the MLP architectures, the main job's "ego_mlp" among them), `XlaCollector`
runs those chains in JAX as well, and a whole batch of steps is one program: the host launches it once per batch.
The chains read the teams' own weights, taken again at every batch; their outputs agree with torch's to float32
rounding (the sums run in another order).

Actions are drawn from JAX's random streams, one per team, each seeded at every batch from the team's torch stream
(`RandomStream`), so a resumed run draws what it would have. Everything else is `KitchenCollector`'s: the batch's
keys, shapes and dtypes, the kitchens stepped and reset by the env's own programs and keys (the steps a
`KitchenEnv` takes with those actions, bit for bit; `tests/torch_kitchen/test_xla_rollout.py`), the env left where
the batch ended (its checkpoint, its next reset). Recurrent and graph models, and envs with transforms, collect
with `KitchenCollector` (`trainers.rollout.make_collector` picks).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from jax_env.observation import Channel
from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.env import KitchenEnv, ProgramCache, kitchen_programs, output_entries
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, OBSERVATION, SHAPED_REWARD, VALUE
from torch_kitchen.rollout import NEXT, InPlaceCollector, as_path, as_tensordict
from torch_kitchen.teams import TeamPolicy, layers_of, stackable_acting

# A network's layers as JAX runs them: ("flatten", start, end), ("linear",), ("relu",), ("egocentric", (H, W, C)).
Chain = tuple[tuple, ...]


def jax_chain(network: nn.Module) -> Chain | None:
    """A chain of (nested `nn.Sequential`s of) Flatten, Linear, `EgocentricLinear` and ReLU layers as JAX runs it
    (`run_chain`), or None where it holds another layer (a bias-free linear layer, a graph layer)."""
    chain = []
    for layer in layers_of(network):
        if isinstance(layer, nn.Flatten):
            chain.append(("flatten", layer.start_dim, layer.end_dim))
        elif isinstance(layer, nn.ReLU):
            chain.append(("relu",))
        elif isinstance(layer, nn.Linear) and layer.bias is None:
            return None
        elif isinstance(layer, EgocentricLinear):
            chain.append(("egocentric", layer.obs_shape))
        elif isinstance(layer, nn.Linear):
            chain.append(("linear",))
        else:
            return None
    return tuple(chain)


def chain_weights(network: nn.Module) -> list[torch.Tensor]:
    """The weights and biases of a chain's linear layers, in order."""
    return [tensor for layer in layers_of(network) if isinstance(layer, nn.Linear)
            for tensor in (layer.weight, layer.bias)]


def agent_window(obs: jax.Array) -> jax.Array:
    """`EgocentricLinear.window` in JAX: observations [..., H, W, C] -> their agent-centred windows [..., (2H - 1) *
    (2W - 1) * C], flat. The kitchen padded by H - 1 rows and W - 1 columns of zeros on every side holds the
    agent's window at the agent's own cell: a slice where the layer scatters. The slices are taken one kitchen
    after another (`lax.map`): under vmap they become one gather, 7x slower on a CPU."""
    *batch, height, width, channels = obs.shape
    flat = obs.reshape(-1, height, width, channels)
    agent_cell = flat[..., Channel.SELF].reshape(len(flat), -1).argmax(-1)  # an all-zero row: cell 0, as torch's
    padded = jnp.pad(flat, ((0, 0), (height - 1, height - 1), (width - 1, width - 1), (0, 0)))

    def window(kitchen_and_cell):
        kitchen, cell = kitchen_and_cell
        corner = (cell // width, cell % width, 0)
        return jax.lax.dynamic_slice(kitchen, corner, (2 * height - 1, 2 * width - 1, channels))

    return jax.lax.map(window, (padded, agent_cell)).reshape(*batch, -1)


def run_chain(chain: Chain, weights: Sequence[jax.Array], x: jax.Array) -> jax.Array:
    """What the torch chain computes on x (uint8 observations are cast to float32 at the first linear layer), in
    float32 at full precision (a GPU's TF32 products would stray from torch's)."""
    weights = iter(weights)
    for op, *args in chain:
        if op == "flatten":
            start, end = (dim % x.ndim for dim in args)
            x = x.reshape(*x.shape[:start], -1, *x.shape[end + 1:])
        elif op == "relu":
            x = jax.nn.relu(x)
        else:
            if op == "egocentric":
                x = agent_window(x)
            weight, bias = next(weights), next(weights)
            x = jnp.matmul(x.astype(weight.dtype), weight.T, precision=jax.lax.Precision.HIGHEST) + bias
    return x


def xla_chains(env: EnvBase, policy) -> tuple[Chain, Chain] | None:
    """The (policy, value) chains the teams of `policy` act with, where `XlaCollector` can run them over `env`: a
    bare `KitchenEnv` and a `TeamPolicy` whose every team acts with an acting pass over MLP chains; else None."""
    if not isinstance(env, KitchenEnv) or not isinstance(policy, TeamPolicy) or not policy.acts_on_observation:
        return None
    networks = stackable_acting(list(policy.policies))
    if networks is None:
        return None
    chains = {(jax_chain(policy_net), jax_chain(value_net)) for policy_net, value_net in networks}
    if len(chains) != 1 or None in next(iter(chains)):
        return None
    return next(iter(chains))


_PROGRAMS = ProgramCache(kept=8)


def rollout_program(env: KitchenEnv, chains: tuple[Chain, Chain], steps: int) -> Callable:
    """The jitted rollout of `steps` steps of every kitchen of `env` with the teams acting by `chains` (built once
    per kitchen settings, shape and chains, and shared, as the env's own programs are):
    (weights, (start states, states, deliveries, env key), act keys [teams, 2], carrier) -> ((states, deliveries,
    env key, carrier), records [B, steps, ...]), where carrier = (observation, scalars, done), the policy's next
    input as the env's programs give it, and records = (observation, scalars, done, logits, action, log-prob,
    value, next observation, next scalars, next done)."""
    key = (env.jax_env.settings, env.num_envs, env.teams, env.pinned_levels is not None, chains, steps)
    return _PROGRAMS.get(key, lambda: _build_rollout(env, chains, steps))


def _build_rollout(env: KitchenEnv, chains: tuple[Chain, Chain], steps: int) -> Callable:
    programs = kitchen_programs(env.jax_env, env.num_envs, env.teams, env.pinned_levels is not None, packed=False)
    policy_chain, value_chain = chains
    teams, team_size = env.teams, env.team_size

    def act(weights, keys, observation):
        def team(policy_weights, value_weights, key, observation):
            logits = run_chain(policy_chain, policy_weights, observation)
            action = jax.random.categorical(key, logits)
            log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
            return logits, action, log_prob, run_chain(value_chain, value_weights, observation)

        by_team = observation.reshape(teams, team_size, *observation.shape[1:])
        outputs = jax.vmap(team)(*weights, keys, by_team)
        return [value.reshape(teams * team_size, *value.shape[2:]) for value in outputs]

    def step(start_states, weights, carry, _):
        states, deliveries, env_key, act_keys, carrier = carry
        act_keys, used = jax.vmap(jax.random.split, out_axes=1)(act_keys)
        logits, action, log_prob, value = act(weights, used, carrier[0])
        states, deliveries, stepped = programs.step(states, deliveries, action.astype(jnp.int32))
        ended = stepped[2][:, 0]

        def reset(_):  # as `KitchenEnv._reset` after TorchRL's partial reset, merged by TorchRL's rule
            kept, used_key = programs.split_keys(env_key)
            fresh_states, fresh_deliveries, fresh = jax.lax.cond(
                ended.all(),
                lambda: programs.reset_all(start_states, used_key),
                lambda: programs.reset_masked(start_states, used_key, states, deliveries, ended))
            merged = [jnp.where(ended.reshape(-1, *[1] * (a.ndim - 1)), a, b) for a, b in zip(fresh, stepped)]
            return fresh_states, fresh_deliveries, kept, tuple(merged)

        next_states, next_deliveries, env_key, next_carrier = jax.lax.cond(
            ended.any(), reset, lambda _: (states, deliveries, env_key, tuple(stepped)), None)
        record = (*carrier, logits, action, log_prob, value, *stepped)
        return (next_states, next_deliveries, env_key, act_keys, next_carrier), record

    @jax.jit
    def rollout(weights, kitchens, act_keys, carrier):
        start_states, states, deliveries, env_key = kitchens
        carry = (states, deliveries, env_key, act_keys, carrier)
        carry, records = jax.lax.scan(lambda c, x: step(start_states, weights, c, x), carry, None, length=steps)
        states, deliveries, env_key, _, carrier = carry
        return (states, deliveries, env_key, carrier), [jnp.swapaxes(record, 0, 1) for record in records]

    return rollout


class XlaCollector(InPlaceCollector):
    """A TorchRL collector whose batches are rolled out inside one XLA program (see the module docstring):
    `KitchenCollector`'s batches, keys and storage (an `InPlaceCollector`), with the actions drawn by JAX.
    `xla_chains(env, policy)` must not be None (`trainers.rollout.make_collector` checks)."""

    def __init__(self, env: KitchenEnv, policy: TeamPolicy, frames_per_batch: int, total_frames: int = -1):
        super().__init__(env, frames_per_batch, total_frames)
        chains = xla_chains(env, policy)
        if chains is None:
            raise ValueError("XlaCollector runs acting passes over MLP chains on a bare KitchenEnv; collect this "
                             "policy with KitchenCollector")
        self.policy = policy
        self._program = rollout_program(env, chains, self.steps)
        self._networks = stackable_acting(list(policy.policies))
        with torch.no_grad():
            first = env.reset()
        self._carrier = self._carrier_of(first)

    def _to_jax(self, tensor: torch.Tensor) -> jax.Array:
        return jax.device_put(jax.dlpack.from_dlpack(tensor.detach().contiguous()), self.env.jax_device)

    def _carrier_of(self, tensordict: TensorDictBase) -> tuple[jax.Array, ...]:
        """The env's reset output as the programs give it: (observation, scalars [B, 6], done), the scalars' reward
        columns zero (a reset earns nothing)."""
        shaped = tensordict.get(SHAPED_REWARD).squeeze(-1)
        scalars = torch.cat([torch.zeros_like(shaped), shaped, tensordict.get("deliveries"),
                             tensordict.get("episode_deliveries")], dim=-1)
        return tuple(self._to_jax(value) for value in (tensordict.get(OBSERVATION), scalars, tensordict.get("done")))

    def _weights(self) -> tuple[list[jax.Array], list[jax.Array]]:
        """The teams' current weights, stacked along a leading team dim."""
        with torch.no_grad():
            return tuple([self._to_jax(torch.stack(tensors)) for tensors in zip(*map(chain_weights, nets))]
                         for nets in zip(*self._networks))

    def _act_keys(self) -> jax.Array:
        """uint32 [teams, 2]: each team's key for this batch's draws, from its torch stream."""
        seeds = []
        for stream in self.policy.streams:
            with stream.active():
                seeds.append(torch.randint(0, 2**31 - 1, (2,), dtype=torch.int64))
        return self._to_jax(torch.stack(seeds).to(torch.int32)).view(jnp.uint32)

    def rollout(self) -> TensorDictBase:
        """The next batch: `steps` steps of every kitchen, written into the storage; the env left where they end."""
        env = self.env
        (states, deliveries, key, self._carrier), records = self._program(
            self._weights(), env.kitchens(), self._act_keys(), self._carrier)
        env.continue_from(states, deliveries, key, self._carrier[0])
        observation, scalars, done, logits, action, log_prob, value, *stepped = map(torch.from_dlpack, records)
        values = {**output_entries(observation, scalars, done, with_reward=False),
                  LOGITS: logits, ACTION: action, LOG_PROB: log_prob, VALUE: value,
                  **{(NEXT, *as_path(key)): tensor for key, tensor in output_entries(*stepped, True).items()}}
        if self._storage is None:
            self._storage = as_tensordict({key: value.clone() for key, value in values.items()},
                                          torch.Size([env.num_envs, self.steps]), env.device)
            self._storage[ACTION] = self._storage[ACTION].long()
            self._storage.refine_names(..., "time")
            self._keys = list(self._storage.keys(True, True))
        else:
            torch._foreach_copy_([self._storage.get(key) for key in self._keys], [values[key] for key in self._keys])
        return self._storage
