"""Rollouts of a `KitchenEnv` written in place: the batches TorchRL's `Collector` gives, without its per-step work.

A TorchRL collector builds, at every step, the env's output TensorDict, its `step_mdp` successor and the policy's
copy, then stacks the steps into the batch. Here the batch [B, T] is allocated once and each step writes its
tensors straight into its time slice; the kitchens are stepped through the env's JAX programs
(`KitchenEnv.step_entries`: on a GPU one DLPack crossing each way), and episode ends are known on the host, so no
step waits for the device.

Two ways of stepping, the same batches (`tests/torch_kitchen/test_rollout.py`, bit for bit against `Collector`):

    a bare `KitchenEnv`       the JAX step's outputs go to the batch and to the policy's next input as tensors;
                              where the policy is an acting pass on the observations (`TeamPolicy.act`), a
                              TensorDict is built only at an episode's end, for TorchRL's own partial reset
    a `TransformedKitchenEnv` the transforms (an LSTM's states, E3T's partner context) run as TorchRL runs them,
                              `step_and_maybe_reset`; only the storage is this module's

`KitchenCollector` offers this as a TorchRL collector (`BaseCollector`): a loop written for TorchRL's collectors
takes it as it is. `KitchenEnv.rollout(..., break_when_any_done=False)` runs the same steps.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import BaseCollector
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torch_kitchen.keys import ACTION, AGENTS, OBSERVATION, REWARD

NEXT = "next"
N_AGENTS = 2  # the agent dim of the "agents" entries


class RolloutStorage:
    """A batch [B, T] allocated once, like the first step's record, with every leaf's view at each step precomputed:
    writing step t is one `_foreach_copy_` into `batch`'s own memory (a batch handed out is overwritten by the next
    rollout into the same storage: consume it first)."""

    def __init__(self, record: TensorDictBase, steps: int, device: torch.device | None):
        with torch.no_grad():
            batch = record.detach().unsqueeze(-1).expand(*record.batch_size, steps).clone().zero_()
        if device is not None:
            batch = batch.to(device)
        batch.refine_names(..., "time")
        self.batch, self.steps = batch, steps
        self.keys = list(batch.keys(True, True))
        leaves = [batch.get(key) for key in self.keys]
        time_dim = record.ndim
        self.views = [[leaf.select(time_dim, t) for leaf in leaves] for t in range(steps)]

    def write(self, t: int, values: list[torch.Tensor | None]) -> None:
        """Step t's leaves, in `keys`' order. KeyError if one is missing: every step must hold the first one's keys
        (a rollout continued from a tensordict with keys a step does not give back, such as the reward left at the
        root by `torchrl.envs.utils.step_mdp`'s default reward key; use `env.step_mdp`)."""
        for key, value in zip(self.keys, values):
            if value is None:
                raise KeyError(f"step {t} of the rollout has no {key!r}, which its first step had: a rollout's "
                               "steps must hold the same keys (continue from `env.step_mdp(rollout[..., -1])`)")
        with torch.no_grad():  # the batch holds values, not the graph that made them
            torch._foreach_copy_(self.views[t], values)  # one call for every leaf (grouped kernels on a GPU)


def as_tensordict(values: dict, batch_size: torch.Size, device: torch.device | None) -> TensorDictBase:
    """Tensors by (nested) key as one TensorDict of `batch_size` and `device`, built in one go, its "agents" entries
    with the agent dim as the env's specs have it ([*B, 2])."""
    nested = {}
    for key, value in values.items():
        *path, name = as_path(key)
        node = nested
        for part in path:
            node = node.setdefault(part, {})
        node[name] = value
    return _nested_tensordict(nested, batch_size, device)


def _nested_tensordict(nested: dict, batch_size: torch.Size, device: torch.device | None) -> TensorDictBase:
    return TensorDict({
        name: _nested_tensordict(value, (*batch_size, N_AGENTS) if name == AGENTS else batch_size, device)
        if isinstance(value, dict) else value
        for name, value in nested.items()
    }, batch_size=batch_size, device=device)  # fmt: skip


def leaves(tensordict: TensorDictBase) -> dict:
    """A TensorDict's tensors by (nested) key."""
    return {key: tensordict.get(key) for key in tensordict.keys(True, True)}


def acting_on(policy, env: EnvBase) -> Callable[[dict], dict]:
    """`policy` as a function of the policy's input by key to its outputs by key: an acting pass on the
    observations alone where the policy offers one (`TeamPolicy.act`: no TensorDict), else the policy on a
    TensorDict of its input."""
    if getattr(policy, "acts_on_observation", False):
        return lambda root: policy.act(root[OBSERVATION])

    def act(root: dict) -> dict:
        return leaves(policy(as_tensordict(root, env.batch_size, env.device)))
    return act


def advance(env, next_values: dict) -> dict:
    """The policy's next input by key after a step of the bare `env`: the step's outputs but the reward (`step_mdp`),
    with the kitchens whose episode ended reset as TorchRL resets them (`maybe_reset`, a partial reset merged by
    TorchRL's own rule)."""
    root = {key: value for key, value in next_values.items() if key != REWARD}
    if env.episode_ended():
        return leaves(env.maybe_reset(as_tensordict(root, env.batch_size, env.device)))
    return root


def as_path(key) -> tuple[str, ...]:
    """A (nested) key as a tuple of names."""
    return (key,) if isinstance(key, str) else tuple(key)


def next_entry(key) -> object:
    """The key under "next" of a storage key ("next", ...), or None for a root key."""
    if not isinstance(key, tuple) or key[0] != NEXT:
        return None
    return key[1] if len(key) == 2 else key[1:]


def rollout_into(env: EnvBase, policy, carrier: TensorDictBase, steps: int, storage: RolloutStorage | None = None,
                 reset_last: bool = True) -> tuple[RolloutStorage, TensorDictBase | None]:
    """`steps` steps of every kitchen of `env` from `carrier` (the policy's first input: a reset's output, or the
    last step's successor) with `policy` acting, written into `storage` (allocated at the first step if None).
    Resets episodes as they end: at the last step too where `reset_last` (a collector's way; TorchRL's
    `EnvBase.rollout` leaves the last step's kitchens for the next call's `maybe_reset`). Returns the storage and
    the policy's next input (None where the last step was not followed by one). Runs in the caller's grad mode, as
    `EnvBase.rollout` does (collectors run without gradients)."""
    if isinstance(env, TransformedEnv):
        return transformed_rollout_into(env, policy, carrier, steps, storage, reset_last)
    act = acting_on(policy, env)
    root = leaves(carrier)
    sources = None  # each leaf's key among the step's "next" outputs, or None where the policy's input holds it
    for t in range(steps):
        acted = {**root, **act(root)}
        next_values = env.step_entries(acted[ACTION])
        if storage is None:
            record = {**acted, **{(NEXT, *as_path(key)): value for key, value in next_values.items()}}
            storage = RolloutStorage(as_tensordict(record, env.batch_size, env.device), steps, env.device)
        if sources is None:
            sources = [entry if entry in next_values else None for entry in map(next_entry, storage.keys)]
        storage.write(t, [acted.get(key) if source is None else next_values[source]
                          for key, source in zip(storage.keys, sources)])
        root = advance(env, next_values) if reset_last or t < steps - 1 else None
    return storage, None if root is None else as_tensordict(root, env.batch_size, env.device)


def transformed_rollout_into(env: TransformedEnv, policy, carrier: TensorDictBase, steps: int,
                             storage: RolloutStorage | None, reset_last: bool
                             ) -> tuple[RolloutStorage, TensorDictBase | None]:
    """`rollout_into` through `env`'s transforms, which run as TorchRL runs them (`step_and_maybe_reset`)."""
    for t in range(steps):
        carrier = policy(carrier)
        if reset_last or t < steps - 1:
            stepped, carrier = env.step_and_maybe_reset(carrier)
        else:
            stepped, carrier = env.step(carrier), None
        if storage is None:
            storage = RolloutStorage(stepped, steps, env.device)
        storage.write(t, [stepped.get(key) for key in storage.keys])
    return storage, carrier


class InPlaceCollector(BaseCollector):
    """A TorchRL collector over an env whose batches [B, frames_per_batch / B] its subclass's `rollout()` writes
    into one storage, every batch into the same (consume it before asking for the next), on the env's device."""

    def __init__(self, env: EnvBase, frames_per_batch: int, total_frames: int = -1):
        super().__init__()
        num_envs = env.batch_size.numel()
        if frames_per_batch % num_envs:
            raise ValueError(f"frames_per_batch={frames_per_batch} is not a whole number of steps of the env's "
                             f"{num_envs} kitchens")
        self.env = env
        self.frames_per_batch = self.requested_frames_per_batch = frames_per_batch
        self.total_frames = total_frames  # -1: no end, as TorchRL's collectors take it
        self.steps = frames_per_batch // num_envs
        self._frames = 0
        self._storage = None  # the subclass's, allocated at its first batch

    def rollout(self) -> TensorDictBase:
        """The next batch."""
        raise NotImplementedError

    def iterator(self) -> Iterator[TensorDictBase]:
        while self.total_frames < 0 or self._frames < self.total_frames:
            batch = self.rollout()
            self._frames += self.frames_per_batch
            yield batch

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        return self.env.set_seed(seed, static_seed=static_seed)

    def state_dict(self) -> OrderedDict:
        return OrderedDict(env_state_dict=self.env.state_dict(), frames=self._frames)

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        self.env.load_state_dict(state_dict["env_state_dict"])
        self._frames = state_dict["frames"]

    def shutdown(self, timeout: float | None = None, close_env: bool = True, raise_on_error: bool = True) -> None:
        self._storage = None
        if close_env and not self.env.is_closed:
            self.env.close()


class KitchenCollector(InPlaceCollector):
    """A TorchRL collector whose batches come from `rollout_into`: what TorchRL's `Collector(env, policy,
    frames_per_batch, total_frames, return_same_td=True)` yields over a `KitchenEnv`, bit for bit, at a fraction
    of the host's work per step (an `InPlaceCollector`). Actions are sampled (`exploration_type`, RANDOM by
    default)."""

    def __init__(self, env: EnvBase, policy, frames_per_batch: int, total_frames: int = -1,
                 exploration_type: ExplorationType = ExplorationType.RANDOM):
        super().__init__(env, frames_per_batch, total_frames)
        self.policy = policy
        self.exploration_type = exploration_type
        with torch.no_grad(), set_exploration_type(exploration_type):
            self._carrier = env.reset()
            # TorchRL's Collector learns the policy's outputs by running it once on a copy of the first input (its
            # random draws included): done here too, so a run collects what it collected with TorchRL's.
            policy(self._carrier.copy())

    def rollout(self) -> TensorDictBase:
        with torch.no_grad(), set_exploration_type(self.exploration_type):
            self._storage, self._carrier = rollout_into(self.env, self.policy, self._carrier, self.steps,
                                                        self._storage)
        return self._storage.batch
