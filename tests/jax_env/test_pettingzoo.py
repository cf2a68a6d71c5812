"""The PettingZoo adapter: PettingZoo's own API check, step-for-step agreement with the JAX env, seeding, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("pettingzoo", reason="the PettingZoo adapter needs the extra: pip install .[pettingzoo]")

from pettingzoo.test import parallel_api_test  # noqa: E402

from jax_env import DELIVERY_REWARD, EAST, INTERACT, NORTH, SOUTH, STAY, WEST, Overcooked, parse_layout  # noqa: E402
from jax_env.pettingzoo import KitchenParallelEnv  # noqa: E402

AGENTS = ["agent_0", "agent_1"]
# Each agent in a one-cell booth: pot north, goal south, onion pile and plate pile to its sides.
BOOTHS = parse_layout("WPWPW\nO0B1O\nWXWXW", name="booths")


def random_actions(seed: int, steps: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 6, size=(steps, 2))


def play(env: KitchenParallelEnv, actions: np.ndarray) -> list:
    """Every step's (observations, rewards, truncations) until the episode ends or the actions run out."""
    trajectory = []
    for a0, a1 in actions:
        if not env.agents:
            break
        observations, rewards, _, truncations, _ = env.step({"agent_0": a0, "agent_1": a1})
        trajectory.append((observations, rewards, truncations))
    return trajectory


def assert_same_trajectory(first: list, second: list) -> None:
    assert len(first) == len(second)
    for (obs_a, rew_a, trunc_a), (obs_b, rew_b, trunc_b) in zip(first, second):
        assert rew_a == rew_b and trunc_a == trunc_b
        for agent in obs_a:
            np.testing.assert_array_equal(obs_a[agent], obs_b[agent])


@pytest.fixture(scope="module")
def infinite_env():
    # Shared: every test seeds it, and compiling the level generator once keeps the tests fast.
    return KitchenParallelEnv("infinite", max_steps=12)


@pytest.mark.parametrize("level", ["cramped_room", "infinite"])
def test_parallel_api_test_passes(level, infinite_env, recwarn):
    # Short episodes, so that the check also walks through the truncating step and the emptied agents list.
    env = infinite_env if level == "infinite" else KitchenParallelEnv(level, max_steps=12)
    parallel_api_test(env, num_cycles=20)
    assert not [str(w.message) for w in recwarn if "agent" in str(w.message).lower()]
    assert env.agents == []  # the check ran each episode to its end


def test_spaces_and_a_step_have_the_documented_shapes():
    env = KitchenParallelEnv("cramped_room", max_steps=5, shaped_reward=True, render_mode="rgb_array", tile_size=8)
    space = env.observation_space("agent_0")
    assert space is env.observation_space("agent_0")
    assert (space.shape, space.dtype, space.low.min(), space.high.max()) == ((4, 5, 26), np.uint8, 0, 255)
    assert env.action_space("agent_1").n == 6 and env.action_space("agent_1") is env.action_space("agent_1")
    with pytest.raises(KeyError, match="unknown agent"):
        env.observation_space("agent_2")

    observations, infos = env.reset(seed=0)
    assert env.agents == AGENTS and set(observations) == set(infos) == set(AGENTS)
    assert all(space.contains(obs) for obs in observations.values())
    assert env.render().shape == (4 * 8, 5 * 8, 3)
    np.testing.assert_array_equal(env.state(), observations["agent_0"])
    for step in range(5):
        observations, rewards, terminations, truncations, infos = env.step({"agent_0": 4, "agent_1": 4})
        assert all(space.contains(obs) for obs in observations.values())
        assert rewards == {"agent_0": 0.0, "agent_1": 0.0} and not any(terminations.values())
        assert infos == {"agent_0": {"shaped_reward": 0.0}, "agent_1": {"shaped_reward": 0.0}}
        assert all(truncations.values()) == (step == 4)
    assert env.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"agent_0": 4, "agent_1": 4})


def cook_in_booth(steps: int, seed: int) -> np.ndarray:
    """Actions for `BOOTHS`: agent 0 cooks and delivers soups on a fixed script, agent 1 acts at random."""
    onion = [WEST, INTERACT, NORTH, INTERACT]
    serve = [EAST, INTERACT, NORTH, INTERACT, SOUTH, INTERACT]
    script = onion * 3 + [STAY] * 22 + serve  # a pot cooks for 20 steps once its third onion is in
    cook = np.resize(script, steps)
    return np.stack([cook, random_actions(seed, steps)[:, 1]], axis=1)


def test_steps_match_the_jax_env():
    seed, max_steps = 7, 100
    env = KitchenParallelEnv(BOOTHS, max_steps=max_steps, shaped_reward=True)
    kitchen = Overcooked(BOOTHS, max_steps=max_steps)
    reference_step, reference_obs = jax.jit(kitchen.step_env), jax.jit(kitchen.get_obs)
    # The adapter's documented key derivation: a seeded reset plays split(PRNGKey(seed))[1].
    expected_obs, state = kitchen.reset(jax.random.split(jax.random.PRNGKey(seed))[1])
    observations, _ = env.reset(seed=seed)
    for i, agent in enumerate(AGENTS):
        np.testing.assert_array_equal(observations[agent], np.asarray(expected_obs[i]))

    total_reward = 0.0
    for t, (a0, a1) in enumerate(cook_in_booth(max_steps, seed=0)):
        state, reward, done, info = reference_step(state, jnp.asarray([a0, a1], jnp.int32))
        expected_obs = reference_obs(state)
        observations, rewards, terminations, truncations, infos = env.step({"agent_0": a0, "agent_1": a1})
        for i, agent in enumerate(AGENTS):
            np.testing.assert_array_equal(observations[agent], np.asarray(expected_obs[i]), err_msg=f"step {t}")
            assert rewards[agent] == float(reward[i]), f"step {t}"
            assert infos[agent]["shaped_reward"] == float(info["shaped_reward"][i]), f"step {t}"
            assert truncations[agent] == bool(done) and terminations[agent] is False, f"step {t}"
        total_reward += rewards["agent_0"]
    assert bool(done) and env.agents == []
    assert total_reward >= 2 * DELIVERY_REWARD  # the script's two soups: the comparison covered real rewards


def test_same_seed_same_trajectory_and_unseeded_resets_continue_the_stream(infinite_env):
    env, actions = infinite_env, random_actions(1, 30)

    def two_episodes(seed):
        """The first reset seeded, the second not: each episode's start grid and trajectory."""
        env.reset(seed=seed)
        first = (np.asarray(env.kitchen_state.grid), play(env, actions))
        env.reset()
        return first, (np.asarray(env.kitchen_state.grid), play(env, actions))

    run, rerun = two_episodes(3), two_episodes(3)
    for (grid, trajectory), (regrid, retrajectory) in zip(run, rerun):
        np.testing.assert_array_equal(grid, regrid)
        assert len(trajectory) == env.max_steps  # the episode ran to its truncation
        assert_same_trajectory(trajectory, retrajectory)
    # The unseeded reset drew a new level: the key stream moved on instead of replaying the seeded episode.
    assert not np.array_equal(run[0][0], run[1][0])


def test_different_seeds_give_different_infinite_levels(infinite_env):
    env = infinite_env
    assert env.observation_space("agent_0").shape == (7, 7, 26)
    grids, observations = [], []
    for seed in (0, 1):
        obs, _ = env.reset(seed=seed)
        grids.append(np.asarray(env.kitchen_state.grid))
        observations.append(obs["agent_0"])
    assert not np.array_equal(grids[0], grids[1])
    assert not np.array_equal(observations[0], observations[1])
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(env.kitchen_state.grid, grids[0])
    np.testing.assert_array_equal(obs["agent_0"], observations[0])


def test_bad_level_and_bad_actions_are_refused_clearly():
    with pytest.raises(ValueError, match="unknown layout 'no_such_kitchen'; registered layouts: cramped_room"):
        KitchenParallelEnv("no_such_kitchen")
    with pytest.raises(ValueError, match="does not exist"):
        KitchenParallelEnv("missing/kitchen.txt")

    env = KitchenParallelEnv("cramped_room")
    with pytest.raises(RuntimeError, match="reset"):
        env.step({"agent_0": 0, "agent_1": 0})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="missing \\['agent_1'\\]"):
        env.step({"agent_0": 0})
    with pytest.raises(ValueError, match="in \\[0, 6\\)"):
        env.step({"agent_0": 6, "agent_1": 0})
