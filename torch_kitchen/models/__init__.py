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
                                                                    (`torch_kitchen.models.e3t_partner.PartnerContext`)
         out ("agents", "partner_logits" | "partner_prediction") float32 [*B, 2, 6]

Collection: feed-forward models also carry an `ActingPass` (`ActorCritic.acting`), actor and critic in one pass
over plain tensors that writes what the actor then the critic write, bit for bit; `acting_policy()` uses it
where there is one.

The package by concern: `networks` (encoders, heads, one network per agent or shared, `make_network`),
`recurrence` (the LSTM and its carried states), `acting` (sampling, and the `ActingPass` for collection),
`partner_predictor` (E3T's partner model); here, `ActorCritic`, the built-in architectures and the registry.

Recurrent models run one step at a time by default (collection); wrap training calls on [B, T] batches in
`torchrl.modules.set_recurrent_mode(True)` for backpropagation through time, T the last batch dim. Either way
the LSTM state is zeroed where "is_init" is True, also in the middle of a sequence.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

from tensordict.nn import (
    TensorDictModuleBase,
    TensorDictSequential,
)
from torchrl.envs import InitTracker, Transform
from torchrl.modules import ProbabilisticActor

from jax_env import NUM_ACTIONS
from torch_kitchen.keys import (
    LOGITS,
    PARTNER_PREDICTION,
    VALUE,
)
from torch_kitchen.models.acting import ActingPass, plain_network, sampling_actor
from torch_kitchen.models.e3t_partner import PartnerContext
from torch_kitchen.models.networks import (
    make_network,
)
from torch_kitchen.models.partner_predictor import (
    PartnerPredictor,
    partner_context_length,
)
from torch_kitchen.models.recurrence import agent_state_primer, recurrent_states

ARCHITECTURES = ("mlp", "mlp_lstm", "gnn", "gnn_lstm", "ego_mlp")
E3T_ARCHITECTURES = ("e3t_mlp", "e3t_gnn")  # with a partner predictor: trained with algorithm "e3t"


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
Builder = Callable[..., ActorCritic]  # builder(obs_shape=(H, W, C), hidden=h, share_params=bool, **options)
_REGISTRY: dict[str, Builder] = {}


def register_architecture(name: str, builder: Builder) -> None:
    """Make `make_actor_critic(name, ...)` call `builder(obs_shape=..., hidden=..., share_params=..., **options)`
    (options: plain values an architecture of its own takes, e.g. the scripted cook's convention; a checkpoint's
    model header keeps them).

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
                      share_params: bool = True, **options) -> ActorCritic:
    """Actor and critic of a registered architecture ("mlp", "mlp_lstm", "gnn", "gnn_lstm", "ego_mlp", "e3t_mlp",
    "e3t_gnn" or your own).

    obs_shape: (H, W, C) of one agent's observation; the model rejects other shapes. hidden: width h of every
    layer. share_params: one network for both agents (the paper's Infinite Kitchen runs) or one per agent
    (its Single Kitchen runs).
    """
    if architecture not in _REGISTRY:
        raise ValueError(f"unknown architecture {architecture!r}; registered: {', '.join(_REGISTRY)}")
    return _REGISTRY[architecture](obs_shape=tuple(obs_shape), hidden=hidden, share_params=share_params, **options)


def model_identity(architecture: str, obs_shape, hidden: int, share_params: bool) -> dict:
    """The recipe `make_actor_critic` builds a model from: what must match for saved weights to load into it,
    compared before any tensor is touched (`trainers.checkpoint.check_identity`)."""
    return {
        "architecture": architecture,
        "obs_shape": list(obs_shape),
        "hidden": hidden,
        "share_params": share_params,
    }
