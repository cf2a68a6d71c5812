"""The TorchRL hooks this project relies on that are not public API, all in this one module.

Each is tested in `tests/torch_kitchen/test_torchrl_internals.py`, so a TorchRL release that renames one fails
there, with the hook named, rather than somewhere deep in training.

- `MultiAgentNetBase` builds each agent's network through `_build_single_net()`, checks inputs in
  `_pre_forward_check()` and keeps a parameter-less template of the network in `_empty_net`. `MultiAgentNet`
  turns these into a plain `build` callable and a public `check_input()`. With shared parameters it runs the
  network built once by `get_stateful_net` instead of MultiAgentNetBase's per-call `to_module` into `_empty_net`,
  while the parameters are its own (others swapped in by a functional call run through the template); with one
  network per agent, it vmaps `vmap_func_module` over a copy of `_empty_net` of the calling thread's own.
- `ClipPPOLoss` keeps its value-clipping threshold as the tensor buffer `clip_value` and branches on it (`if
  self.clip_value:`) in every forward. `hold_value_clip_on_host` makes it a Python float: the same threshold,
  without a host read per minibatch or a graph break in a compiled loss.
- `ClipPPOLoss._get_entropy` checks the closed-form entropy for non-finite entries on the host (eager) or mixes in
  a sampled estimate (compiled). `entropy_without_host_check` takes the closed form as it is, eager and compiled.
- `TensorboardLogger` opens its `SummaryWriter` in `_create_experiment()`. `PurgingTensorboardLogger` opens it
  with `purge_step`, so that a resumed run drops the events a killed run wrote after its last checkpoint, and
  names its event file so that it is read after the killed run's.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn
from torch.utils.tensorboard import SummaryWriter
from torchrl.modules.distributions.utils import has_analytic_entropy
from torchrl.modules.models.multiagent import MultiAgentNetBase
from torchrl.record.loggers import TensorboardLogger

TEMPLATE = "_empty_net"  # MultiAgentNetBase's parameter-less copy of one agent's network
TIED = "_shared_net"  # the shared network holding the parameters, kept out of the module tree
TIED_LEAF = "_shared_net_leaf"  # (key, tensor): one of the parameters as the shared network holds it
THREAD_TEMPLATES = "_thread_templates"  # threading.local: each thread's copy of the template


def _drop_template_entries(module: nn.Module, state_dict: dict, prefix: str, local_metadata) -> None:
    for key in [key for key in state_dict if key.startswith(prefix + TEMPLATE + ".")]:
        del state_dict[key]


class MultiAgentNet(MultiAgentNetBase):
    """Any torch module applied to each agent: float [..., n_agents, *in_shape] -> [..., n_agents, *out].

    `build()` makes one agent's module (it must accept any leading dims). Shared: one module over both agents.
    Not shared: one module per agent, agent i's on input[..., i, *in_shape] (vmapped over stacked parameters).
    Subclasses refine `check_input`, which sees (and may convert) every input before the networks do.
    """

    def __init__(self, build: Callable[[], nn.Module], in_shape: tuple[int, ...], *, n_agents: int = 2,
                 share_params: bool = True):
        self.build = build
        self.in_shape = tuple(in_shape)
        super().__init__(n_agents=n_agents, centralized=False, share_params=share_params,
                         agent_dim=-len(in_shape) - 1)
        # torch-geometric layers save their weights themselves, even from the parameter-less template that
        # MultiAgentNetBase keeps; those entries are not parameters and must stay out of checkpoints.
        self.register_state_dict_post_hook(_drop_template_entries)
        self._tie()

    def check_input(self, inputs: torch.Tensor) -> torch.Tensor:
        """Raises ValueError unless `inputs` is [..., n_agents, *in_shape]; returns what the networks read."""
        expected = (self.n_agents, *self.in_shape)
        if tuple(inputs.shape[-len(expected):]) != expected:
            raise ValueError(f"{type(self).__name__} expects inputs [..., {', '.join(map(str, expected))}], "
                             f"got {list(inputs.shape)}")
        return inputs

    def _build_single_net(self, *, device=None, **kwargs) -> nn.Module:
        # MultiAgentNetBase rebuilds a parameter-less copy under `torch.device("meta")`: no device to pass on.
        return self.build()

    def _pre_forward_check(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.check_input(inputs)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        inputs = self.check_input(torch.cat(inputs, -1) if len(inputs) > 1 else inputs[0])
        if self.share_params and self.holds_own_parameters():  # the agent dim is one more batch dim
            return self.shared_net()(inputs)
        if self.share_params:  # parameters swapped in from outside (a functional call, vmap over teams)
            with self.params.to_module(self.thread_template(), preserve_module_state=False):
                return self.thread_template()(inputs)
        agent_dim = inputs.ndim + self.agent_dim
        per_agent = self.vmap_func_module(self.thread_template(), in_dims=(0, agent_dim), out_dims=(agent_dim,),
                                          randomness=self.vmap_randomness)
        return per_agent(self.params, inputs)

    def holds_own_parameters(self) -> bool:
        """Whether `params` are the parameters the built shared network holds: not while a functional call
        (`torch.func.functional_call`, `TensorDict.to_module`) has swapped others in."""
        tied = self.__dict__[TIED_LEAF]
        return tied is None or self.params.get(tied[0]) is tied[1]

    def thread_template(self) -> nn.Module:
        """The calling thread's copy of the parameter-less template into which each agent's parameters are moved
        while it runs: threads that run the network at once (a minibatch's shards) would otherwise move theirs
        into one module. A compiled graph (a compiled minibatch step is never split into shards) takes the
        template itself: it cannot trace thread-local storage."""
        if torch.compiler.is_compiling():
            return getattr(self, TEMPLATE)
        templates = self.__dict__.setdefault(THREAD_TEMPLATES, threading.local())
        if not hasattr(templates, "module"):
            templates.module = copy.deepcopy(getattr(self, TEMPLATE))
        return templates.module

    def shared_net(self) -> nn.Module:
        """The shared network as a plain module holding this net's own parameters (TorchRL's
        `get_stateful_net`), built once: MultiAgentNetBase would move them into its template on every call.
        Weights changed in place (optimizers, `load_state_dict`) are its weights; a copy, a pickle or a move
        to another device builds it anew."""
        net = self.__dict__.get(TIED)
        if net is None:
            net = self.__dict__[TIED] = self.get_stateful_net(copy=True)
        return net

    def _tie(self) -> None:
        """Notes one of the parameters as the module holds it now (built, moved or copied)."""
        key = next(iter(self.params.keys(include_nested=True, leaves_only=True)), None)
        self.__dict__[TIED_LEAF] = None if key is None else (key, self.params.get(key))  # None: no parameters

    def forget_built_networks(self) -> None:
        """Drops the shared network and the threads' templates built so far: the next call builds them again from
        the template and the parameters (after `.to()`, or layers given other classes)."""
        self.__dict__.pop(TIED, None)
        self.__dict__.pop(THREAD_TEMPLATES, None)

    def _apply(self, fn, *args, **kwargs):
        self.forget_built_networks()  # `.to()` may replace the parameters
        module = super()._apply(fn, *args, **kwargs)
        self._tie()
        return module

    def __getstate__(self) -> dict:
        state = dict(super().__getstate__())
        for built in (TIED, TIED_LEAF, THREAD_TEMPLATES):  # a copy builds its own, on its own parameters
            state.pop(built, None)
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        self._tie()


def hold_value_clip_on_host(loss: nn.Module) -> None:
    """Turns a TorchRL PPO loss's `clip_value` buffer (a one-element tensor, or absent) into a Python float: the
    loss branches on it in every forward, which on a tensor waits for the device (and breaks a compiled graph)."""
    threshold = loss._buffers.pop("clip_value", None)
    if threshold is not None:
        loss.clip_value = float(threshold)


def entropy_without_host_check(loss: nn.Module) -> None:
    """Gives a TorchRL PPO loss the closed-form entropy of its distribution as it is. Eager, the loss asks the device
    whether that entropy is finite in every forward (`entropy.isfinite().all()`): a host read per minibatch, and a
    branch on a tensor's value, which `torch.vmap` refuses. A categorical distribution over finite logits has a
    finite entropy; over NaN logits the loss is NaN either way."""
    def entropy(dist, adv_shape):
        if not has_analytic_entropy(dist):
            return type(loss)._get_entropy(loss, dist, adv_shape=adv_shape)
        return dist.entropy().unsqueeze(-1)

    loss._get_entropy = entropy


class PurgingTensorboardLogger(TensorboardLogger):
    """TorchRL's TensorBoard logger whose writer discards earlier events at steps >= `purge_step` (None: none)."""

    def __init__(self, exp_name: str, log_dir: str, purge_step: int | None = None):
        self.purge_step = purge_step
        super().__init__(exp_name=exp_name, log_dir=log_dir)

    def _create_experiment(self) -> SummaryWriter:
        directory = Path(self.log_dir) / self.exp_name
        if self.purge_step is not None:
            wait_past_last_event_file(directory)
        return SummaryWriter(log_dir=str(directory), purge_step=self.purge_step)


def wait_past_last_event_file(directory: Path) -> None:
    """Sleeps until the clock's second is past the newest event file's in `directory`.

    TensorBoard reads a run's event files in name order, and a name is the second it was opened then a
    per-process counter (so `.10` sorts before `.9`): a file opened in the same second as the last one may be read
    first, and its purge then drops nothing. A later second always sorts last."""
    last = max((int(path.name.split(".")[3]) for path in directory.glob("events.out.tfevents.*")), default=None)
    while last is not None and time.time() < last + 1:
        time.sleep(last + 1 - time.time())
