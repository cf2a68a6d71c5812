"""Several independently trained teams in one batch of kitchens: each team acts, draws and resets as it would alone.

A `KitchenEnv` built with K seeds holds K teams of B/K kitchens, team k on rows k*B/K .. (k+1)*B/K - 1, each with
its own JAX key. The torch side keeps the teams apart with four pieces:

`RandomStream`   a team's own torch random stream (CPU, and its CUDA device), swapped in around the team's work,
                 so its weights, sampled actions and minibatch orders are those of a run of its own;
`TeamPolicy`     one TensorDict policy over the whole batch: team k's policy acts on team k's rows, in its stream;
                 stacked (`stack=True`, the GPU's way), the teams' networks run as one batched network over weights
                 stacked along a team dim, and only the sampling runs per team, in its stream;
`TeamTransform`  one env transform over the whole batch from one stateful transform per team (E3T's partner
                 seats, each drawing from its own generator), each on its team's rows.
`StackedLoss`    the K teams' losses of a minibatch as one computation (`torch.vmap` over their parameters
                 stacked along a team dim): every team's loss terms and metrics, at the kernel launches of one.

Team k's networks see exactly the tensors, of exactly the shapes, that a run of its own would give them, so
the arithmetic is the same, bit for bit (`tests/trainers/test_teams.py`). Stacked, the products are batched over
the teams: the same to float rounding (`tests/trainers/test_teams.py`), at the kernel launches of one team.
"""

from __future__ import annotations

import contextlib
import copy
import functools
from collections.abc import Callable, Iterator, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Composite
from torchrl.envs import Transform

from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.env import team_rows
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, OBSERVATION, VALUE
from torch_kitchen.models.acting import ActingPass, draw_categorical, layers_of, sample_actions


class RandomStream:
    """A torch random stream of its own, seeded like `torch.manual_seed(seed)`: `with stream.active():` makes it
    torch's global stream (CPU, and `device` if that is a GPU) and keeps where it got to for the next time. Inside
    its own `active()` a second one changes nothing: the stream goes on where it is."""

    def __init__(self, seed: int, device: str | torch.device = "cpu"):
        device = torch.device(device)
        self._cuda = device if device.type == "cuda" else None
        with torch.random.fork_rng(devices=[] if self._cuda is None else [self._cuda]):
            torch.manual_seed(seed)
            self._state = self._capture()
        self._active = False

    def _capture(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        cuda = torch.cuda.get_rng_state(self._cuda) if self._cuda is not None else None
        return torch.get_rng_state(), cuda

    def _restore(self, state: tuple[torch.Tensor, torch.Tensor | None]) -> None:
        torch.set_rng_state(state[0])
        if self._cuda is not None:
            torch.cuda.set_rng_state(state[1], self._cuda)

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        if self._active:  # already torch's stream: switching in its saved state would replay its draws
            yield
            return
        outer = self._capture()
        self._restore(self._state)
        self._active = True
        try:
            yield
        finally:
            self._active = False
            self._state = self._capture()
            self._restore(outer)


class StackedNetworks:
    """K networks of one architecture, chains of Flatten, Linear (`EgocentricLinear` included) and ReLU layers, run
    as one: called on x [K, ...], it gives network k's output on x[k], each linear layer one batched product
    (`baddbmm`) over copies of the K weights stacked along a leading team dim. The copies are taken again by
    `restack()`, after the networks' weights changed (an update, a load): optimizers change weights in place
    without a trace (fused Adam bumps no version counter)."""

    def __init__(self, networks: Sequence[nn.Module], compile_mode: str | None = None):
        """compile_mode: run the layers as one `torch.compile`d graph in this mode (None: eagerly). In
        "reduce-overhead" (a CUDA graph, whose outputs live in buffers the next replay overwrites) every output is
        copied out, since a collector keeps each step's outputs until the batch is stacked."""
        by_network = [layers_of(network) for network in networks]
        self.layers = by_network[0]
        if not all(isinstance(layer, STACKABLE) for layer in self.layers):
            raise ValueError(f"stacked networks hold {', '.join(t.__name__ for t in STACKABLE)} layers alone")
        self.weights = [[(layer.weight, layer.bias) if isinstance(layer, nn.Linear) else () for layer in layers]
                        for layers in by_network]
        self.stacked = [tuple(torch.stack([weights[i][j].detach() for weights in self.weights])
                              for j in range(len(self.weights[0][i]))) for i in range(len(self.layers))]
        self.compile_mode = compile_mode
        self._run = self._layers if compile_mode is None else torch.compile(self._layers, mode=compile_mode,
                                                                             fullgraph=True)

    def restack(self) -> None:
        """Copies the networks' weights into the stacked ones (in place: a CUDA graph keeps reading them there)."""
        with torch.no_grad():
            for i, stacked in enumerate(self.stacked):
                for j, out in enumerate(stacked):
                    torch.stack([weights[i][j].detach() for weights in self.weights], out=out)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.compile_mode != "reduce-overhead":
            return self._run(x, self.stacked)
        torch.compiler.cudagraph_mark_step_begin()
        return self._run(x, self.stacked).clone()

    def _layers(self, x: torch.Tensor, stacked: list[tuple[torch.Tensor, ...]]) -> torch.Tensor:
        for layer, stacked in zip(self.layers, stacked):
            if isinstance(layer, nn.Flatten):
                x = layer(x)
            elif isinstance(layer, nn.ReLU):
                x = torch.relu(x)
            else:  # a linear layer: [K, *N, in] -> [K, *N, out]
                if isinstance(layer, EgocentricLinear):
                    x = layer.window(x)
                weight, bias = stacked
                rows = x.reshape(x.shape[0], -1, x.shape[-1]).to(weight.dtype)
                out = torch.baddbmm(bias.unsqueeze(1), rows, weight.transpose(1, 2))
                x = out.reshape(*x.shape[:-1], weight.shape[1])
        return x


STACKABLE = (nn.Flatten, nn.Linear, nn.ReLU)


def acting_pass_of(policy: TensorDictModuleBase) -> ActingPass | None:
    """The `ActingPass` a policy is (alone, or alone in a `TensorDictSequential`), or None: the policy reads more
    than the observations or does more than act on them."""
    acting = policy.module[0] if isinstance(policy, TensorDictSequential) and len(policy.module) == 1 else policy
    return acting if isinstance(acting, ActingPass) else None


def stackable_acting(policies: Sequence[TensorDictModuleBase]) -> list[tuple[nn.Module, nn.Module]] | None:
    """Each policy's (policy network, value network) as plain chains, where every policy is an `ActingPass` alone
    over shared networks (`ActingPass.shared_networks`) that `StackedNetworks` can run; else None."""
    networks = []
    for policy in policies:
        acting = acting_pass_of(policy)
        pair = acting.shared_networks() if acting is not None else None
        if pair is None or not all(isinstance(layer, STACKABLE) for network in pair for layer in layers_of(network)):
            return None
        networks.append(pair)
    return networks


def compiled_call(function: Callable, mode: str) -> Callable:
    """`function` compiled in `mode`. In "reduce-overhead" (CUDA graphs on a GPU) its outputs live in buffers the next
    replay overwrites, and a rollout keeps every step's: each call marks a new step and returns copies."""
    run = torch.compile(function, mode=mode)
    if mode != "reduce-overhead":
        return run

    def replay(*args):
        torch.compiler.cudagraph_mark_step_begin()
        outputs = run(*args)
        return type(outputs)(output.clone() for output in outputs) if isinstance(outputs, tuple | list) else \
            outputs.clone()

    return replay


class TeamPolicy(TensorDictModuleBase):
    """Team k's `policies[k]` acts on team k's rows of the batch, drawing from `streams[k]` (see the module
    docstring). The policies read and write the same keys; one team's policy acts on the batch as it is.

    stack: run the teams' feed-forward acting passes as one network over stacked weights (`StackedNetworks`;
    `restack()` after the weights change) and sample per team; where the policies cannot be stacked (recurrent, GNN,
    an algorithm's acting modules), or with one team, the policies run one after the other. ValueError if asked to
    stack what cannot be.
    compile_mode: `torch.compile` in this mode (None: eager) the stacked networks, or else each team's acting pass
    on plain tensors, or else each team's policy.

    Where every policy is an acting pass, `act(observation)` runs the teams' passes on plain tensors, as `forward`
    does for a TensorDict: a rollout's way (`torch_kitchen.rollout`), with no TensorDict at a step.
    """

    def __init__(self, policies: Sequence[TensorDictModuleBase], streams: Sequence[RandomStream], team_size: int,
                 stack: bool = False, compile_mode: str | None = None):
        super().__init__()
        if len(policies) != len(streams):
            raise ValueError(f"{len(policies)} policies and {len(streams)} random streams: give one of each per team")
        self.policies = torch.nn.ModuleList(policies)
        self.streams = list(streams)
        self.team_size = team_size
        self.in_keys = list(policies[0].in_keys)
        self.out_keys = list(policies[0].out_keys)
        passes = [acting_pass_of(policy) for policy in policies]
        self.acts_on_observation = all(acting is not None for acting in passes)
        stacking = stack and len(policies) > 1
        compiled = functools.partial(compiled_call, mode=compile_mode) if compile_mode and not stacking else \
            (lambda f: f)
        # How the teams act: their passes on plain tensors, or else their policies on TensorDicts.
        self.passes = [compiled(acting.act) for acting in passes] if self.acts_on_observation else None
        self.runs = None if self.acts_on_observation else [compiled(policy) for policy in policies]
        self.stacked = None
        if stacking:
            networks = stackable_acting(policies)
            if networks is None:
                raise ValueError("only feed-forward acting passes over shared MLP networks stack; these policies "
                                 "run one team after another")
            policy_nets, value_nets = zip(*networks)
            self.stacked = StackedNetworks(policy_nets, compile_mode), StackedNetworks(value_nets, compile_mode)

    def restack(self) -> None:
        """Takes the stacked copies of the teams' weights again, if stacked: after every change to them."""
        for networks in self.stacked or ():
            networks.restack()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.acts_on_observation:
            for key, value in self.act(tensordict.get(OBSERVATION)).items():
                tensordict.set(key, value)
            return tensordict
        if len(self.runs) == 1:  # every step: spare one team the split and the copy back
            with self.streams[0].active():
                return self.runs[0](tensordict)
        acted = []
        for team, (policy, stream) in enumerate(zip(self.runs, self.streams)):
            with stream.active():
                acted.append(policy(tensordict[team_rows(team, self.team_size)]).select(*self.out_keys))
        return tensordict.update(torch.cat(acted))

    def act(self, observation: torch.Tensor) -> dict:
        """Every team's acting pass on its rows of observation uint8 [B, 2, H, W, C], each in its random stream: the
        outputs by key (`ActingPass.out_keys`: logits, action, log-prob, value). Only where `acts_on_observation`."""
        if self.stacked is not None:
            return self._stacked_act(observation)
        if len(self.passes) == 1:
            with self.streams[0].active():
                outputs = self.passes[0](observation)
        else:
            by_team = []
            for team, (act, stream) in enumerate(zip(self.passes, self.streams)):
                with stream.active():
                    by_team.append(act(observation[team_rows(team, self.team_size)]))
            outputs = [torch.cat(values) for values in zip(*by_team)]
        return dict(zip(ACTING_KEYS, outputs))

    def _stacked_act(self, observation: torch.Tensor) -> dict:
        by_team = observation.reshape(len(self.streams), self.team_size, *observation.shape[1:])
        policy_net, value_net = self.stacked
        logits = policy_net(by_team).flatten(0, 1)

        def draw_per_team(probs):  # rows by team: each team's draws from its own stream
            draws = []
            for team_probs, stream in zip(probs.chunk(len(self.streams)), self.streams):
                with stream.active():
                    draws.append(draw_categorical(team_probs))
            return torch.cat(draws)

        action, log_prob = sample_actions(logits, draw_per_team)
        return dict(zip(ACTING_KEYS, (logits, action, log_prob, value_net(by_team).flatten(0, 1))))


ACTING_KEYS = (LOGITS, ACTION, LOG_PROB, VALUE)  # what an acting pass writes, in `ActingPass.act`'s order


class StackedLoss:
    """The losses of K teams (modules of one kind, e.g. TorchRL's `ClipPPOLoss`) as one computation: one of them
    runs under `torch.vmap` over the teams' parameters stacked along a leading team dim, on their minibatches
    stacked the same way. Called on minibatches [K, ...], it gives every output of team k's loss on minibatch k,
    reduced to its mean, as entry k of a [K] tensor: loss terms and metrics are each team's own (to float rounding),
    and the gradient of the sum of the teams' loss terms reaches each team's own parameters as its loss's gradient.

    `prepare(minibatch)`, where given, runs on each team's minibatch first (an algorithm's `process_minibatch`).
    Under vmap, the loss and `prepare` may branch on no tensor's value: feed-forward models with shared parameters
    (recurrent ones do, and per-agent networks vmap over agents themselves).
    """

    def __init__(self, losses: Sequence[nn.Module], prepare: Callable[[TensorDictBase], None] | None = None):
        self.losses = list(losses)
        self.template = copy.deepcopy(self.losses[0])  # runs every team's parameters in turn, its own none
        # Reduced per team below: under vmap a loss's mean is a scalar, which TorchRL then fails to squeeze.
        self.template.reduction = "none"
        self.names = [name for name, _ in self.template.named_parameters()]
        self.prepare = prepare

    def parameters(self) -> dict[str, torch.Tensor]:
        """The teams' parameters stacked along the team dim, by name, differentiably: gradients flow back to each
        team's (or stop at these, `torch.autograd.grad`)."""
        by_team = [dict(loss.named_parameters()) for loss in self.losses]
        return {name: torch.stack([parameters[name] for parameters in by_team]) for name in self.names}

    def _team_loss(self, parameters: TensorDictBase, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        if self.prepare is not None:
            self.prepare(minibatch)
        # tensordict's swap keeps the stacked tensors as they are; `torch.func.functional_call` would make the
        # entries of TorchRL's `TensorDictParams` new leaf parameters, cutting them off from the teams' weights.
        with parameters.to_module(self.template):
            outputs = self.template(minibatch)
        return {key: value.mean() for key, value in outputs.items()}

    def __call__(self, minibatches: TensorDictBase,
                 parameters: dict[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """Every team's loss outputs on its minibatch, [K] each, with `parameters` (default: `self.parameters()`)."""
        stacked = self.parameters() if parameters is None else parameters
        parameters = TensorDict(stacked, batch_size=[len(self.losses)]).unflatten_keys(".")
        return torch.vmap(self._team_loss)(parameters, minibatches)


class TeamTransform(Transform):
    """An env transform made of one transform per team, transform k on team k's rows (see the module docstring).
    The transforms write the same keys and specs; each keeps its own state."""

    def __init__(self, transforms: Sequence[Transform], team_size: int):
        first = transforms[0]
        super().__init__(in_keys=list(first.in_keys), out_keys=list(first.out_keys))
        self.transforms = torch.nn.ModuleList(transforms)
        self.team_size = team_size

    def _by_team(self, method: str, tensordict: TensorDictBase | None, out: TensorDictBase) -> TensorDictBase:
        """Calls every team's `transform.<method>(tensordict rows, out rows)` and writes their outputs into `out`."""
        parts = []
        for team, transform in enumerate(self.transforms):
            rows = team_rows(team, self.team_size)
            part = getattr(transform, method)(None if tensordict is None else tensordict[rows], out[rows])
            parts.append(part.select(*self.out_keys))
        return out.update(torch.cat(parts))

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._by_team("_reset", tensordict, tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._by_team("_step", tensordict, next_tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return self.transforms[0].transform_observation_spec(observation_spec)
