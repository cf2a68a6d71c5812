"""Rollouts inside one XLA program: the kitchens and the teams' acting passes stepped together by `jax.lax.scan`.

`KitchenCollector` steps the kitchens' JAX program once per step and runs the teams' torch networks in between, so
the host launches every step's work. Where every team's networks run in JAX as well, `XlaCollector` runs them
beside the kitchens, and a whole batch of steps is one program: the host launches it once per batch. That is:

    feed-forward   acting passes over chains of Flatten, Linear, ReLU, agent-centred linear layers and the GNN's
                   graph encoder (the MLP architectures, the main job's "ego_mlp", "gnn"), shared by the agents or one
                   network per agent (`share_params=false`, the SK configs'), on a bare `KitchenEnv`
    recurrent      "mlp_lstm" and "gnn_lstm", shared or per agent: actor and critic each an encoder, an LSTM cell
                   and a head (LayerNorm, Linear, ReLU), on a `KitchenEnv` with the model's transforms alone
                   (`ActorCritic.env_transforms()`: InitTracker and the primer of the LSTM states)

Each layer's JAX twin is in `torch_kitchen.xla_layers`. On a CPU a network's first layer over the observations
reads a cell table (`tabled`; its products with every view a cell can give, made once per batch by `table_weights`),
on a GPU the dense product.

The chains read the teams' own weights, taken again at every batch; their outputs agree with torch's to float32
rounding (the sums run in another order). A recurrent team's states are carried from step to step and from batch
to batch inside the program, zeroed where an episode starts ("is_init"), as `MultiAgentLSTM` zeroes them, and the
batch holds them as the transforms give them: the state each step read, ("next", ...) the state it left.

Actions are drawn from JAX's random streams, one per team, each seeded at every batch from the team's torch stream
(`RandomStream`), so a resumed run draws what it would have. Everything else is `KitchenCollector`'s: the batch's
keys, shapes and dtypes, the kitchens stepped and reset by the env's own programs and keys (the steps a
`KitchenEnv` takes with those actions, bit for bit; `tests/torch_kitchen/test_xla_rollout.py`), the env left where
the batch ended (its checkpoint, its next reset). E3T's and other transforms, and other algorithms' acting modules,
collect with `KitchenCollector` (`trainers.ppo.collection.make_collector` picks).

Zoo cooks (`trainers.algorithms.zoo_ippo`: a team beside scripted cooks of the zoo's conventions in a share of its
kitchens, or beside one stranger in all of them for its best response) play inside the program as well, where one
team trains: the env's `ZooSeats` draws each episode's seats in the program (from a key its generator hands out per
batch, its draws kept up to date for its checkpoint), and the cooks plan with `jax_env.cook` in their seats
(`torch_kitchen.partners.zoo_seats.cook_actions`), as `ZooPartners` does outside.

A teacher's guidance (`GuidedPolicy`, distillation's DAgger rounds) plays inside the program too: the teacher plans for
every seat with `jax_env.cook`, each seat takes its drawn action instead of the learner's with the guide's share, and
the batch holds its action distribution (`TEACHER_PROBS`); the teacher and the share are the program's inputs, so one
program serves every round.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.envs import Compose, EnvBase, InitTracker, TensorDictPrimer, TransformedEnv
from torchrl.modules import ProbabilisticActor

from jax_env import NUM_ACTIONS
from jax_env.cook import cook_logits, floor_tables, walkable_floor
from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.env import KitchenEnv, ProgramCache, kitchen_programs, output_entries
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, N_AGENTS, OBSERVATION, SHAPED_REWARD, VALUE
from torch_kitchen.models.acting import ActingPass, ActionDistribution, layers_of, plain_network
from torch_kitchen.models.networks import GraphEncoder
from torch_kitchen.models.recurrence import MultiAgentLSTM
from torch_kitchen.partners.guide import TEACHER_PROBS, GuidedPolicy
from torch_kitchen.partners.pairing import SeatedPolicy
from torch_kitchen.partners.scripted_cook import ScriptedCook, stacked_conventions
from torch_kitchen.partners.zoo_seats import ZOO_COOK, ZooPartners, ZooSeats, cook_actions, draw_seats, seating
from torch_kitchen.rollout import NEXT, InPlaceCollector, as_path, as_tensordict
from torch_kitchen.teams import ACTING_KEYS, TeamPolicy, acting_pass_of
from torch_kitchen.torchrl_internals import TEMPLATE, MultiAgentNet
from torch_kitchen.xla_layers import (
    agent_window,
    cell_table,
    cell_table_weights,
    dense,
    graph_runs,
    graph_scene,
    graph_weights,
    layer_norm,
    lstm_cell,
)

# A network's layers as JAX runs them: ("flatten", start, end), ("linear",), ("relu",), ("egocentric", (H, W, C)),
# ("layer_norm", eps), ("lstm",), ("graph",), ("cell_table", (H, W, C), agent-centred) (`torch_kitchen.xla_layers`
# computes each; the last is `tabled`'s first layer on a CPU), or a network per agent:
# (("per_agent", chain),), one agent's chain run on each agent's observation (and LSTM state) with its own weights.
Chain = tuple[tuple, ...]
IS_INIT = "is_init"  # InitTracker's key: the kitchens whose episode starts at this step


class ActingNetwork(NamedTuple):
    """A team's policy or value network as XLA runs it: its layers in order (nested `nn.Sequential`s, with an
    `nn.LSTM` in a recurrent one), holding the team's weights, and the env's keys of its LSTM state (h, c), ()
    without one. With a network per agent, `layers` are one agent's (their structure, not its weights) and
    `agent_parts` the `MultiAgentNet`s and `MultiAgentLSTM` that hold every agent's weights, in order."""

    layers: nn.Module
    state_keys: tuple = ()
    agent_parts: tuple = ()


def network_chain(network: ActingNetwork) -> Chain | None:
    """The chain JAX runs for an acting network (`jax_chain`; a network per agent as one agent's chain), or None
    where a layer does not convert."""
    chain = jax_chain(network.layers)
    return chain if chain is None or not network.agent_parts else (("per_agent", chain),)


def network_weights(network: ActingNetwork) -> list[torch.Tensor]:
    """The acting network's weights in the order its chain reads them; with a network per agent each [n_agents, ...],
    the agents' weights stacked."""
    if not network.agent_parts:
        return chain_weights(network.layers)
    weights = []
    for part in network.agent_parts:
        if isinstance(part, MultiAgentLSTM):
            weights += [torch.stack(agents) for agents in zip(*(chain_weights(lstm.lstm) for lstm in part.lstms))]
            continue
        template = part.thread_template()
        with part.params.to_module(template):  # the template then holds the stacked weights, as in its forward
            weights += chain_weights(template)
    return weights


def jax_chain(network: nn.Module) -> Chain | None:
    """A chain of (nested `nn.Sequential`s of) Flatten, Linear, `EgocentricLinear`, ReLU, LayerNorm and `GraphEncoder`
    layers, and at most one single-layer LSTM, as JAX runs it (`run_chain`), or None where it holds another layer (a
    bias-free linear layer, a graph layer built otherwise)."""
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
        elif isinstance(layer, nn.LayerNorm) and len(layer.normalized_shape) == 1 and layer.bias is not None:
            chain.append(("layer_norm", layer.eps))
        elif isinstance(layer, nn.LSTM) and _one_cell(layer) and ("lstm",) not in chain:  # one state per network
            chain.append(("lstm",))
        elif isinstance(layer, GraphEncoder) and graph_runs(layer):
            chain.append(("graph",))
        else:
            return None
    return tuple(chain)


def _one_cell(lstm: nn.LSTM) -> bool:
    """Whether an LSTM is one cell that `lstm_cell` runs: one layer, one direction, biases, no projection."""
    return lstm.num_layers == 1 and lstm.bias and not lstm.bidirectional and lstm.proj_size == 0


def chain_weights(network: nn.Module) -> list[torch.Tensor]:
    """The parameters of a chain's layers in the order `run_chain` reads them: each linear layer's and LayerNorm's
    weight and bias, an LSTM's weight_ih, weight_hh, bias_ih and bias_hh, a graph encoder's `graph_weights`."""
    weights = []
    for layer in layers_of(network):
        if isinstance(layer, GraphEncoder):
            weights += graph_weights(layer)
        elif isinstance(layer, nn.Linear | nn.LayerNorm):
            weights += [layer.weight, layer.bias]
        elif isinstance(layer, nn.LSTM):
            weights += [layer.weight_ih_l0, layer.weight_hh_l0, layer.bias_ih_l0, layer.bias_hh_l0]
    return weights


def run_chain(chain: Chain, weights: Sequence[jax.Array], x: jax.Array, state: tuple = ()) -> tuple[jax.Array, tuple]:
    """What the torch chain computes on x (uint8 observations are cast to float32 at the first linear layer), in
    float32 at full precision, and its LSTM's next state: state (h, c) float32 [..., 1, hidden] each, as the env
    carries them, () for a chain without an LSTM. -> (output, next state)."""
    weights = iter(weights)
    for op, *args in chain:
        if op == "flatten":
            start, end = (dim % x.ndim for dim in args)
            x = x.reshape(*x.shape[:start], -1, *x.shape[end + 1:])
        elif op == "relu":
            x = jax.nn.relu(x)
        elif op == "layer_norm":
            x = layer_norm(x, next(weights), next(weights), *args)
        elif op == "lstm":
            x, state = lstm_cell([next(weights) for _ in range(4)], x, state)
        elif op == "graph":
            x = graph_scene(x, [next(weights) for _ in range(6)])
        elif op == "cell_table":
            x = cell_table(x, next(weights), next(weights), next(weights), args[1])
        elif op == "per_agent":  # x [..., n_agents, H, W, C], state [..., n_agents, 1, h]: each agent's own
            (agent_chain,) = args
            agents = x.ndim - 4  # the agent dim, after as many leading dims in every input and output
            x, state = jax.vmap(lambda agent_weights, view, agent_state: run_chain(agent_chain, agent_weights, view,
                                                                                   agent_state),
                                in_axes=(0, agents, agents), out_axes=agents)(list(weights), x, state)
        else:
            if op == "egocentric":
                x = agent_window(x)
            x = dense(x, next(weights), next(weights))
    return x, state


def tabled(chain: Chain, obs_shape: tuple[int, int, int]) -> Chain:
    """The chain with its first layer over the observations run from a cell table (`cell_table`, one row summed per
    cell where the product reads mostly zeros): an agent-centred layer, or a Flatten of the observation then a linear
    layer; a network per agent's likewise. Its weights then go through `table_weights` once per batch."""
    if chain[0][0] == "per_agent":
        return (("per_agent", tabled(chain[0][1], obs_shape)),)
    if chain[0][0] == "egocentric":
        return (("cell_table", chain[0][1], True), *chain[1:])
    if chain[:2] == (("flatten", -3, -1), ("linear",)):
        return (("cell_table", tuple(obs_shape), False), *chain[2:])
    return chain


def table_weights(chain: Chain, weights: Sequence[jax.Array]) -> list[jax.Array]:
    """A chain's weights as `run_chain` reads them: a "cell_table" layer's weight made its table and urgency rows
    (`cell_table_weights`), every other weight as it is; a network per agent's, agent by agent."""
    op, *args = chain[0]
    if op == "per_agent":
        return jax.vmap(lambda agent_weights: table_weights(args[0], agent_weights))(list(weights))
    if op != "cell_table":
        return list(weights)
    weight, *rest = weights
    return [*cell_table_weights(weight, *args), *rest]


def restarted(is_init: jax.Array, state: tuple) -> tuple:
    """An LSTM state [B, ...] zeroed in the kitchens whose episode starts (is_init bool [B, 1]), as `MultiAgentLSTM`
    zeroes it and the env's primer gives it at a reset."""
    return jax.tree.map(lambda value: jnp.where(is_init.reshape(-1, *[1] * (value.ndim - 1)), 0, value), state)


def recurrent_network(network: TensorDictModuleBase, out_key) -> ActingNetwork | None:
    """`make_network`'s recurrent network writing `out_key` (an encoder, a `MultiAgentLSTM`, a head, all shared by
    the agents or all per agent) as an `ActingNetwork`; else None (shared and per-agent parts mixed, extra inputs to
    the head, another model)."""
    if not isinstance(network, TensorDictSequential) or len(network.module) != 3:
        return None
    encoder, memory, head = network.module
    if not (isinstance(memory, MultiAgentLSTM)
            and all(isinstance(part, TensorDictModule) and isinstance(part.module, MultiAgentNet)
                    and part.module.share_params == memory.share_params for part in (encoder, head))
            and list(encoder.in_keys) == [OBSERVATION] and list(encoder.out_keys) == memory.in_keys[:1]
            and list(head.in_keys) == memory.out_keys[:1] and list(head.out_keys) == [out_key]):
        return None
    state_keys = tuple(memory.in_keys[1:3])
    if memory.share_params:
        layers = nn.Sequential(encoder.module.shared_net(), memory.lstms[0].lstm, head.module.shared_net())
        return ActingNetwork(layers, state_keys)
    one_agent = nn.Sequential(getattr(encoder.module, TEMPLATE), memory.lstms[0].lstm, getattr(head.module, TEMPLATE))
    return ActingNetwork(one_agent, state_keys, agent_parts=(encoder.module, memory, head.module))


def recurrent_acting(policy: TensorDictModuleBase) -> tuple[ActingNetwork, ActingNetwork] | None:
    """A recurrent model's collection policy, `ActorCritic.acting_policy()` (its sampling actor, then its critic),
    as its (policy, value) networks; else None (an algorithm's acting modules between them, another model)."""
    if not isinstance(policy, TensorDictSequential) or len(policy.module) != 2:
        return None
    actor, critic = policy.module
    if not isinstance(actor, ProbabilisticActor) or len(actor.module) != 2:
        return None
    network, sampler = actor.module
    if getattr(sampler, "distribution_class", None) is not ActionDistribution or \
            list(sampler.out_keys) != [ACTION, LOG_PROB]:
        return None
    pair = recurrent_network(network, LOGITS), recurrent_network(critic, VALUE)
    return None if None in pair else pair


def feed_forward_acting(acting: ActingPass | None) -> tuple[ActingNetwork, ActingNetwork] | None:
    """An acting pass's (policy, value) networks: shared by the agents (`ActingPass.shared_networks`), or each a
    chain of `MultiAgentNet` parts with a network per agent; else None (no acting pass, or shared and per-agent
    parts mixed)."""
    if acting is None:
        return None
    pair = plain_acting_network(acting.policy_net), plain_acting_network(acting.value_net)
    if None in pair or bool(pair[0].agent_parts) != bool(pair[1].agent_parts):
        return None
    return pair


def plain_acting_network(network: nn.Module) -> ActingNetwork | None:
    """A plain chain of `MultiAgentNet` parts (`plain_network`) as an `ActingNetwork`: every part shared by the agents,
    or every part one network per agent; else None."""
    parts = list(network) if isinstance(network, nn.Sequential) else [network]
    if not all(isinstance(part, MultiAgentNet) for part in parts):
        return None
    if all(part.share_params for part in parts):
        return ActingNetwork(nn.Sequential(*(part.shared_net() for part in parts)))
    if not any(part.share_params for part in parts):
        return ActingNetwork(nn.Sequential(*(getattr(part, TEMPLATE) for part in parts)), agent_parts=tuple(parts))
    return None


def without_zoo(policy: TensorDictModuleBase) -> tuple[TensorDictModuleBase, ZooPartners | None]:
    """A team's policy without the zoo cooks that act after its actor (`ZooPartners`, an algorithm's acting module),
    and those cooks (None where none act)."""
    modules = list(policy.module) if isinstance(policy, TensorDictSequential) else []
    zoo = [module for module in modules if isinstance(module, ZooPartners)]
    if not zoo:
        return policy, None
    return TensorDictSequential(*(module for module in modules if module is not zoo[0])), zoo[0]


def team_networks(policy) -> list[tuple[ActingNetwork, ActingNetwork]] | None:
    """Each team's (policy, value) networks, where every team of the `TeamPolicy` (or the learner a `GuidedPolicy`
    guides, one team) acts by an acting pass (`feed_forward_acting`) or by a recurrent model's policy with shared
    networks (`recurrent_acting`), zoo cooks after it or not; else None. Whether JAX runs their layers is
    `network_chain`'s to say."""
    if isinstance(policy, GuidedPolicy):
        teams = [policy.learner]
    elif isinstance(policy, TeamPolicy):
        teams = [without_zoo(team)[0] for team in policy.policies]
    else:
        return None
    if all(acting_pass_of(team) is not None for team in teams):
        pairs = [feed_forward_acting(acting_pass_of(team)) for team in teams]
    else:
        pairs = [recurrent_acting(team) for team in teams]
    return None if None in pairs else pairs


def zoo_seats(env: EnvBase, policy) -> tuple[ZooSeats, ZooPartners] | None:
    """The zoo's seats (the env's last transform) and cooks (after the actor) of a one-team policy, or None where
    no zoo cook plays; ValueError where they do not come in that pair."""
    cooks = [without_zoo(team)[1] for team in policy.policies] if isinstance(policy, TeamPolicy) else [None]
    transforms = _transforms(env)[1]
    seats = transforms[-1] if transforms and type(transforms[-1]) is ZooSeats else None
    if cooks == [None] * len(cooks) and seats is None:
        return None
    if len(cooks) != 1 or cooks[0] is None or seats is None:
        raise ValueError("zoo cooks play inside XLA beside one team, with the env's ZooSeats as its last transform")
    return seats, cooks[0]


def _transforms(env: EnvBase) -> tuple[EnvBase, list]:
    """An env's base and its transforms in order ([] for a bare env)."""
    if not isinstance(env, TransformedEnv):
        return env, []
    return env.base_env, list(env.transform) if isinstance(env.transform, Compose) else [env.transform]


def env_runs_in_xla(env: EnvBase, networks: Sequence[ActingNetwork], zoo: bool = False) -> bool:
    """Whether the rollout program can stand in for `env`'s steps with these networks acting: a bare `KitchenEnv`
    for feed-forward ones; for recurrent ones a `KitchenEnv` with exactly the model's transforms
    (`ActorCritic.env_transforms()`): InitTracker of "is_init", and a primer of these networks' LSTM states
    [*B, 2, 1, h], zeros at a reset. With `zoo`, a one-team `KitchenEnv` with the zoo's `ZooSeats` after those."""
    sizes = {key: layer.hidden_size for network in networks for layer in layers_of(network.layers)
             if isinstance(layer, nn.LSTM) for key in network.state_keys}
    base, transforms = _transforms(env)
    if not isinstance(base, KitchenEnv):
        return False
    if zoo:
        if base.teams != 1 or not transforms or type(transforms[-1]) is not ZooSeats:
            return False
        transforms = transforms[:-1]
    if not sizes:
        return not transforms
    trackers = [t for t in transforms if type(t) is InitTracker and list(t.init_keys) == [IS_INIT]]
    primers = [t for t in transforms if type(t) is TensorDictPrimer and not t.random]
    if len(transforms) != 2 or len(trackers) != 1 or len(primers) != 1:
        return False
    primer = primers[0]
    specs = {key: primer.primers[key] for key in primer.primers.keys(True, True)}
    defaults = primer.default_value if isinstance(primer.default_value, dict) else \
        dict.fromkeys(specs, primer.default_value)
    return set(specs) == set(sizes) and all(
        tuple(spec.shape[-3:]) == (N_AGENTS, 1, sizes[key]) and spec.dtype == torch.float32
        and isinstance(defaults.get(key), int | float) and defaults[key] == 0 for key, spec in specs.items())


def xla_chains(env: EnvBase, policy) -> tuple[Chain, Chain] | None:
    """The (policy, value) chains the teams of `policy` act with, where `XlaCollector` can run them over `env`: a
    `TeamPolicy` whose every team acts with networks JAX runs (`team_networks`), one chain for all, over the env
    they need (`env_runs_in_xla`, with the zoo's seats where zoo cooks play); else None."""
    networks = team_networks(policy)
    try:
        zoo = zoo_seats(env, policy) is not None
    except ValueError:
        return None
    if networks is None or not env_runs_in_xla(env, networks[0], zoo):
        return None
    chains = {tuple((network_chain(network), network.state_keys) for network in pair) for pair in networks}
    if len(chains) != 1 or any(chain is None for chain, _ in next(iter(chains))):
        return None
    return tuple(chain for chain, _ in next(iter(chains)))


_PROGRAMS = ProgramCache(kept=8)


def kitchen_floors(observation: jax.Array) -> jax.Array:
    """Each kitchen's floor tables [B, H * W, H * W] (`jax_env.cook.floor_tables`), read off seat 0's view of
    observations [B, 2, H, W, C]: walls and counters never move within an episode, nor on a level."""
    return floor_tables(walkable_floor(observation[:, 0]))


def rollout_program(env: KitchenEnv, chains: tuple[Chain, Chain], steps: int, zoo_share: float | None = None,
                    guided: bool = False) -> Callable:
    """The jitted rollout of `steps` steps of every kitchen of `env` with the teams acting by `chains` (built once
    per kitchen settings, shape and chains, and shared, as the env's own programs are):
    (weights, (start states, states, deliveries, env key), act keys [teams, 2], carrier) -> ((states, deliveries,
    env key, carrier), records [B, steps, ...]), where carrier = ((observation, scalars, done), (is_init, policy
    state, value state)), the policy's next input as the env's programs and transforms give it (a state (h, c)
    [B, 2, 1, h] each, () without an LSTM), and records = (carrier, (logits, action, log-prob, value), (next policy
    state, next value state), (next observation, next scalars, next done), zoo seating).

    zoo_share: zoo cooks play in that share of the kitchens (None: none). The program then takes zoo = (conventions
    [C, ...], draws [B], key) (() without a zoo), carries the draws, returns them last in its first output and
    records each step's seating [B, steps, 2] (`ZOO_COOK`).

    guided: a teacher guides the one team (`GuidedPolicy`): the program then takes guide = (the teacher's convention,
    its share float32, key) (() unguided) and records each step's teacher probabilities [B, steps, 2, 6] last."""
    key = (env.jax_env.settings, env.num_envs, env.teams, env.pinned_levels is not None, chains, steps,
           env.jax_device.platform, zoo_share, guided)
    return _PROGRAMS.get(key, lambda: _build_rollout(env, _team_act(env, chains), steps, zoo_share, guided))


def seated_program(env: KitchenEnv, teams: tuple[Chain | str, ...], slots: tuple[int, ...], steps: int) -> Callable:
    """`rollout_program` for kitchens whose seats different teams play (`SeatedCollector`): each team's policy chain,
    or `COOK` for a scripted cook, and the number of seats each plays (`slots`, static); the program's weights are
    (each network's weights, the cooks' conventions [C, ...], the kitchens' floor tables, each team's seats)
    (`_seated_act`). No value network runs (the values are zeros), and no zoo."""
    key = (env.jax_env.settings, env.num_envs, env.teams, env.pinned_levels is not None, ("seated", teams, slots),
           steps, env.jax_device.platform, None, False)
    return _PROGRAMS.get(key, lambda: _build_rollout(env, _seated_act(env, teams), steps, None))


class Acting(NamedTuple):
    """A rollout's acting pass: `act` (weights, keys, observation, states) -> (outputs, next states), once per step,
    on the weights as `prepare` makes them from the program's, once per batch."""

    prepare: Callable
    act: Callable


def _chains_here(env: KitchenEnv, chains: Sequence[Chain]) -> list[Chain]:
    """The chains as the env's device runs them best: on a CPU, first layers from cell tables (`tabled`); on a GPU,
    whose dense products are cheap, as they are."""
    if env.jax_device.platform != "cpu":
        return list(chains)
    return [tabled(chain, env.jax_env.obs_shape) for chain in chains]


def _team_act(env: KitchenEnv, chains: tuple[Chain, Chain]) -> Acting:
    """The acting pass of the rollout's teams, each in its own kitchens: (weights, keys [teams, 2], observation,
    (policy state, value state)) -> ((logits, action, log-prob, value), next states)."""
    policy_chain, value_chain = _chains_here(env, chains)
    teams, team_size = env.teams, env.team_size

    def prepare(weights):
        return jax.vmap(lambda policy, value: (table_weights(policy_chain, policy),
                                               table_weights(value_chain, value)))(*weights)

    def act(weights, keys, observation, states):
        def team(policy_weights, value_weights, key, observation, policy_state, value_state):
            logits, policy_state = run_chain(policy_chain, policy_weights, observation, policy_state)
            action = jax.random.categorical(key, logits)
            log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
            value, value_state = run_chain(value_chain, value_weights, observation, value_state)
            return (logits, action, log_prob, value), (policy_state, value_state)

        by_team = jax.tree.map(lambda value: value.reshape(teams, team_size, *value.shape[1:]), (observation, *states))
        outputs = jax.vmap(team)(*weights, keys, *by_team)
        return jax.tree.map(lambda value: value.reshape(teams * team_size, *value.shape[2:]), outputs)

    return Acting(prepare, act)


COOK = "cook"  # a seated team that is the scripted cook of a convention (`jax_env.cook`), not a network


def _seated_act(env: KitchenEnv, teams: tuple[Chain | str, ...]) -> Acting:
    """The acting pass of kitchens whose seats different teams play: weights = (each network team's weights, in
    order, the cooks' conventions [C, ...] and floors (None without a cook), and each team's seats: (kitchens int32
    [R], seats int32 [R]) per network team, then the cooks' (kitchens, seats, which convention) together; a kitchen
    index of B pads a list). floors: (the floor tables of the kitchens' levels [P, ...], each kitchen's level int32
    [B]).

    A network shared by the agents runs on the views of the seats its team plays, one with a network per agent on
    both views of their kitchens (its seat's logits kept, as `SeatedPolicy` keeps them); the cooks plan in their seats
    in one call. One draw per seat from keys[0]. -> ((logits, action, log-prob, zero values), no states)."""
    networks = _chains_here(env, [chain for chain in teams if chain != COOK])
    on_gpu = env.jax_device.platform != "cpu"

    def prepare(weights):
        network_weights, *rest = weights
        return ([table_weights(chain, own) for chain, own in zip(networks, network_weights)], *rest)

    def act(weights, keys, observation, states):
        network_weights, conventions, floors, slots = weights
        count = observation.shape[0]
        logits = jnp.zeros((count, N_AGENTS, NUM_ACTIONS), jnp.float32)
        for chain, own, (kitchens, seats) in zip(networks, network_weights, slots):
            safe = jnp.minimum(kitchens, count - 1)
            if chain[0][0] == "per_agent":  # each seat its own network: both run, the team's seat kept
                out, _ = run_chain(chain, own, observation[safe])
                picked = jnp.take_along_axis(out, seats[:, None, None], axis=1)[:, 0]
            else:  # one network for both seats: on the seated agent's view alone
                picked, _ = run_chain(chain, own, observation[safe, seats])
            logits = logits.at[kitchens, seats].set(picked, mode="drop")
        if conventions is not None:
            kitchens, seats, which = slots[-1]
            safe = jnp.minimum(kitchens, count - 1)
            rows = jax.tree.map(lambda leaf: leaf[which], conventions)
            tables, plan = floors
            planned = cook_logits(observation[safe, seats], rows, tables, plan[safe],
                                  detour_rows=None if on_gpu else max(1, len(kitchens) // 4), seats=seats)
            logits = logits.at[kitchens, seats].set(planned, mode="drop")
        action = jax.random.categorical(keys[0], logits)
        log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
        return (logits, action, log_prob, jnp.zeros((count, N_AGENTS, 1), jnp.float32)), ((), ())

    return Acting(prepare, act)


def _with_zoo_cooks(conventions, zoo, observation, acted, zoo_share: float, on_gpu: bool):
    """The actions with the zoo cooks' in their seats, the seating they played by, and the zoo's next key."""
    draws, key, tables = zoo
    key, used = jax.random.split(key)
    logits, action, log_prob, value = acted
    # On a CPU the cooks plan for twice their expected number of kitchens while no more have one.
    at_most = None if on_gpu else max(1, math.ceil(2 * zoo_share * len(draws)))
    action = cook_actions(used, observation, action, draws, conventions, at_most, tables)
    return (logits, action, log_prob, value), seating(draws), key


def _next_zoo(conventions, zoo, ended, observation, zoo_share: float):
    """The zoo after a step: where an episode ended, its seats drawn anew (as ZooSeats does at a reset) and its
    new floor's tables."""
    draws, key, tables = zoo

    def started(key):
        key, drawn = jax.random.split(key)
        fresh = draw_seats(drawn, len(ended), conventions.scores.shape[0], zoo_share)
        return jnp.where(ended, fresh, draws), key, _new_floors(tables, ended, observation)

    return jax.lax.cond(ended.any(), started, lambda key: (draws, key, tables), key)


def _new_floors(tables, ended, observation):
    """The kitchens' floor tables with those of the episodes that `ended` made from their next `observation`
    (walls and counters never move within an episode)."""
    return jnp.where(ended[:, None, None], kitchen_floors(observation), tables)


def _with_teacher(guide, tables, observation, acted, on_gpu: bool):
    """The actions with each seat's taken from the teacher with the guide's share, and the teacher's action
    probabilities [B, 2, 6] in every seat: guide = (convention, share, key), tables the kitchens' floor tables."""
    convention, share, key = guide
    drawn, taken = jax.random.split(key)
    logits, action, log_prob, value = acted
    views = observation.reshape(-1, *observation.shape[2:])
    plan = jnp.repeat(jnp.arange(observation.shape[0]), N_AGENTS)  # both seats of a kitchen read its table
    taught = cook_logits(views, convention, tables, plan, detour_rows=None if on_gpu else max(1, len(views) // 4))
    taught = taught.reshape(*action.shape, NUM_ACTIONS)
    takes = jax.random.uniform(taken, action.shape) < share
    action = jnp.where(takes, jax.random.categorical(drawn, taught).astype(action.dtype), action)
    return (logits, action, log_prob, value), jax.nn.softmax(taught)


def _build_rollout(env: KitchenEnv, acting: Acting, steps: int, zoo_share: float | None, guided: bool = False
                   ) -> Callable:
    programs = kitchen_programs(env.jax_env, env.num_envs, env.teams, env.pinned_levels is not None, packed=False)
    on_gpu = env.jax_device.platform != "cpu"

    def step(start_states, weights, conventions, teacher, carry, _):
        states, deliveries, env_key, act_keys, carrier, zoo, guide = carry
        observed, (is_init, *network_states) = carrier
        act_keys, used = jax.vmap(jax.random.split, out_axes=1)(act_keys)
        acted, next_network_states = acting.act(weights, used, observed[0], restarted(is_init, network_states))
        seated = labels = ()
        if zoo_share is not None:
            acted, seated, zoo_key = _with_zoo_cooks(conventions, zoo, observed[0], acted, zoo_share, on_gpu)
            zoo = (zoo[0], zoo_key, zoo[2])
        if guided:
            guide_key, used_key = jax.random.split(guide[0])
            acted, labels = _with_teacher((*teacher, used_key), guide[1], observed[0], acted, on_gpu)
        states, deliveries, stepped = programs.step(states, deliveries, acted[1].astype(jnp.int32))
        ended = stepped[2][:, 0]

        def reset(_):  # as `KitchenEnv._reset` after TorchRL's partial reset, merged by TorchRL's rule
            kept, used_key = programs.split_keys(env_key)
            fresh_states, fresh_deliveries, fresh = jax.lax.cond(
                ended.all(),
                lambda: programs.reset_all(start_states, used_key),
                lambda: programs.reset_masked(start_states, used_key, states, deliveries, ended))
            merged = [jnp.where(ended.reshape(-1, *[1] * (a.ndim - 1)), a, b) for a, b in zip(fresh, stepped)]
            return fresh_states, fresh_deliveries, kept, tuple(merged)

        next_states, next_deliveries, env_key, next_observed = jax.lax.cond(
            ended.any(), reset, lambda _: (states, deliveries, env_key, tuple(stepped)), None)
        if zoo_share is not None:
            zoo = _next_zoo(conventions, zoo, ended, next_observed[0], zoo_share)
        if guided:
            guide = (guide_key, jax.lax.cond(ended.any(), _new_floors, lambda tables, *_: tables, guide[1], ended,
                                             next_observed[0]))
        # The transforms' next input: episodes that ended start again (InitTracker), their states zero (the primer).
        next_memory = (stepped[2], *restarted(stepped[2], next_network_states))
        record = (carrier, acted, next_network_states, tuple(stepped), seated, labels)
        return (next_states, next_deliveries, env_key, act_keys, (next_observed, next_memory), zoo, guide), record

    @jax.jit
    def rollout(weights, kitchens, act_keys, carrier, zoo=(), guide=()):
        start_states, states, deliveries, env_key = kitchens
        conventions, *zoo = zoo or (None,)
        if zoo:  # the floor tables of the kitchens' episodes, made again at each batch's start
            zoo = (*zoo, kitchen_floors(carrier[0][0]))
        teacher, guide = (guide[:2], (guide[2], kitchen_floors(carrier[0][0]))) if guide else ((), ())
        carry = (states, deliveries, env_key, act_keys, carrier, tuple(zoo), guide)
        weights = acting.prepare(weights)
        carry, records = jax.lax.scan(lambda c, x: step(start_states, weights, conventions, teacher, c, x), carry,
                                      None, length=steps)
        states, deliveries, env_key, _, carrier, zoo, _ = carry
        return (states, deliveries, env_key, carrier, *zoo[:1]), jax.tree.map(
            lambda record: jnp.swapaxes(record, 0, 1), records)

    return rollout


class XlaCollector(InPlaceCollector):
    """A TorchRL collector whose batches are rolled out inside one XLA program (see the module docstring):
    `KitchenCollector`'s batches, keys and storage (an `InPlaceCollector`), with the actions drawn by JAX.

    env: a bare `KitchenEnv` for feed-forward teams; for recurrent ones the `KitchenEnv` with the model's transforms
    (`with_transforms(kitchen, actor_critic.env_transforms())`), whose base env the program steps. ValueError where
    `xla_chains(env, policy)` is None (`trainers.ppo.collection.make_collector` checks, and collects those with
    `KitchenCollector`)."""

    def __init__(self, env: EnvBase, policy: TeamPolicy, frames_per_batch: int, total_frames: int = -1):
        super().__init__(env, frames_per_batch, total_frames)
        chains = xla_chains(env, policy)
        if chains is None:
            raise ValueError("XlaCollector runs teams of feed-forward acting passes (MLP, agent-centred MLP, GNN; "
                             "shared or per agent) on a bare KitchenEnv, or of their recurrent networks (mlp_lstm, "
                             "gnn_lstm) on a KitchenEnv with the model's transforms alone (with_model_transforms); "
                             "collect this policy and env with KitchenCollector")
        self.policy = policy
        self.kitchen_env = env.base_env if isinstance(env, TransformedEnv) else env
        zoo = zoo_seats(env, policy)
        self._seats = None if zoo is None else zoo[0]
        self._conventions = None if zoo is None else jax.tree.map(
            lambda leaf: jax.device_put(leaf, self.kitchen_env.jax_device), zoo[1].conventions)
        self._guide = policy if isinstance(policy, GuidedPolicy) else None
        self._program = rollout_program(self.kitchen_env, chains, self.steps,
                                        None if zoo is None else zoo[0].share, guided=self._guide is not None)
        networks = team_networks(policy)
        self._networks = [list(pair) for pair in networks]
        self._state_keys = [network.state_keys for network in networks[0]]
        self._recurrent = any(self._state_keys)
        with torch.no_grad():
            first = env.reset()
        self._carrier = self._carrier_of(first)

    def _to_jax(self, tensor: torch.Tensor) -> jax.Array:
        """A copy in XLA's own memory: on a GPU, the program's command buffers (XLA's CUDA graphs) fail to update
        their copies from torch's memory at the next call (CUDA_ERROR_INVALID_VALUE, jax 0.11.2 on an H200), and the
        program runs 1.55x faster with them than compiled without them (BENCHMARKS.md, "A fourth lending")."""
        shared = jax.device_put(jax.dlpack.from_dlpack(tensor.detach().contiguous()), self.kitchen_env.jax_device)
        return jnp.array(shared, copy=True)

    def _carrier_of(self, tensordict: TensorDictBase) -> tuple:
        """The env's reset output as the program carries it: ((observation, scalars [B, 6], done), (is_init, policy
        state, value state)), the scalars' reward columns zero (a reset earns nothing), every episode starting."""
        shaped = tensordict.get(SHAPED_REWARD).squeeze(-1)
        scalars = torch.cat([torch.zeros_like(shaped), shaped, tensordict.get("deliveries"),
                             tensordict.get("episode_deliveries")], dim=-1)
        done = tensordict.get("done")
        observed = tuple(self._to_jax(value) for value in (tensordict.get(OBSERVATION), scalars, done))
        is_init = tensordict.get(IS_INIT, None)
        is_init = torch.ones_like(done) if is_init is None else is_init  # a bare env's: unread, but carried
        states = [tuple(self._to_jax(tensordict.get(key)) for key in keys) for keys in self._state_keys]
        return observed, (self._to_jax(is_init), *states)

    def _weights(self) -> tuple[list[jax.Array], list[jax.Array]]:
        """The teams' current weights, stacked along a leading team dim."""
        with torch.no_grad():
            return tuple([self._to_jax(torch.stack(tensors)) for tensors in zip(*map(network_weights, nets))]
                         for nets in zip(*self._networks))

    def _act_keys(self) -> jax.Array:
        """uint32 [teams, 2]: each team's key for this batch's draws, from its torch stream (a guided learner's: torch's
        current one)."""
        seeds = []
        for stream in getattr(self.policy, "streams", [None]):
            with stream.active() if stream is not None else contextlib.nullcontext():
                seeds.append(torch.randint(0, 2**31 - 1, (2,), dtype=torch.int64))
        return self._to_jax(torch.stack(seeds).to(torch.int32)).view(jnp.uint32)

    def _guidance(self) -> tuple:
        """The program's guide input: (the teacher's convention, its share, this batch's key from torch's current
        stream), () unguided. Read at every batch: a distillation changes both between rounds."""
        if self._guide is None:
            return ()
        seed = torch.randint(0, 2**31 - 1, (2,), dtype=torch.int64)
        convention = jax.tree.map(lambda leaf: jax.device_put(leaf, self.kitchen_env.jax_device),
                                  self._guide.teacher.arrays)
        return (convention, jnp.float32(self._guide.teacher_share),
                self._to_jax(seed.to(torch.int32)).view(jnp.uint32))

    def _zoo(self) -> tuple:
        """The program's zoo input: (conventions, the seats' current draws, this batch's key from their generator),
        () without zoo cooks."""
        if self._seats is None:
            return ()
        seed = torch.randint(0, 2**31 - 1, (2,), dtype=torch.int64, generator=self._seats.generator)
        return (self._conventions, self._to_jax(self._seats.draws.to(torch.int32)),
                self._to_jax(seed.to(torch.int32)).view(jnp.uint32))

    def _state_entries(self, is_init: torch.Tensor, states: list, next_states: list) -> dict:
        """A recurrent batch's entries of the model's transforms: "is_init" (and ("next", "is_init"), which
        InitTracker leaves False), the state each step read, and the state it left under "next"."""
        entries = {IS_INIT: is_init, (NEXT, IS_INIT): torch.zeros_like(is_init)}
        for keys, state, next_state in zip(self._state_keys, states, next_states):
            entries.update(zip(keys, state))
            entries.update({(NEXT, *as_path(key)): value for key, value in zip(keys, next_state)})
        return entries

    def rollout(self) -> TensorDictBase:
        """The next batch: `steps` steps of every kitchen, written into the storage; the env left where they end."""
        env = self.kitchen_env
        (states, deliveries, key, self._carrier, *draws), records = self._program(
            self._weights(), env.kitchens(), self._act_keys(), self._carrier, self._zoo(), self._guidance())
        env.continue_from(states, deliveries, key, self._carrier[0][0])
        if draws:  # the seats where the batch left them: the next batch's, and the checkpoint's
            self._seats.draws = torch.from_dlpack(draws[0]).long().cpu()
        (observed, (is_init, *states)), acted, next_states, stepped, seated, labels = jax.tree.map(torch.from_dlpack,
                                                                                                   records)
        values = {**output_entries(*observed, with_reward=False), **dict(zip(ACTING_KEYS, acted)),
                  **{(NEXT, *as_path(key)): tensor for key, tensor in output_entries(*stepped, True).items()}}
        if self._recurrent:
            values.update(self._state_entries(is_init, states, next_states))
        if self._seats is not None:  # a seating lasts its episode: the same after the step
            values.update({ZOO_COOK: seated, (NEXT, *ZOO_COOK): seated})
        if self._guide is not None:
            values[TEACHER_PROBS] = labels
        if self._storage is None:
            self._storage = as_tensordict({key: value.clone() for key, value in values.items()},
                                          torch.Size([env.num_envs, self.steps]), env.device)
            for key in (ACTION, *((ZOO_COOK, (NEXT, *ZOO_COOK)) if self._seats is not None else ())):
                self._storage[key] = self._storage[key].long()
            self._storage.refine_names(..., "time")
            self._keys = list(self._storage.keys(True, True))
        else:
            torch._foreach_copy_([self._storage.get(key) for key in self._keys], [values[key] for key in self._keys])
        return self._storage


def seated_teams(env: EnvBase, policy) -> tuple[SeatedPolicy, list[ActingNetwork | ScriptedCook]] | None:
    """A seated actor's (`make_seated_actor`) `SeatedPolicy` and each of its teams as `SeatedCollector` plays it: a
    feed-forward actor's policy network, where JAX runs its layers, or a scripted cook; None where a team acts
    otherwise (recurrent, E3T's predictor) or the env is not a bare `KitchenEnv` whose kitchens are pinned to levels, as
    evaluation's are (a cook's floor tables then hold for the whole play; `seat` not yet called: None too)."""
    if not (isinstance(env, KitchenEnv) and env.pinned_levels is not None and isinstance(policy, ProbabilisticActor)
            and isinstance(policy.module[0], SeatedPolicy) and policy.module[0].seating is not None
            and getattr(policy.module[1], "distribution_class", None) is ActionDistribution):
        return None
    seated, teams = policy.module[0], []
    for actor in seated.actors:
        network = actor.module[0] if isinstance(actor, ProbabilisticActor) else None
        if isinstance(network, TensorDictModule) and isinstance(network.module, ScriptedCook):
            teams.append(network.module)
            continue
        if not (isinstance(network, TensorDictSequential) and list(network.in_keys) == [OBSERVATION]
                and LOGITS in network.out_keys):
            return None
        acting = plain_acting_network(plain_network(network))
        if acting is None or network_chain(acting) is None:
            return None
        teams.append(acting)
    return seated, teams


_KITCHEN_FLOORS = jax.jit(kitchen_floors)


def _padded(columns: Sequence[torch.Tensor], pad: Sequence[int], device) -> tuple[jax.Array, ...]:
    """Index columns int [R] padded to a power of two with `pad` (one compilation serves any count up to it)."""
    count = len(columns[0])
    size = 1 << max(0, count - 1).bit_length()
    return tuple(jax.device_put(torch.cat([column, column.new_full((size - count,), fill)]).int().numpy(), device)
                 for column, fill in zip(columns, pad))


class SeatedCollector(XlaCollector):
    """`XlaCollector` for kitchens whose seats different teams play (evaluation's `make_seated_actor`, seated by
    `SeatedPolicy.seat` for the collector's life): feed-forward teams' policy networks and scripted cooks act inside
    one program (`seated_program`), on a bare `KitchenEnv` pinned to levels; the batch holds zero values (no critic
    plays). The teams' weights and the levels' floor tables are taken once, at the start: an evaluation's teams do not
    learn while they play. Actions are drawn from a key of torch's current random stream at each batch. ValueError
    where `seated_teams` is None (`trainers.ppo.collection.make_collector` checks)."""

    def __init__(self, env: EnvBase, policy: ProbabilisticActor, frames_per_batch: int, total_frames: int = -1):
        InPlaceCollector.__init__(self, env, frames_per_batch, total_frames)
        found = seated_teams(env, policy)
        if found is None:
            raise ValueError("SeatedCollector plays seated feed-forward teams (MLP, agent-centred MLP, GNN) and "
                             "scripted cooks on a bare KitchenEnv; play the others with KitchenCollector")
        seated, teams = found
        self.policy, self.kitchen_env = policy, env
        self._seats, self._guide, self._recurrent, self._state_keys = None, None, False, [(), ()]
        device, seating = env.jax_device, seated.seating.cpu()
        network_teams = [team for team in teams if isinstance(team, ActingNetwork)]
        slots = [_padded((seating == index).nonzero(as_tuple=True), (env.num_envs, 0), device)
                 for index, team in enumerate(teams) if isinstance(team, ActingNetwork)]
        cooks = [index for index, team in enumerate(teams) if not isinstance(team, ActingNetwork)]
        conventions = floors = None
        with torch.no_grad():
            first = env.reset()
        self._carrier = self._carrier_of(first)
        if cooks:
            kitchens, seats = torch.isin(seating, torch.tensor(cooks)).nonzero(as_tuple=True)
            which = torch.searchsorted(torch.tensor(cooks), seating[kitchens, seats])
            slots.append(_padded((kitchens, seats, which), (env.num_envs, 0, 0), device))
            conventions = jax.tree.map(lambda leaf: jax.device_put(leaf, device),
                                       stacked_conventions([teams[index].convention for index in cooks]))
            # The kitchens of a level share its floor tables (a table per level reads faster than one per kitchen):
            # those of its first kitchen.
            levels = env.pinned_levels
            floors = (_KITCHEN_FLOORS(self._carrier[0][0][np.unique(levels, return_index=True)[1]]),
                      jax.device_put(levels.astype(np.int32), device))
        with torch.no_grad():
            networks = tuple([self._to_jax(weight) for weight in network_weights(team)] for team in network_teams)
        # The program's weights: each network team's, the cooks' conventions and floors, every team's seats.
        self._inputs = (networks, conventions, floors, tuple(slots))
        chains = tuple(network_chain(team) for team in network_teams) + ((COOK,) if cooks else ())
        self._program = seated_program(env, chains, tuple(len(slot[0]) for slot in slots), self.steps)

    def _weights(self) -> tuple:
        return self._inputs

    def _act_keys(self) -> jax.Array:
        """uint32 [1, 2]: this batch's key for the draws, from torch's current random stream."""
        seed = torch.randint(0, 2**31 - 1, (1, 2), dtype=torch.int64)
        return self._to_jax(seed.to(torch.int32)).view(jnp.uint32)
