"""`KitchenEnv`: the JAX kitchens as one batched TorchRL environment, with tensors crossing by DLPack.

Every `step` and `reset` is one jitted JAX call over all `num_envs` kitchens. Actions go from torch to JAX and
observations, rewards and dones come back through DLPack without copies; the JAX state stays on this object,
so TorchRL (which writes into the tensors it is given) never holds a buffer the state depends on.

Keys (B = num_envs, H x W the kitchen, 7x7 for the Infinite Kitchen):

    ("agents", "observation")    uint8   [B, 2, H, W, 26]  agent i's view (uint8 keeps rollouts 4x smaller;
                                                           models cast to float)
    ("agents", "action")         int64   [B, 2]            Categorical(6)
    ("agents", "reward")         float32 [B, 2, 1]         the shared sparse reward (20 per delivery)
    ("agents", "shaped_reward")  float32 [B, 2, 1]         each agent's shaped reward, unweighted by annealing
    "deliveries"                 float32 [B, 1]            soups delivered this step
    "episode_deliveries"         float32 [B, 1]            soups delivered so far this episode (the episode's
                                                           total on its last step)
    "done" / "truncated"         bool    [B, 1]            the time limit; "terminated" is always False

Teams: with a list of K seeds the kitchens form K teams of B/K (team k holds rows k*B/K .. (k+1)*B/K - 1), each
with its own key, so team k sees exactly the levels and resets of an env of B/K kitchens seeded with seed k. The
trainer steps several independently trained teams in one batch this way (`trainers.ppo.loop.train_teams`).
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv

from jax_env import DELIVERY_REWARD, NUM_ACTIONS, GeneratorConfig, Overcooked, ShapingWeights, State
from jax_env.env import Levels
from torch_kitchen.jax_settings import share_process_with_torch
from torch_kitchen.keys import ACTION, AGENTS, N_AGENTS, OBSERVATION, REWARD, SHAPED_REWARD
from torch_kitchen.rollout import as_tensordict, rollout_into

share_process_with_torch()


def team_rows(team: int, team_size: int) -> slice:
    """The rows of team `team` in a batch of teams of `team_size` kitchens."""
    return slice(team * team_size, (team + 1) * team_size)


def jax_device_for(device: torch.device) -> jax.Device:
    """The JAX device that shares memory with a torch device, or a `RuntimeError` that says what to install."""
    if device.type == "cpu":
        return jax.devices("cpu")[0]
    if device.type == "cuda":
        try:
            gpus = jax.devices("gpu")
        except RuntimeError:
            gpus = []
        index = device.index or 0
        if index >= len(gpus):
            raise RuntimeError(
                f"KitchenEnv(device={str(device)!r}) needs JAX on the same GPU, but this JAX sees "
                f"{len(gpus)} GPU(s) (backend: {jax.default_backend()}). Install a CUDA build of JAX matching "
                "your driver, e.g. `pip install -U \"jax[cuda12]\"`, or use device='cpu'."
            )
        return gpus[index]
    raise RuntimeError(f"KitchenEnv supports device='cpu' or 'cuda[:i]', got {str(device)!r}")


_STATE_FIELDS = dataclasses.fields(State)  # the kitchens travel in checkpoints as tensors named by these


def _to_tensor(array, dtype=None) -> torch.Tensor:
    """A CPU tensor copy of a JAX array (a copy: JAX's host buffers are read-only)."""
    return torch.from_numpy(np.array(array, dtype=dtype))


def pack_outputs(observation: jax.Array, scalars: jax.Array, done: jax.Array) -> jax.Array:
    """A step's outputs as one flat uint8 buffer, so that they cross DLPack once: the observations uint8 [B, 2, H, W,
    26], then the per-env scalars float32 [B, 6] as their bytes (reward x2, shaped reward x2, deliveries this step,
    episode deliveries), then done bool [B]. The observations' size (52 H W bytes a kitchen) keeps the floats
    4-byte aligned. `unpack_outputs` gives the three back as torch views."""
    as_bytes = jax.lax.bitcast_convert_type(scalars, jnp.uint8)
    return jnp.concatenate([observation.reshape(-1), as_bytes.reshape(-1), done.astype(jnp.uint8)])


def unpack_outputs(packed: torch.Tensor, num_envs: int,
                   obs_shape: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`pack_outputs`'s buffer, as a torch tensor, back as views: observation uint8 [B, 2, H, W, C], scalars
    float32 [B, 6], done bool [B, 1]."""
    observation_bytes = num_envs * 2 * int(np.prod(obs_shape))
    scalar_bytes = num_envs * 6 * 4
    observation, scalars, done = packed.split([observation_bytes, scalar_bytes, num_envs])
    return (observation.view(num_envs, 2, *obs_shape), scalars.view(torch.float32).view(num_envs, 6),
            done.view(torch.bool).view(num_envs, 1))


def output_entries(observation: torch.Tensor, scalars: torch.Tensor, done: torch.Tensor, with_reward: bool) -> dict:
    """A program's outputs, observation uint8 [*B, 2, H, W, C], scalars float32 [*B, 6] and done bool [*B, 1] (for
    one step, or a rollout's steps [B, T]), by key (the module docstring's keys), as views where they can be."""
    entries = {
        OBSERVATION: observation,
        SHAPED_REWARD: scalars[..., 2:4].unsqueeze(-1),
        "deliveries": scalars[..., 4:5],
        "episode_deliveries": scalars[..., 5:6],
        "done": done,
        "truncated": done.clone(),
        "terminated": torch.zeros_like(done),
    }
    if with_reward:
        entries[REWARD] = scalars[..., 0:2].unsqueeze(-1)
    return entries


class KitchenPrograms(NamedTuple):
    """The jitted JAX functions behind a `KitchenEnv`. Each returns (states, deliveries, outputs): the step's
    observations uint8 [B, 2, H, W, 26], scalars float32 [B, 6] and dones bool [B, 1] in fresh arrays, none of them
    part of the state. On a GPU the outputs are packed into one buffer (`pack_outputs`) so that they cross DLPack
    once (a crossing costs tens of microseconds there); on the CPU they stay three arrays, since packing them
    keeps XLA:CPU from writing the observations in place and doubles the step (120-200 us against 290-410 at
    JaxMARL's 16 kitchens), where a crossing costs about 15 us. The levels' start states are an argument, not a
    constant, so that kitchens of one size and settings share one compilation (a server starting a game compiles
    nothing)."""

    reset_all: Callable  # (start_states, keys [teams, 2]) -> every kitchen fresh
    reset_masked: Callable  # (start_states, keys, states, deliveries, mask [B]) -> the masked kitchens fresh
    observe: Callable  # (states, deliveries) -> the kitchens as they stand: nothing earned, not done
    step: Callable  # (states, deliveries, actions int32 [B, 2]) -> one step of every kitchen, no reset
    split_keys: Callable  # keys [teams, 2] -> (kept, used)


class ProgramCache:
    """Compiled programs by the settings and shapes they were built for, built once and shared by every env of
    them; the least recently used beyond `kept` are dropped (with their compilations). Envs are built from several
    threads (teams trained in parallel, a server), so a lookup holds a lock."""

    def __init__(self, kept: int):
        self.kept, self._programs, self._lock = kept, OrderedDict(), threading.Lock()

    def get(self, key: tuple, build: Callable[[], object]):
        """The programs built for `key`, built by `build()` if none are kept."""
        with self._lock:
            if key not in self._programs:
                self._programs[key] = build()
                if len(self._programs) > self.kept:
                    self._programs.popitem(last=False)
            self._programs.move_to_end(key)
            return self._programs[key]


_PROGRAMS = ProgramCache(kept=32)


def kitchen_programs(kitchen: Overcooked, num_envs: int, teams: int, pin_levels: bool,
                     packed: bool = False) -> KitchenPrograms:
    """The programs of `num_envs` kitchens of `kitchen`'s settings in `teams` teams, their outputs `packed` or not,
    built once per settings and shape and reused by every env of them (see `KitchenPrograms`)."""
    return _PROGRAMS.get((kitchen.settings, num_envs, teams, pin_levels, packed),
                         lambda: _build_programs(kitchen, num_envs, teams, pin_levels, packed))


def _build_programs(kitchen: Overcooked, num_envs: int, teams: int, pin_levels: bool,
                    packed: bool) -> KitchenPrograms:
    team_size = num_envs // teams
    # The level of every kitchen of a team, or None: a fresh draw per episode.
    levels_of_team = jnp.asarray(np.arange(team_size) % kitchen.num_levels, jnp.int32) if pin_levels else None

    def outputs(states, deliveries, reward, shaped_reward, done):
        delivered = (reward[:, 0] / DELIVERY_REWARD).astype(jnp.int32)
        deliveries = deliveries + delivered
        scalars = jnp.concatenate(
            [reward, shaped_reward, delivered[:, None], deliveries[:, None]], axis=1, dtype=jnp.float32
        )
        observation = jax.vmap(kitchen.get_obs)(states)
        out = pack_outputs(observation, scalars, done) if packed else (observation, scalars, done[:, None])
        return states, deliveries, out

    def observe(states, deliveries):
        zeros = jnp.zeros((num_envs, 2), jnp.float32)
        return outputs(states, deliveries, zeros, zeros, jnp.zeros(num_envs, bool))

    # Resets run per team (vmapped over the teams' keys) on [teams, team_size] views of the kitchens.
    def by_team(tree):
        return jax.tree_util.tree_map(lambda x: x.reshape(teams, team_size, *x.shape[1:]), tree)

    def flat(tree):
        return jax.tree_util.tree_map(lambda x: x.reshape(num_envs, *x.shape[2:]), tree)

    def reset_all(start_states, keys):
        levels = kitchen.with_start_states(start_states)
        _, states = jax.vmap(lambda key: levels.reset_batch(key, team_size, levels_of_team))(keys)
        return observe(flat(states), jnp.zeros(num_envs, jnp.int32))

    def reset_masked(start_states, keys, states, deliveries, mask):
        levels = kitchen.with_start_states(start_states)
        reset = jax.vmap(lambda key, states, mask: levels.reset_where(key, states, mask, levels_of_team))
        states = flat(reset(keys, by_team(states), by_team(mask)))
        return observe(states, jnp.where(mask, 0, deliveries))

    def step(states, deliveries, actions):
        states, reward, done, info = jax.vmap(kitchen.step_env)(states, actions)
        return outputs(states, deliveries, reward, info["shaped_reward"], done)

    def split_keys(keys):
        keys = jax.vmap(jax.random.split)(keys)  # [teams, 2, 2]
        return keys[:, 0], keys[:, 1]

    return KitchenPrograms(*(jax.jit(f) for f in (reset_all, reset_masked, observe, step, split_keys)))


class KitchenEnv(EnvBase):
    """A batch of Overcooked kitchens as a TorchRL environment (see the module docstring for the keys).

    Args:
        num_envs: kitchens stepped together (the env's batch size).
        levels: "infinite" (a new Infinite Kitchen level per episode, held-out levels excluded), "heldout",
            a layout name or text-grid file, or a list of them; see `jax_env.Overcooked`.
        max_steps: episode length.
        shaping: weights of the shaped rewards reported in ("agents", "shaped_reward").
        generator: the Infinite Kitchen generator's probabilities.
        device: "cpu" or "cuda[:i]"; JAX runs on the same device.
        seed: seed of the levels, start facings and resets (also `set_seed`); a list of K seeds splits the
            kitchens into K teams, one seed each (see the module docstring).
        pin_levels: kitchen b always plays level b % len(levels) of a list (or of "heldout") instead of a
            random one per episode: evaluation lays out its batch so that every test grid gets its kitchens.
    """

    batch_locked = True

    def __init__(
        self,
        num_envs: int = 32,
        levels: Levels = "infinite",
        max_steps: int = 256,
        shaping: ShapingWeights | Sequence[float] = ShapingWeights(),
        generator: GeneratorConfig = GeneratorConfig(),
        device: str | torch.device = "cpu",
        seed: int | Sequence[int] = 0,
        pin_levels: bool = False,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        self.teams = 1 if isinstance(seed, int) else len(seed)
        if self.teams < 1 or num_envs % self.teams:
            raise ValueError(f"{self.teams} team seeds cannot split {num_envs} kitchens into equal teams")
        team_size = self.team_size = num_envs // self.teams
        device = torch.device(device)
        self._jax_device = jax_device_for(device)
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        self.num_envs = num_envs
        self.jax_env = Overcooked(levels, max_steps=max_steps, shaping=ShapingWeights(*shaping), generator=generator)
        self._make_specs()

        kitchen = self.jax_env
        if pin_levels and kitchen.num_levels == 0:
            raise ValueError("pin_levels needs a list of levels (or 'heldout'); the Infinite Kitchen generates them")
        self.pinned_levels = np.tile(np.arange(team_size) % kitchen.num_levels, self.teams) if pin_levels else None
        self._packed = self._jax_device.platform != "cpu"  # see `KitchenPrograms`
        self._programs = kitchen_programs(kitchen, num_envs, self.teams, pin_levels, self._packed)
        # On the env's device once: an argument of the compiled resets, not a copy per reset.
        self._start_states = jax.device_put(kitchen.start_states, self._jax_device)
        self._states = None  # the JAX kitchens, batched
        self._deliveries = None  # int32 [B]: soups delivered this episode
        self._last_obs = None  # the JAX array behind the last observation handed out (zero-copy checks)
        self._restored = False  # set by `load_state_dict`: the next full reset hands out the restored kitchens
        self._episode_steps = None  # int [B] on the host: each kitchen's steps this episode, as its state counts them
        self.set_seed(seed)

    def _make_specs(self) -> None:
        batch, (height, width, channels) = self.batch_size, self.jax_env.obs_shape
        agents = (*batch, 2)
        self.observation_spec = Composite(
            agents=Composite(
                observation=Bounded(0, 255, shape=(*agents, height, width, channels), dtype=torch.uint8),
                shaped_reward=Unbounded(shape=(*agents, 1), dtype=torch.float32),
                shape=agents,
            ),
            deliveries=Unbounded(shape=(*batch, 1), dtype=torch.float32),
            episode_deliveries=Unbounded(shape=(*batch, 1), dtype=torch.float32),
            shape=batch,
        )
        self.action_spec = Composite(
            agents=Composite(action=Categorical(NUM_ACTIONS, shape=agents, dtype=torch.int64), shape=agents),
            shape=batch,
        )
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded(shape=(*agents, 1), dtype=torch.float32), shape=agents), shape=batch
        )
        done = Categorical(2, shape=(*batch, 1), dtype=torch.bool)
        self.done_spec = Composite(done=done, terminated=done.clone(), truncated=done.clone(), shape=batch)

    # -------------------------------------------------------------------------------------------- JAX side
    def _next_key(self) -> jax.Array:
        """uint32 [teams, 2]: a fresh key per team (each team's stream advances as a one-team env's would)."""
        self._key, key = self._programs.split_keys(self._key)
        return key

    # ------------------------------------------------------------------------------------------ torch side
    def _unpack(self, out) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A program's outputs as torch tensors sharing their memory: observation [B, 2, H, W, C], scalars [B, 6],
        done [B, 1] (one DLPack crossing where packed, three where not)."""
        if self._packed:
            self._last_obs = out
            return unpack_outputs(torch.from_dlpack(out), self.num_envs, self.jax_env.obs_shape)
        self._last_obs = out[0]
        return tuple(torch.from_dlpack(array) for array in out)

    def _entries(self, out, with_reward: bool) -> dict:
        """A program's outputs by key (the module docstring's keys), sharing JAX's memory: read them, do not write."""
        return output_entries(*self._unpack(out), with_reward)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        full = mask is None or bool(mask.all())
        if self._restored and full:
            self._restored = False
            self._states, self._deliveries, out = self._programs.observe(self._states, self._deliveries)
        elif self._states is None or full:
            self._states, self._deliveries, out = self._programs.reset_all(self._start_states, self._next_key())
        else:
            mask = jax.dlpack.from_dlpack(mask.reshape(-1).contiguous())
            self._states, self._deliveries, out = self._programs.reset_masked(
                self._start_states, self._next_key(), self._states, self._deliveries, mask
            )
        self._episode_steps = np.array(self._states.step)  # read once per reset, not per step
        return as_tensordict(self._entries(out, with_reward=False), self.batch_size, self.device)

    @staticmethod
    def _actions_to_jax(actions: torch.Tensor):
        """int actions [B, 2] -> what the jitted step takes. On the CPU a jitted call takes a NumPy array as it is
        (1.5 us); importing through DLPack costs 19 us a step. On a GPU, DLPack keeps the actions on the device.
        int32 and contiguous either way, so no cast."""
        actions = actions.detach().to(torch.int32).contiguous()
        return actions.numpy() if actions.device.type == "cpu" else jax.dlpack.from_dlpack(actions)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return as_tensordict(self.step_entries(tensordict.get(ACTION)), self.batch_size, self.device)

    def step_entries(self, actions: torch.Tensor) -> dict:
        """One step of every kitchen with `actions` int [B, 2], no reset: what `step` puts under "next", by key,
        without building a TensorDict (`torch_kitchen.rollout`). The tensors share JAX's memory: read them, do not
        write them."""
        self._states, self._deliveries, out = self._programs.step(
            self._states, self._deliveries, self._actions_to_jax(actions))
        self._episode_steps += 1
        return self._entries(out, with_reward=True)

    def episode_ended(self) -> bool:
        """Whether a kitchen's episode ended at the last step, known on the host (episodes end on a step count)."""
        return bool((self._episode_steps >= self.jax_env.max_steps).any())

    def rollout(self, max_steps: int, policy=None, callback=None, *, break_when_any_done: bool | None = None,
                auto_reset: bool = True, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        """TorchRL's `EnvBase.rollout`; with a policy and `break_when_any_done=False` (episodes reset as they end)
        the kitchens are stepped as `torch_kitchen.rollout` steps them: the same values, written in place into one
        batch (which holds no autograd graph)."""
        return kitchen_rollout(super(), self, max_steps, policy, callback, break_when_any_done, auto_reset,
                               tensordict, kwargs)

    def any_done(self, tensordict: TensorDictBase) -> bool:
        """Whether a kitchen's episode ended at the step that gave `tensordict` (marked under "_reset", as TorchRL's
        `EnvBase.any_done` does). Episodes end on a step count, so the host knows without reading "done" from the
        device: TorchRL's own check would wait for the device at every step."""
        if self._episode_steps is None:
            return super().any_done(tensordict)
        if not self.episode_ended():
            return False
        tensordict.set("_reset", tensordict.get("done").clone())
        return True

    def precompile(self) -> None:
        """Compiles the step for these kitchens without stepping them (the result is discarded), so that the first
        real step costs what every step costs: a server ticking several games cannot afford a compilation inside
        one game's tick. Resets first if the kitchens were never reset."""
        if self._states is None:
            self.reset()
        # Actions of the kind a real step passes (a NumPy array on the CPU is not a device array to the jit cache).
        actions = self._actions_to_jax(torch.zeros(self.num_envs, 2, dtype=torch.int32, device=self.device))
        jax.block_until_ready(self._programs.step(self._states, self._deliveries, actions))

    def _set_seed(self, seed: int | Sequence[int] | None) -> None:
        seeds = list(seed) if isinstance(seed, Sequence) else [seed or 0]
        if len(seeds) != self.teams:
            raise ValueError(f"this env has {self.teams} teams and needs as many seeds, got {seed}")
        keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
        self._key = jax.device_put(keys, self._jax_device)  # uint32 [teams, 2]
        self._states = None  # the next reset starts every kitchen from the new seed

    # Checkpoints: a team's state (`team_state`) carries its kitchens, episode counters and key, so a resumed run
    # continues with exactly the levels and episodes it would have seen; `env.state_dict()` holds every team's. All
    # of it is CPU tensors, so that a checkpoint loads with `torch.load(weights_only=True)`: data, never code.
    def team_state(self, team: int = 0) -> dict:
        """Team `team`'s key (int64 [2]), kitchens (`State`'s fields by name, in their own dtypes, [team_size, ...])
        and deliveries: what a one-team env with that team's seed would save."""
        if self._states is None:
            self.reset()
        rows = self._team_rows(team)
        return {
            # The key is uint32, which torch supports only in part; int64 holds every value exactly.
            "key": _to_tensor(self._key[team], np.int64),
            "states": {field.name: _to_tensor(getattr(self._states, field.name)[rows]) for field in _STATE_FIELDS},
            "deliveries": _to_tensor(self._deliveries[rows]),
        }

    def load_team_state(self, team: int, state: dict) -> None:
        """Restores one team's `team_state`; once every team's is loaded, the next full `reset()` hands the kitchens
        out as they were."""
        reset = self._programs.reset_all
        expected_states, expected_deliveries, _ = jax.eval_shape(reset, self._start_states, self._key)
        expected = {field.name: getattr(expected_states, field.name) for field in _STATE_FIELDS}
        saved = state["states"]
        team_shapes = {name: (self.team_size, *value.shape[1:]) for name, value in expected.items()}
        if {name: tuple(value.shape) for name, value in saved.items()} != team_shapes:
            raise ValueError(
                f"this env state holds {len(state['deliveries'])} kitchens of another shape; the env's teams have "
                f"{self.team_size} {self.jax_env.obs_shape[0]}x{self.jax_env.obs_shape[1]} kitchens: build the env "
                "with the num_envs and levels the state was saved with"
            )
        if tuple(state["key"].shape) != self._key.shape[1:]:
            raise ValueError(
                f"this env state holds a JAX key of shape {tuple(state['key'].shape)}, this JAX makes keys of shape "
                f"{self._key.shape[1:]}: load it with the JAX PRNG implementation it was saved with"
            )
        if self._states is None:  # an empty frame for the teams' rows, each filled by its team's state
            self._states, self._deliveries = jax.tree_util.tree_map(
                lambda shape: jnp.zeros(shape.shape, shape.dtype, device=self._jax_device),
                (expected_states, expected_deliveries),
            )
        rows = self._team_rows(team)
        self._key = self._key.at[team].set(self._to_jax(state["key"], self._key.dtype))
        self._states = State(**{
            name: getattr(self._states, name).at[rows].set(self._to_jax(saved[name], value.dtype))
            for name, value in expected.items()
        })  # fmt: skip
        self._deliveries = self._deliveries.at[rows].set(self._to_jax(state["deliveries"], expected_deliveries.dtype))
        self._restored = True

    def get_extra_state(self) -> dict:
        """One team: its `team_state`; several: {"teams": [team_state(k) for every team]}."""
        if self.teams == 1:
            return self.team_state(0)
        return {"teams": [self.team_state(team) for team in range(self.teams)]}

    def set_extra_state(self, state: dict) -> None:
        teams = state["teams"] if "teams" in state else [state]
        if len(teams) != self.teams:
            raise ValueError(f"this env state holds {len(teams)} teams, the env has {self.teams}")
        for team, team_state in enumerate(teams):
            self.load_team_state(team, team_state)

    def _team_rows(self, team: int) -> slice:
        if not 0 <= team < self.teams:
            raise IndexError(f"team {team} of an env with {self.teams} teams")
        return team_rows(team, self.team_size)

    def _to_jax(self, tensor: torch.Tensor, dtype) -> jax.Array:
        # Through NumPy on the CPU: a checkpoint may have been loaded onto any torch device.
        return jax.device_put(np.asarray(tensor.detach().cpu().numpy(), dtype=dtype), self._jax_device)

    @property
    def obs_shape(self) -> tuple[int, int, int]:
        """(height, width, channels) of an agent's observation of these kitchens."""
        return self.jax_env.obs_shape

    @property
    def jax_device(self) -> jax.Device:
        """The JAX device the kitchens live on (the env's torch device's twin)."""
        return self._jax_device

    def kitchens(self) -> tuple:
        """(start states, states, deliveries, key) as the env's programs take them: for a program that steps the
        kitchens outside the env (`torch_kitchen.xla_rollout`), which hands them back with `continue_from`."""
        return self._start_states, self._states, self._deliveries, self._key

    def continue_from(self, states, deliveries, key, observation: jax.Array) -> None:
        """The kitchens where a program outside the env left them (and the last observation it handed out): the
        env's next step, reset or checkpoint goes on from there."""
        self._states, self._deliveries, self._key, self._last_obs = states, deliveries, key, observation
        self._episode_steps = np.array(states.step)  # read once per program, as once per reset

    @property
    def states(self):
        """The JAX kitchens (a batched `jax_env.State`), read-only: for rendering and scenario checks."""
        return self._states


class AgentDones(Transform):
    """("agents", "done" | "terminated" | "truncated") bool [*B, 2, 1]: the kitchen's flags beside each agent's
    reward, where TorchRL's multi-agent GAE and PPO loss read them (`set_keys(done=("agents", "done"),
    terminated=("agents", "terminated"))`), as TorchRL's PettingZoo wrapper gives them per group: a TorchRL loop
    over the kitchens needs no expansion of its own (docs/environment.md)."""

    FLAGS = ("done", "terminated", "truncated")

    def __init__(self):
        super().__init__(in_keys=list(self.FLAGS), out_keys=[(AGENTS, flag) for flag in self.FLAGS])

    def _call(self, tensordict: TensorDictBase) -> TensorDictBase:
        for flag in self.FLAGS:
            kitchen = tensordict.get(flag)  # [*B, 1]
            tensordict.set((AGENTS, flag), kitchen.unsqueeze(-2).expand(*kitchen.shape[:-1], N_AGENTS, 1))
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        agents = observation_spec[AGENTS]
        for flag in self.FLAGS:
            agents[flag] = Categorical(2, shape=(*agents.shape, 1), dtype=torch.bool, device=agents.device)
        return observation_spec


class TransformedKitchenEnv(TransformedEnv):
    """A `KitchenEnv` with transforms that leave "done" as the kitchens give it (the models' and algorithms'):
    whether an episode ended is the kitchens' own answer, known on the host (`KitchenEnv.any_done`)."""

    def any_done(self, tensordict: TensorDictBase) -> bool:
        return self.base_env.any_done(tensordict)

    def rollout(self, max_steps: int, policy=None, callback=None, *, break_when_any_done: bool | None = None,
                auto_reset: bool = True, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        """As `KitchenEnv.rollout`, the transforms run as TorchRL runs them."""
        return kitchen_rollout(super(), self, max_steps, policy, callback, break_when_any_done, auto_reset,
                               tensordict, kwargs)


def kitchen_rollout(torchrl_env, env: EnvBase, max_steps: int, policy, callback, break_when_any_done: bool | None,
                    auto_reset: bool, tensordict: TensorDictBase | None, options: dict) -> TensorDictBase:
    """`env.rollout(...)`: stepped by `torch_kitchen.rollout` where TorchRL's rollout would step every kitchen
    `max_steps` times with `policy`, resetting episodes as they end; else by TorchRL (`torchrl_env`, the
    `super()` of `env`'s class)."""
    plain = {"return_contiguous": (False, None, True), "out": (None,), "storing_device": (None,),
             "auto_cast_to_device": (False,), "set_truncated": (False,), "trust_policy": (False, True)}
    fast = (policy is not None and callback is None and break_when_any_done is False
            and all(value in plain.get(name, ()) for name, value in options.items()))
    if not fast:
        return torchrl_env.rollout(max_steps, policy, callback, break_when_any_done=break_when_any_done,
                                   auto_reset=auto_reset, tensordict=tensordict, **options)
    if auto_reset:
        carrier = env.reset(tensordict)
    elif tensordict is None:
        raise RuntimeError("tensordict must be provided when auto_reset is False")
    else:
        carrier = env.maybe_reset(tensordict)
    storage, _ = rollout_into(env, policy, carrier, max_steps, reset_last=False)
    return storage.batch


def with_transforms(env: EnvBase, transforms: Sequence[Transform]) -> EnvBase:
    """`env` with `transforms` appended (e.g. a model's `env_transforms()`), or `env` itself if there are none.
    The transforms must leave "done" as `env` gives it."""
    if not transforms:
        return env
    wrapper = TransformedKitchenEnv if isinstance(env, KitchenEnv) else TransformedEnv
    return wrapper(env, Compose(*transforms))
