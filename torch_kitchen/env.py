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
"""

from __future__ import annotations

import dataclasses
import os
from typing import Sequence

# JAX would otherwise take 75% of the GPU's memory at its first operation and starve torch.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict, TensorDictBase  # noqa: E402
from torchrl.data import Bounded, Categorical, Composite, Unbounded  # noqa: E402
from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv  # noqa: E402

from jax_env import DELIVERY_REWARD, NUM_ACTIONS, GeneratorConfig, Overcooked, ShapingWeights, State  # noqa: E402
from jax_env.env import Levels  # noqa: E402


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
        seed: seed of the levels, start facings and resets (also `set_seed`).
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
        seed: int = 0,
        pin_levels: bool = False,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be at least 1, got {num_envs}")
        device = torch.device(device)
        self._jax_device = jax_device_for(device)
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        self.num_envs = num_envs
        self.kitchen = Overcooked(levels, max_steps=max_steps, shaping=ShapingWeights(*shaping), generator=generator)
        self._make_specs()

        kitchen = self.kitchen
        if pin_levels and kitchen.num_levels == 0:
            raise ValueError("pin_levels needs a list of levels (or 'heldout'); the Infinite Kitchen generates them")
        # The level of every kitchen, or None: a fresh draw per episode.
        self.pinned_levels = np.arange(num_envs) % kitchen.num_levels if pin_levels else None
        levels_of_envs = None if self.pinned_levels is None else jnp.asarray(self.pinned_levels, jnp.int32)

        def observe(states, deliveries):
            """The outputs of kitchens as they stand: nothing earned, not done (resets and restores)."""
            zeros = jnp.zeros((num_envs, 2), jnp.float32)
            return self._outputs(states, deliveries, zeros, zeros, jnp.zeros(num_envs, bool))

        def reset_all(key):
            _, states = kitchen.reset_batch(key, num_envs, levels_of_envs)
            return observe(states, jnp.zeros(num_envs, jnp.int32))

        def reset_masked(key, states, deliveries, mask):
            return observe(kitchen.reset_where(key, states, mask, levels_of_envs), jnp.where(mask, 0, deliveries))

        def step(states, deliveries, actions):
            states, reward, done, info = jax.vmap(kitchen.step_env)(states, actions)
            return self._outputs(states, deliveries, reward, info["shaped_reward"], done)

        self._reset_all = jax.jit(reset_all)
        self._observe = jax.jit(observe)
        self._reset_masked = jax.jit(reset_masked)
        self._step_jax = jax.jit(step)
        self._states = None  # the JAX kitchens, batched
        self._deliveries = None  # int32 [B]: soups delivered this episode
        self._last_obs = None  # the JAX array behind the last observation handed out (zero-copy checks)
        self._restored = False  # set by `load_state_dict`: the next full reset hands out the restored kitchens
        self.set_seed(seed)

    def _make_specs(self) -> None:
        batch, (height, width, channels) = self.batch_size, self.kitchen.obs_shape
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
    def _outputs(self, states, deliveries, reward, shaped_reward, done):
        """(states, deliveries, (observation, scalars, done)): fresh arrays only, none of them part of the state.

        The per-env scalars travel as one float32 [B, 6] array (reward x2, shaped reward x2, deliveries this
        step, episode deliveries) so that a step crosses DLPack three times instead of six.
        """
        delivered = (reward[:, 0] / DELIVERY_REWARD).astype(jnp.int32)
        deliveries = deliveries + delivered
        scalars = jnp.concatenate(
            [reward, shaped_reward, delivered[:, None], deliveries[:, None]], axis=1, dtype=jnp.float32
        )
        return states, deliveries, (jax.vmap(self.kitchen.get_obs)(states), scalars, done[:, None])

    def _next_key(self) -> jax.Array:
        self._key, key = jax.random.split(self._key)
        return key

    # ------------------------------------------------------------------------------------------ torch side
    def _to_tensordict(self, out: tuple, with_reward: bool) -> TensorDictBase:
        observation, scalars, done = out
        self._last_obs = observation
        scalars, done = torch.from_dlpack(scalars), torch.from_dlpack(done)
        agents = {
            "observation": torch.from_dlpack(observation),
            "shaped_reward": scalars[:, 2:4].unsqueeze(-1),
        }
        if with_reward:
            agents["reward"] = scalars[:, 0:2].unsqueeze(-1)
        return TensorDict(
            {
                "agents": TensorDict(agents, batch_size=(*self.batch_size, 2), device=self.device),
                "deliveries": scalars[:, 4:5],
                "episode_deliveries": scalars[:, 5:6],
                "done": done,
                "truncated": done.clone(),
                "terminated": torch.zeros_like(done),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        full = mask is None or bool(mask.all())
        if self._restored and full:
            self._restored = False
            self._states, self._deliveries, out = self._observe(self._states, self._deliveries)
        elif self._states is None or full:
            self._states, self._deliveries, out = self._reset_all(self._next_key())
        else:
            mask = jax.dlpack.from_dlpack(mask.reshape(-1).contiguous())
            self._states, self._deliveries, out = self._reset_masked(
                self._next_key(), self._states, self._deliveries, mask
            )
        return self._to_tensordict(out, with_reward=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get(("agents", "action"))
        # int32 and contiguous, so JAX takes the memory as it is instead of a down-casting copy.
        actions = jax.dlpack.from_dlpack(actions.detach().to(torch.int32).contiguous())
        self._states, self._deliveries, out = self._step_jax(self._states, self._deliveries, actions)
        return self._to_tensordict(out, with_reward=True)

    def _set_seed(self, seed: int | None) -> None:
        self._key = jax.device_put(jax.random.PRNGKey(0 if seed is None else seed), self._jax_device)
        self._states = None  # the next reset starts every kitchen from the new seed

    # Checkpoints: `env.state_dict()` carries the kitchens, the episode counters and the key, so a resumed run
    # continues with exactly the levels and episodes it would have seen. All of it is CPU tensors, so that a
    # checkpoint loads with `torch.load(weights_only=True)`: data, never code.
    def get_extra_state(self) -> dict:
        """The key (int64 [2]), the kitchens (`State`'s fields by name, in their own dtypes) and the deliveries."""
        if self._states is None:
            self.reset()
        return {
            # The key is uint32, which torch supports only in part; int64 holds every value exactly.
            "key": _to_tensor(self._key, np.int64),
            "states": {field.name: _to_tensor(getattr(self._states, field.name)) for field in _STATE_FIELDS},
            "deliveries": _to_tensor(self._deliveries),
        }

    def set_extra_state(self, state: dict) -> None:
        """Restores the kitchens of `get_extra_state`; the next full `reset()` hands them out as they were."""
        expected_states, expected_deliveries, _ = jax.eval_shape(self._reset_all, self._key)
        expected = {field.name: getattr(expected_states, field.name) for field in _STATE_FIELDS}
        saved = state["states"]
        if {name: tuple(value.shape) for name, value in saved.items()} != {k: v.shape for k, v in expected.items()}:
            raise ValueError(
                f"this env state holds {len(state['deliveries'])} kitchens of another shape; the env has "
                f"{self.num_envs} {self.kitchen.obs_shape[0]}x{self.kitchen.obs_shape[1]} kitchens: build the env "
                "with the num_envs and levels the state was saved with"
            )
        if tuple(state["key"].shape) != self._key.shape:
            raise ValueError(
                f"this env state holds a JAX key of shape {tuple(state['key'].shape)}, this JAX makes keys of shape "
                f"{self._key.shape}: load it with the JAX PRNG implementation it was saved with"
            )
        self._key = self._to_jax(state["key"], self._key.dtype)
        self._states = State(**{name: self._to_jax(saved[name], value.dtype) for name, value in expected.items()})
        self._deliveries = self._to_jax(state["deliveries"], expected_deliveries.dtype)
        self._restored = True

    def _to_jax(self, tensor: torch.Tensor, dtype) -> jax.Array:
        # Through NumPy on the CPU: a checkpoint may have been loaded onto any torch device.
        return jax.device_put(np.asarray(tensor.detach().cpu().numpy(), dtype=dtype), self._jax_device)

    @property
    def states(self):
        """The JAX kitchens (a batched `jax_env.State`), read-only: for rendering and scenario checks."""
        return self._states


def with_transforms(env: EnvBase, transforms: Sequence[Transform]) -> EnvBase:
    """`env` with `transforms` appended (e.g. a model's `env_transforms()`), or `env` itself if there are none."""
    return TransformedEnv(env, Compose(*transforms)) if transforms else env
