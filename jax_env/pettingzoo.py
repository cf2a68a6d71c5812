"""`KitchenParallelEnv`: one kitchen of `jax_env.Overcooked` as a PettingZoo `ParallelEnv`.

For tools outside TorchRL (other RL libraries, human-play front ends, PettingZoo's own checks). Needs the
`pettingzoo` extra (`pip install .[pettingzoo]`); `jax_env` itself never imports this module.

    env = KitchenParallelEnv("cramped_room")           # or "infinite": a new generated level every reset
    observations, infos = env.reset(seed=0)
    observations, rewards, terminations, truncations, infos = env.step({"agent_0": 5, "agent_1": 0})

Per agent ("agent_0", "agent_1"; H x W the kitchen, 7x7 for the Infinite Kitchen):

    observation    numpy uint8 (H, W, 26)   the agent's view (`jax_env.observation`), Box(0, 255)
    action         int in [0, 6)            0-3 move/face north, south, east, west; 4 stay; 5 interact
    reward         float                    the shared sparse reward: 20 per soup delivered this step
    termination    bool                     always False: a kitchen never ends by itself
    truncation     bool                     True on step `max_steps`; the agents list is then emptied
    info           dict                     {"shaped_reward": float} with `shaped_reward=True`, else {}

The JAX state is never modified in place; arrays cross to numpy (as copies) only at the method boundary.
"""

from __future__ import annotations

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from pettingzoo import ParallelEnv

from jax_env.env import NUM_ACTIONS, Levels, Overcooked, ShapingWeights
from jax_env.generator import GeneratorConfig
from jax_env.render import render_state, state_to_text
from jax_env.state import State

AGENTS = ("agent_0", "agent_1")  # agent i is index i of the JAX env's arrays


class KitchenParallelEnv(ParallelEnv):
    """Two cooks sharing one Overcooked kitchen, stepped simultaneously (see the module docstring).

    Args:
        level: a layout name (`jax_env.layout_names()`), a text-grid file, a `Layout`, "infinite" (a freshly
            generated Infinite Kitchen level every reset, held-out levels excluded) or "heldout" (one of the
            held-out evaluation levels every reset); anything `jax_env.Overcooked` takes as `levels`.
        max_steps: episode length; the last step truncates the episode.
        shaped_reward: also report each agent's shaped reward (onion in pot, useful plate, soup pickup) as
            `infos[agent]["shaped_reward"]`. The reward itself stays the sparse delivery reward.
        render_mode: None, "rgb_array" (uint8 (H * tile_size, W * tile_size, 3)) or "ansi" (a text sketch).
        tile_size: pixels per cell for "rgb_array".
        shaping: weights of the shaped rewards.
        generator: the Infinite Kitchen generator's probabilities.

    Seeding: `reset(seed=s)` restarts the env's key stream at `jax.random.PRNGKey(s)`, and every reset plays the
    episode of `jax.random.split(stream)[1]` while the stream moves on to `split(stream)[0]`, so a seeded reset
    and the unseeded resets after it are reproducible. An env never seeded draws its first key from the OS.
    Steps use no randomness.
    """

    metadata = {"name": "infinite_kitchen_v0", "render_modes": ["rgb_array", "ansi"], "render_fps": 10}

    def __init__(
        self,
        level: Levels = "cramped_room",
        max_steps: int = 400,
        shaped_reward: bool = False,
        render_mode: str | None = None,
        tile_size: int = 32,
        shaping: ShapingWeights = ShapingWeights(),
        generator: GeneratorConfig = GeneratorConfig(),
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.jax_env = Overcooked(level, max_steps=max_steps, shaping=shaping, generator=generator)
        self.max_steps = self.jax_env.max_steps
        self.shaped_reward = bool(shaped_reward)
        self.render_mode = render_mode
        self.tile_size = int(tile_size)
        self.possible_agents = list(AGENTS)
        self.agents: list[str] = []
        # Built once: PettingZoo (and action-space seeding) expects the same space object on every call.
        self.observation_spaces = {
            agent: gymnasium.spaces.Box(0, 255, self.jax_env.obs_shape, np.uint8) for agent in self.possible_agents
        }
        self.action_spaces = {agent: gymnasium.spaces.Discrete(NUM_ACTIONS) for agent in self.possible_agents}
        self.state_space = gymnasium.spaces.Box(0, 255, self.jax_env.obs_shape, np.uint8)

        kitchen = self.jax_env

        def step(state: State, actions: jax.Array):
            # No auto-reset: PettingZoo hands the terminal observation out and leaves the next reset to the caller.
            next_state, reward, done, info = kitchen.step_env(state, actions)
            return kitchen.get_obs(next_state), next_state, reward, done, info["shaped_reward"]

        self._reset_jax = jax.jit(kitchen.reset)
        self._step_jax = jax.jit(step)
        self._key: jax.Array | None = None  # the key stream; None until the first reset
        self._state: State | None = None  # the kitchen as it stands, None before the first reset
        self._observations: np.ndarray | None = None  # uint8 (2, H, W, 26) for the current state

    def __repr__(self) -> str:
        return f"KitchenParallelEnv({self.jax_env!r})"

    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        """Box(0, 255, (H, W, 26), uint8), the same object on every call."""
        self._check_agent(agent)
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Discrete:
        """Discrete(6), the same object on every call."""
        self._check_agent(agent)
        return self.action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        """Start an episode: (observations, infos), one entry per agent. `options` is accepted and unused."""
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        elif self._key is None:
            self._key = jax.random.PRNGKey(np.random.SeedSequence().generate_state(1)[0])
        self._key, episode_key = jax.random.split(self._key)
        observations, self._state = self._reset_jax(episode_key)
        self._observations = np.array(observations)
        self.agents = list(self.possible_agents)
        infos = {agent: {"shaped_reward": 0.0} if self.shaped_reward else {} for agent in self.agents}
        return self._per_agent(self._observations, self.agents), infos

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        """Both agents act at once: (observations, rewards, terminations, truncations, infos) per agent.

        `actions` maps every live agent to an int in [0, 6). After the truncating step `agents` is empty and
        the env must be reset before it steps again.
        """
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if not self.agents:
            raise RuntimeError("the episode is over (agents is empty); call reset() to start another")
        missing = [agent for agent in self.agents if agent not in actions]
        if missing:
            raise ValueError(f"step() needs an action for every live agent; missing {missing}")
        chosen = []
        for agent in self.agents:
            action = int(actions[agent])
            if not 0 <= action < NUM_ACTIONS:
                raise ValueError(f"{agent}'s action must be in [0, {NUM_ACTIONS}), got {actions[agent]!r}")
            chosen.append(action)

        observations, self._state, reward, done, shaped = self._step_jax(
            self._state, jnp.asarray(chosen, dtype=jnp.int32)
        )
        observations, reward, done, shaped = jax.device_get((observations, reward, done, shaped))  # one transfer
        self._observations = np.array(observations)
        done = bool(done)

        agents = self.agents
        rewards = {agent: float(reward[AGENTS.index(agent)]) for agent in agents}
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, done)
        if self.shaped_reward:
            infos = {agent: {"shaped_reward": float(shaped[AGENTS.index(agent)])} for agent in agents}
        else:
            infos = {agent: {} for agent in agents}
        if done:
            self.agents = []
        return self._per_agent(self._observations, agents), rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | str | None:
        """The kitchen as it stands: an RGB array for "rgb_array", text for "ansi", None without a render_mode."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() was called without a render_mode; pass render_mode to the constructor")
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        if self.render_mode == "ansi":
            return state_to_text(self._state)
        return render_state(self._state, self.tile_size)

    def state(self) -> np.ndarray:
        """A global view for centralised critics: agent_0's observation, uint8 (H, W, 26) (`state_space`).

        Every observation shows the whole kitchen; agent_0's puts agent 0 in the "self" channels."""
        if self._observations is None:
            raise RuntimeError("call reset() before state()")
        return self._observations[0].copy()

    @property
    def kitchen_state(self) -> State | None:
        """The JAX `State` of the kitchen (None before the first reset), for inspection; do not modify it."""
        return self._state

    def _per_agent(self, observations: np.ndarray, agents: list[str]) -> dict:
        return {agent: observations[AGENTS.index(agent)] for agent in agents}

    def _check_agent(self, agent: str) -> None:
        if agent not in AGENTS:
            raise KeyError(f"unknown agent {agent!r}; this env's agents are {list(AGENTS)}")
