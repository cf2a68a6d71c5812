"""Policy and value networks for the kitchens: MLP or GNN encoders, optionally an LSTM, per agent or shared.

`make_actor_critic(architecture, ...)` builds an `ActorCritic` whose actor and critic are TensorDict modules
with separate torsos (no layer is shared between actor and critic). Each torso, with h = `hidden`:

    encoder   "mlp": flatten H*W*26 -> Linear(h) + ReLU (`ObservationLinear`: reads uint8)
              "ego_mlp": the same over a (2H-1) x (2W-1) window centred on the observing agent
                     (`torch_kitchen.egocentric`): not in the paper
              "gnn": kitchen graph (`torch_kitchen.graph`) -> GATConv(26, 8, heads=4, concat) -> ReLU
                     -> flatten the H*W+2 node embeddings -> Linear(h) + ReLU (the scene embedding)
    memory    recurrent variants only: TorchRL LSTMModule(h) -> LayerNorm(h)
    head      Linear(h) + ReLU -> Linear(h) + ReLU -> Linear(6 logits | 1 value)

The layers are torch's own; on a CPU, `torch_kitchen.cpu_kernels.accelerate_cpu` swaps in faster kernels for the
same products (oneDNN, and the sparse first layers), as the trainer and the evaluation do.

E3T's models ("e3t_mlp", "e3t_gnn") put a partner predictor (`PartnerPredictor`) before the actor's torso; its
predicted distribution of the partner's action, detached, is concatenated to the torso's output before the head.

Orthogonal init as in the authors' code: gain sqrt(2) for hidden Linear layers, 0.01 for the policy head, 1.0
for the value head, zero biases (the GAT layer and the LSTM keep their own default init).
With `share_params` one network serves both agents; otherwise agent i has its own (TorchRL's
`MultiAgentNetBase`, which stacks the agents' parameters and vmaps over them).

Keys (*B = the tensordict's batch dims: [B] while collecting, [B, T] in training batches; h = hidden):

    in   ("agents", "observation")        uint8   [*B, 2, H, W, 26]  (read as float32 inside)
         "is_init"                        bool    [*B, 1]           recurrent only (`InitTracker`)
         ("agents", "<net>_h" | "<net>_c") float32 [*B, 2, 1, h]     recurrent only, <net> = actor | critic
    out  ("agents", "logits")             float32 [*B, 2, 6]
         ("agents", "action")             int64   [*B, 2]           sampled (interaction type RANDOM)
         ("agents", "action_log_prob")    float32 [*B, 2]
         ("agents", "state_value")        float32 [*B, 2, 1]
         ("next", "agents", "<net>_h" | "<net>_c")                  recurrent, step mode only: the state after
                                                                    this step (where a Collector carries it)
    E3T  in  ("agents", "context_observation" | "context_action")  the partner context
                                                                    (`torch_kitchen.partner.PartnerContext`)
         out ("agents", "partner_logits" | "partner_prediction") float32 [*B, 2, 6]

Collection: feed-forward models also carry an `ActingPass` (`ActorCritic.acting`), actor and critic in one pass
over plain tensors that writes what the actor then the critic write, bit for bit; `acting_policy()` uses it
where there is one.

Recurrent models run one step at a time by default (collection); wrap training calls on [B, T] batches in
`torchrl.modules.set_recurrent_mode(True)` for backpropagation through time, T the last batch dim. Either way
the LSTM state is zeroed where "is_init" is True, also in the middle of a sequence.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    InteractionType,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from tensordict.nn.probabilistic import interaction_type
from torch import nn
from torch_geometric.nn import GATConv
from torchrl.data import Composite, Unbounded
from torchrl.envs import InitTracker, TensorDictPrimer, Transform
from torchrl.modules import LSTMModule, ProbabilisticActor

from jax_env import NUM_ACTIONS
from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.graph import build_graph, num_nodes
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, OBSERVATION, PARTNER_LOGITS, PARTNER_PREDICTION, VALUE
from torch_kitchen.partner import CONTEXT_ACTION, CONTEXT_OBSERVATION, NO_ACTION, PartnerContext
from torch_kitchen.sparse_linear import ObservationLinear
from torch_kitchen.torchrl_internals import MultiAgentNet

N_AGENTS = 2
GAT_HEADS, GAT_FEATURES = 4, 8  # per head; concatenated -> 32 features per node

ARCHITECTURES = ("mlp", "mlp_lstm", "gnn", "gnn_lstm", "ego_mlp")
E3T_ARCHITECTURES = ("e3t_mlp", "e3t_gnn")  # with a partner predictor: trained with algorithm "e3t"


# ------------------------------------------------------------------------------------------- single networks
def _orthogonal_(layer: nn.Linear, gain: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def _hidden_linear(in_features: int, out_features: int, layer: type[nn.Linear] = nn.Linear) -> nn.Linear:
    return _orthogonal_(layer(in_features, out_features), math.sqrt(2))


class GraphEncoder(nn.Module):
    """Kitchen graph -> one GAT layer -> scene embedding: [..., H, W, C] (uint8 or float) -> float [..., hidden]."""

    def __init__(self, obs_shape: tuple[int, int, int], hidden: int):
        super().__init__()
        height, width, channels = obs_shape
        self.obs_shape = tuple(obs_shape)
        # Self-loops are part of the graph's edge list (torch_kitchen.graph): don't let GATConv rebuild them.
        self.gat = GATConv(channels, GAT_FEATURES, heads=GAT_HEADS, add_self_loops=False)
        self.scene = _hidden_linear(num_nodes(height, width) * GAT_HEADS * GAT_FEATURES, hidden)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        batch = obs.shape[:-3]
        graphs = obs.reshape(-1, *self.obs_shape).to(torch.float32)
        x, edge_index = build_graph(graphs)
        nodes = torch.relu(self.gat(x, edge_index))  # [N * (H*W + 2), 32]
        scene = torch.relu(self.scene(nodes.reshape(graphs.shape[0], -1)))
        return scene.reshape(*batch, -1)


def make_encoder(kind: str, obs_shape: tuple[int, int, int], hidden: int) -> nn.Module:
    """One agent's encoder: [..., H, W, C] (uint8 observations or float) -> float [..., hidden]; kind "mlp",
    "ego_mlp" (agent-centred) or "gnn". The MLPs' first layer reads uint8 observations (`ObservationLinear`,
    `EgocentricLinear`); on a CPU, `accelerate_cpu` makes it read their non-zero entries alone."""
    if kind == "mlp":
        return nn.Sequential(nn.Flatten(-3), _hidden_linear(math.prod(obs_shape), hidden, ObservationLinear), nn.ReLU())
    if kind == "ego_mlp":
        return nn.Sequential(_orthogonal_(EgocentricLinear(obs_shape, hidden), math.sqrt(2)), nn.ReLU())
    if kind == "gnn":
        return GraphEncoder(obs_shape, hidden)
    raise ValueError(f"unknown encoder {kind!r}, expected 'mlp', 'ego_mlp' or 'gnn'")


def make_head(hidden: int, out_features: int, out_gain: float, layer_norm: bool, in_features: int | None = None
              ) -> nn.Sequential:
    """One agent's head: float [..., in_features] -> float [..., out_features], after a LayerNorm if `layer_norm`.

    in_features: `hidden` by default; wider when other inputs (E3T's partner prediction) join the torso's output.
    """
    in_features = in_features or hidden
    layers = [nn.LayerNorm(in_features)] if layer_norm else []
    layers += [_hidden_linear(in_features, hidden), nn.ReLU(), _hidden_linear(hidden, hidden), nn.ReLU()]
    layers.append(_orthogonal_(nn.Linear(hidden, out_features), out_gain))
    return nn.Sequential(*layers)


# -------------------------------------------------------------------------------------- one net per agent
class ObservationEncoder(MultiAgentNet):
    """Both agents' observations, uint8 [..., 2, H, W, C], to embeddings float32 [..., 2, hidden]. The encoders
    read the uint8 values themselves (the MLP's sparse first layer finds the non-zero bytes without a cast)."""

    def __init__(self, kind: str, obs_shape: tuple[int, int, int], hidden: int, share_params: bool = True):
        super().__init__(functools.partial(make_encoder, kind, obs_shape, hidden), obs_shape,
                         share_params=share_params)

    def check_input(self, inputs: torch.Tensor) -> torch.Tensor:
        height, width, channels = self.in_shape
        if tuple(inputs.shape[-4:]) != (self.n_agents, *self.in_shape):
            raise ValueError(
                f"observation of shape {list(inputs.shape)}, but this model was built for [..., {self.n_agents}, "
                f"{height}, {width}, {channels}] (obs_shape={self.in_shape}): a model built for {height}x{width} "
                f"kitchens needs {height}x{width} levels (7x7: the Infinite Kitchen and the expanded classic "
                f"layouts), or build it with make_actor_critic(..., obs_shape={tuple(inputs.shape[-3:])})"
            )
        return inputs


# ------------------------------------------------------------------------------------------- recurrence
def agent_state_primer(states: dict[str, int], n_agents: int = N_AGENTS) -> TensorDictPrimer:
    """Primer of the LSTM states ("agents", name) float32 [*B, n_agents, 1, size], zeros at every reset.

    states: name -> size. The specs sit in an "agents" Composite of shape [n_agents] so that, expanded to the
    env's batch size, they share the env's ("agents",) batch dims [*B, n_agents].
    """
    agents = Composite({name: Unbounded(shape=(n_agents, 1, size)) for name, size in states.items()},
                       shape=(n_agents,))
    return TensorDictPrimer(Composite(agents=agents), expand_specs=True)


class AgentLSTMModule(LSTMModule):
    """TorchRL's LSTMModule with states ("agents", name) [*B, n_agents, 1, hidden] in its primer.

    Run through `MultiAgentLSTM`, which moves the agent dim into the batch. The primer is what an env must carry,
    so `torchrl.modules.utils.get_primers_from_module` (and the collector's check) see the right shapes.
    """

    def __init__(self, *args, n_agents: int = N_AGENTS, **kwargs):
        super().__init__(*args, **kwargs)
        if any(len(key) != 2 or key[0] != "agents" for key in self.in_keys[1:3]):
            raise ValueError(f"AgentLSTMModule keeps its states under 'agents', got {self.in_keys[1:3]}")
        self.n_agents = n_agents

    def state_sizes(self) -> dict[str, int]:
        """Name under "agents" -> size of the two states (h, c)."""
        return {key[1]: self.lstm.hidden_size for key in self.in_keys[1:3]}

    def make_tensordict_primer(self) -> TensorDictPrimer:
        return agent_state_primer(self.state_sizes(), self.n_agents)


def recurrent_states(network: nn.Module) -> dict[str, int]:
    """Name under "agents" -> width of every LSTM state a network reads (empty if feed-forward)."""
    states = {}
    for module in network.modules():
        if isinstance(module, AgentLSTMModule):
            states.update(module.state_sizes())
    return states


class MultiAgentLSTM(TensorDictModuleBase):
    """LSTM over both agents: ("agents", "<net>_embedding") [*B, 2, h] -> ("agents", "<net>_memory") [*B, 2, h].

    Reads the state ("agents", "<net>_h" | "<net>_c") [*B, 2, 1, h] (zeros if absent) and "is_init" [*B, 1]. In
    step mode it writes the next state to ("next", "agents", "<net>_h" | "<net>_c"); in recurrent mode it leaves
    the stored next states as they are. LSTMModule takes time as the last batch dim, so the agent dim goes just
    before it, [B, T, 2] -> [B, 2, T]: shared, one LSTM runs both agents at once; separate, agent i's LSTM runs
    on agent i's slice.
    """

    def __init__(self, net: str, hidden: int, share_params: bool = True, n_agents: int = N_AGENTS):
        super().__init__()
        self.n_agents, self.share_params = n_agents, share_params
        embedding, memory = ("agents", f"{net}_embedding"), ("agents", f"{net}_memory")
        state_h, state_c = ("agents", f"{net}_h"), ("agents", f"{net}_c")
        self.in_keys = [embedding, state_h, state_c, "is_init"]
        self.out_keys = [memory, ("next", *state_h), ("next", *state_c)]
        self.lstms = nn.ModuleList(
            AgentLSTMModule(input_size=hidden, hidden_size=hidden, n_agents=n_agents, in_keys=list(self.in_keys),
                            out_keys=list(self.out_keys))
            for _ in range(1 if share_params else n_agents)
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if "is_init" not in tensordict:
            raise KeyError("recurrent models need 'is_init' [*B, 1]: append ActorCritic.env_transforms() "
                           "(InitTracker and the state primer) to the env")
        groups = [(0, self.n_agents)] if self.share_params else [(i, 1) for i in range(self.n_agents)]
        outputs = [self._run(lstm, tensordict, *group) for lstm, group in zip(self.lstms, groups)]
        agent_dim = tensordict.ndim
        if self.lstms[0].recurrent_mode:
            # Over a sequence LSTMModule returns next states that are zero but at the last step: keep the collected
            # ("next", ...) states rather than overwrite them with that padding.
            memory, *_ = zip(*outputs)
            tensordict.set(self.out_keys[0], torch.cat(memory, dim=agent_dim))
            return tensordict
        if ("next", "agents") not in tensordict.keys(include_nested=True):
            # Created with the agent dim, like the env's own ("next", "agents").
            tensordict.set(("next", "agents"), tensordict.get("agents").empty())
        for key, *values in zip(self.out_keys, *outputs):
            tensordict.set(key, torch.cat(values, dim=agent_dim))
        return tensordict

    def _run(self, lstm: LSTMModule, tensordict: TensorDictBase, first: int, count: int) -> list[torch.Tensor]:
        """Agents first .. first+count-1 through `lstm`: the out_keys' values, with the agent dim."""
        batch, ndim = tensordict.batch_size, tensordict.ndim
        fold = max(ndim - 1, 0)  # where the agent dim goes: just before time

        def to_lstm(value: torch.Tensor) -> torch.Tensor:
            return value.narrow(ndim, first, count).movedim(ndim, fold)

        is_init = to_lstm(tensordict.get("is_init").unsqueeze(ndim).expand(*batch, self.n_agents, 1))
        agents = {self.in_keys[0][1]: to_lstm(tensordict.get(self.in_keys[0]))}
        for key in self.in_keys[1:3]:
            state = tensordict.get(key, None)
            if state is not None:
                # LSTMModule zeroes the state at "is_init" only in step mode; in recurrent mode it trusts the
                # stored state at a sequence's start. Zeroing here makes a boundary inside a sequence safe too.
                state = to_lstm(state)
                agents[key[1]] = torch.where(is_init.unsqueeze(-1), torch.zeros_like(state), state)
        lstm_batch = is_init.shape[:-1]
        scratch = TensorDict({"agents": TensorDict(agents, batch_size=lstm_batch), "is_init": is_init},
                             batch_size=lstm_batch)
        scratch = lstm(scratch)
        return [scratch.get(key).movedim(fold, ndim) for key in self.out_keys]


# --------------------------------------------------------------------------------------- actor and critic
def make_network(
    net: str,
    encoder: str,
    out_key: tuple[str, str],
    out_features: int,
    out_gain: float,
    obs_shape: tuple[int, int, int],
    hidden: int,
    recurrent: bool,
    share_params: bool,
    extra_inputs: Sequence[tuple[tuple[str, str], int]] = (),
) -> TensorDictSequential:
    """One torso + head as a TensorDictSequential: ("agents", "observation") -> `out_key` [*B, 2, out_features].

    extra_inputs: (key, width) of per-agent features [*B, 2, width] concatenated to the torso's output before
    the head (E3T's partner prediction). Intermediate keys ("agents", "<net>_embedding" | "<net>_memory") are
    dropped from the output, so rollouts don't store them.
    """
    embedding, memory = ("agents", f"{net}_embedding"), ("agents", f"{net}_memory")
    modules = [
        TensorDictModule(ObservationEncoder(encoder, obs_shape, hidden, share_params),
                         in_keys=[OBSERVATION], out_keys=[embedding])
    ]
    selected = [out_key]
    if recurrent:
        lstm = MultiAgentLSTM(net, hidden, share_params)
        modules.append(lstm)
        selected += lstm.out_keys[1:]
    in_features = hidden + sum(width for _, width in extra_inputs)
    head = MultiAgentNet(functools.partial(make_head, hidden, out_features, out_gain, recurrent, in_features),
                         (in_features,), share_params=share_params)
    head_inputs = [memory if recurrent else embedding, *(key for key, _ in extra_inputs)]
    modules.append(TensorDictModule(head, in_keys=head_inputs, out_keys=[out_key]))
    return TensorDictSequential(*modules, selected_out_keys=selected)


def sampling_actor(policy: TensorDictModuleBase) -> ProbabilisticActor:
    """A `ProbabilisticActor` sampling ("agents", "action") and its log-prob from `policy`'s ("agents", "logits")."""
    return ProbabilisticActor(
        policy,
        in_keys={"logits": LOGITS},
        out_keys=[ACTION],
        distribution_class=torch.distributions.Categorical,
        # Validating the logits reads them back on the host at every call; NaN losses are caught once per update.
        distribution_kwargs={"validate_args": False},
        return_log_prob=True,
        log_prob_key=LOG_PROB,
        # The protocol samples actions in training and in evaluation alike.
        default_interaction_type=InteractionType.RANDOM,
    )


class ActingPass(TensorDictModuleBase):
    """A feed-forward actor and critic in one pass over plain tensors: what `TensorDictSequential(actor, critic)`
    writes (logits, sampled action, its log-prob, value), bit for bit, without the TensorDict plumbing around
    each of their modules. Collection runs the policy at every step, where that plumbing costs several times
    the arithmetic of small networks. Holds the actor's and critic's own networks: their weights, not copies.

    policy_net / value_net: uint8 observations [*B, 2, H, W, C] -> logits [*B, 2, 6] / values [*B, 2, 1].
    """

    def __init__(self, policy_net: nn.Module, value_net: nn.Module):
        super().__init__()
        self.policy_net, self.value_net = policy_net, value_net
        self.in_keys = [OBSERVATION]
        self.out_keys = [LOGITS, ACTION, LOG_PROB, VALUE]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        for key, value in zip(self.out_keys, self.act(tensordict.get(OBSERVATION))):
            tensordict.set(key, value)
        return tensordict

    def act(self, observation: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The pass on plain tensors: observation uint8 [*B, 2, H, W, C] -> (logits [*B, 2, 6], action int64 [*B, 2],
        its log-prob [*B, 2], value [*B, 2, 1]), in `out_keys`' order."""
        logits = self.policy_net(observation)
        action, log_prob = sample_actions(logits)
        return logits, action, log_prob, self.value_net(observation)

    def shared_networks(self) -> tuple[nn.Sequential, nn.Sequential] | None:
        """The policy and value networks as chains of plain modules holding these weights (not copies), where both
        share their parameters between the agents; else None."""
        if not all(isinstance(part, MultiAgentNet) and part.share_params
                   for network in (self.policy_net, self.value_net) for part in network):
            return None
        return tuple(nn.Sequential(*(part.shared_net() for part in network))
                     for network in (self.policy_net, self.value_net))


def draw_categorical(probs: torch.Tensor) -> torch.Tensor:
    """One draw per row of probs float [N, 6] from torch's current random stream: int64 [N, 1]."""
    return torch.multinomial(probs, 1, True)


def sample_actions(logits: torch.Tensor, draw: Callable[[torch.Tensor], torch.Tensor] = draw_categorical
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Actions int64 [*B] and their log-probabilities float32 [*B] from logits [*B, 6], as `sampling_actor`'s
    Categorical gives them, bit for bit: sampled by `draw` (interaction type RANDOM, the default), or the most
    likely (DETERMINISTIC or MODE)."""
    # As torch's Categorical(logits=logits) computes them: normalised logits, then their softmax.
    log_probs = logits - logits.logsumexp(-1, keepdim=True)
    probs = torch.softmax(log_probs, -1)
    mode = interaction_type() or InteractionType.RANDOM  # the actor's default: sample
    if mode is InteractionType.RANDOM:
        action = draw(probs.reshape(-1, NUM_ACTIONS)).reshape(logits.shape[:-1])
    elif mode in (InteractionType.DETERMINISTIC, InteractionType.MODE):
        action = probs.argmax(-1)
    else:
        raise ValueError(f"a categorical policy has no {mode.name.lower()} action; sample or take its mode")
    return action, log_probs.gather(-1, action.unsqueeze(-1)).squeeze(-1)


def plain_network(network: TensorDictSequential) -> nn.Sequential:
    """The modules of a chain of TensorDict modules (each reading what the one before wrote) as plain torch."""
    return nn.Sequential(*(module.module for module in network.module))


# ------------------------------------------------------------------------------------- E3T partner model
E3T_CONTEXT = 5  # (observation, partner action) pairs the partner predictor reads


def make_predictor_head(hidden: int, length: int) -> nn.Sequential:
    """One agent's reading of its context: float [..., k, h + 7] (each observation's code, then the one-hot partner
    action: 6 actions and NO_ACTION) -> float [..., 6] logits, through Linear(h) + ReLU -> Linear(6)."""
    return nn.Sequential(
        nn.Flatten(-2),
        _hidden_linear(length * (hidden + NO_ACTION + 1), hidden), nn.ReLU(),
        _orthogonal_(nn.Linear(hidden, NUM_ACTIONS), 0.01),
    )


class PartnerPredictor(TensorDictModuleBase):
    """E3T's partner model over both agents: the partner context -> the partner's next action.

    in:  ("agents", "context_observation") uint8 [*B, 2, k, H, W, C], ("agents", "context_action") int64 [*B, 2, k]
    out: ("agents", "partner_logits") [*B, 2, 6] and ("agents", "partner_prediction"), their softmax, detached:
         the policy reads the prediction as an input and the predictor learns from its own cross-entropy only.
    Each context observation goes through an encoder of the policy's kind ("mlp" or "gnn", weights of its own);
    the head reads the k codes with the k actions. `sequence_logits` gives the same logits for whole
    trajectories while encoding each observation once instead of k times (training).
    """

    def __init__(self, encoder: str, obs_shape: tuple[int, int, int], hidden: int, share_params: bool,
                 length: int = E3T_CONTEXT):
        super().__init__()
        self.length = length
        self.encoder = ObservationEncoder(encoder, obs_shape, hidden, share_params)
        self.head = MultiAgentNet(functools.partial(make_predictor_head, hidden, length),
                                  (length, hidden + NO_ACTION + 1), share_params=share_params)
        self.in_keys = [CONTEXT_OBSERVATION, CONTEXT_ACTION]
        self.out_keys = [PARTNER_LOGITS, PARTNER_PREDICTION]

    def _read(self, codes: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """codes float [*B, 2, k, h], actions int64 [*B, 2, k] -> logits [*B, 2, 6]."""
        one_hot = nn.functional.one_hot(actions, NO_ACTION + 1).to(codes.dtype)
        return self.head(torch.cat([codes, one_hot], -1))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # The encoder wants the agent dim just before the observation: [*B, 2, k, ...] -> [*B, k, 2, ...].
        codes = self.encoder(tensordict.get(CONTEXT_OBSERVATION).movedim(-5, -4)).movedim(-3, -2)
        logits = self._read(codes, tensordict.get(CONTEXT_ACTION))
        tensordict.set(PARTNER_LOGITS, logits)
        tensordict.set(PARTNER_PREDICTION, torch.softmax(logits.detach(), -1))
        return tensordict

    def sequence_logits(self, batch: TensorDictBase) -> torch.Tensor:
        """Logits [B, T, 2, 6] over trajectories [B, T] as a collector gives them (consecutive steps per kitchen).

        Slot j of step t's context holds the observation of step t - k + j, or padding where that step lies
        before the episode's start (there its action is NO_ACTION). So the codes of the batch's own
        observations, after the codes of the context at t = 0 (the steps before the batch), give every
        context by a sliding window; padded slots take the code of an all-zero observation, as they do step by
        step. Equal to `forward` step by step (tested), with one encoding per observation.
        """
        context_obs, actions = batch.get(CONTEXT_OBSERVATION), batch.get(CONTEXT_ACTION)  # [B, T, 2, k, ...]
        observation = batch.get(OBSERVATION)  # [B, T, 2, H, W, C]
        steps = observation.shape[1]
        before = self.encoder(context_obs[:, 0].movedim(-5, -4))  # [B, k, 2, h]: steps -k .. -1
        codes = torch.cat([before, self.encoder(observation)], dim=1)  # [B, k + T, 2, h]
        windows = codes.unfold(1, self.length, 1)[:, :steps].transpose(-1, -2)  # [B, T, 2, k, h]
        padding = self.encoder(torch.zeros_like(observation[:1, 0]))  # [1, 2, h]
        padded = (actions == NO_ACTION).unsqueeze(-1)
        windows = torch.where(padded, padding.unsqueeze(-2), windows)
        return self._read(windows, actions)


def partner_context_length(network: nn.Module) -> int:
    """The context length k a network's partner predictor reads (0 without one)."""
    lengths = {module.length for module in network.modules() if isinstance(module, PartnerPredictor)}
    if len(lengths) > 1:
        raise ValueError(f"one network reads partner contexts of several lengths {sorted(lengths)}")
    return lengths.pop() if lengths else 0


def split_partner_predictor(actor: ProbabilisticActor) -> tuple[PartnerPredictor, ProbabilisticActor]:
    """An E3T actor, `sampling_actor(TensorDictSequential(predictor, policy))` as `build_e3t` makes it, as its
    `PartnerPredictor` and the sampling actor of `policy` alone, which reads the ("agents", "partner_prediction")
    already in a tensordict (the one stored while acting) instead of predicting it anew. Shares their weights.

    Raises ValueError for an actor of another form (e.g. one without a predictor).
    """
    body = actor.module[0] if len(actor.module) else None
    parts = list(body.module) if isinstance(body, TensorDictSequential) else []
    if len(parts) < 2 or not isinstance(parts[0], PartnerPredictor):
        raise ValueError(
            "E3T needs an actor of the form sampling_actor(TensorDictSequential(PartnerPredictor(...), policy)), "
            "as the architectures e3t_mlp and e3t_gnn build it"
        )
    return parts[0], sampling_actor(TensorDictSequential(*parts[1:]))


@dataclass
class ActorCritic:
    """A policy and a value network over both agents (keys in the module docstring).

    actor: writes ("agents", "logits") [*B, 2, 6], ("agents", "action") int64 [*B, 2] and
        ("agents", "action_log_prob") [*B, 2]; samples by default (interaction type RANDOM).
    critic: writes ("agents", "state_value") float32 [*B, 2, 1].
    recurrent: whether both carry an LSTM state (then see `env_transforms` and `set_recurrent_mode`).
    acting: optional, both in one pass for collection (e.g. an `ActingPass`), writing what `actor` then `critic`
        write, from the same weights; `acting_policy` falls back to running `actor` then `critic`.
    """

    actor: ProbabilisticActor
    critic: TensorDictModuleBase
    recurrent: bool
    acting: TensorDictModuleBase | None = None

    def acting_policy(self, *after_actor: TensorDictModuleBase) -> TensorDictSequential:
        """The collection policy: the actor, `after_actor` (an algorithm's acting modules, which may change the
        actions), the critic. The critic reads only observations, so with a fused `acting` pass it runs first."""
        if self.acting is not None:
            return TensorDictSequential(self.acting, *after_actor)
        return TensorDictSequential(self.actor, *after_actor, self.critic)

    def env_transforms(self) -> list[Transform]:
        """Transforms to append to the KitchenEnv: none for a feed-forward model; for recurrent ones InitTracker()
        and one primer of every LSTM state of actor and critic ([*B, 2, 1, h] under "agents", zeroed at reset);
        for E3T models the partner context."""
        transforms = []
        if self.recurrent:
            states = {**recurrent_states(self.actor), **recurrent_states(self.critic)}
            transforms += [InitTracker(), agent_state_primer(states)]
        context_length = partner_context_length(self.actor)
        if context_length:
            transforms.append(PartnerContext(context_length))
        return transforms


def build_builtin(architecture: str, obs_shape: tuple[int, int, int], hidden: int,
                  share_params: bool) -> ActorCritic:
    """The four architectures of the paper, "mlp", "mlp_lstm", "gnn", "gnn_lstm", and the agent-centred MLP
    "ego_mlp"."""
    encoder, recurrent = architecture.removesuffix("_lstm"), architecture.endswith("_lstm")
    common = {"encoder": encoder, "obs_shape": tuple(obs_shape), "hidden": hidden, "recurrent": recurrent,
              "share_params": share_params}
    policy = make_network("actor", out_key=LOGITS, out_features=NUM_ACTIONS, out_gain=0.01, **common)
    critic = make_network("critic", out_key=VALUE, out_features=1, out_gain=1.0, **common)
    acting = None if recurrent else ActingPass(plain_network(policy), plain_network(critic))
    return ActorCritic(actor=sampling_actor(policy), critic=critic, recurrent=recurrent, acting=acting)


def build_e3t(encoder: str, obs_shape: tuple[int, int, int], hidden: int, share_params: bool) -> ActorCritic:
    """E3T's networks ("e3t_mlp", "e3t_gnn"): the feed-forward actor of `encoder` whose head also reads the
    partner prediction, after the partner predictor; the critic as in "mlp" / "gnn"."""
    common = {"encoder": encoder, "obs_shape": tuple(obs_shape), "hidden": hidden, "recurrent": False,
              "share_params": share_params}
    predictor = PartnerPredictor(encoder, obs_shape, hidden, share_params)
    policy = make_network("actor", out_key=LOGITS, out_features=NUM_ACTIONS, out_gain=0.01,
                          extra_inputs=[(PARTNER_PREDICTION, NUM_ACTIONS)], **common)
    critic = make_network("critic", out_key=VALUE, out_features=1, out_gain=1.0, **common)
    return ActorCritic(actor=sampling_actor(TensorDictSequential(predictor, policy)), critic=critic, recurrent=False)


# ----------------------------------------------------------------------------------------------- registry
Builder = Callable[..., ActorCritic]  # builder(obs_shape=(H, W, C), hidden=h, share_params=bool) -> ActorCritic
_REGISTRY: dict[str, Builder] = {}


def register_architecture(name: str, builder: Builder) -> None:
    """Make `make_actor_critic(name, ...)` call `builder(obs_shape=..., hidden=..., share_params=...)`.

    The builder returns an `ActorCritic` honouring the keys of the module docstring. A name can be registered
    once (`ValueError` otherwise), so a second registration cannot silently replace another architecture.
    """
    if name in _REGISTRY:
        raise ValueError(f"architecture {name!r} is already registered")
    _REGISTRY[name] = builder


for _name in ARCHITECTURES:
    register_architecture(_name, functools.partial(build_builtin, _name))
for _name in E3T_ARCHITECTURES:
    register_architecture(_name, functools.partial(build_e3t, _name.removeprefix("e3t_")))
del _name


def make_actor_critic(architecture: str, obs_shape: tuple[int, int, int] = (7, 7, 26), hidden: int = 256,
                      share_params: bool = True) -> ActorCritic:
    """Actor and critic of a registered architecture ("mlp", "mlp_lstm", "gnn", "gnn_lstm", "ego_mlp", "e3t_mlp",
    "e3t_gnn" or your own).

    obs_shape: (H, W, C) of one agent's observation; the model rejects other shapes. hidden: width h of every
    layer. share_params: one network for both agents (the paper's Infinite Kitchen runs) or one per agent
    (its Single Kitchen runs).
    """
    if architecture not in _REGISTRY:
        raise ValueError(f"unknown architecture {architecture!r}; registered: {', '.join(_REGISTRY)}")
    return _REGISTRY[architecture](obs_shape=tuple(obs_shape), hidden=hidden, share_params=share_params)
