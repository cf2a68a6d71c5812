import jax
import numpy as np
import pytest
import torch

from jax_env import Overcooked
from jax_env.state import State
from torch_kitchen.symmetry import NUM_SYMMETRIES, direction_map, transform_action_probs, transform_observation


def _mirrored(state: State, symmetry: int) -> State:
    """The kitchen `state` under `symmetry`, cell by cell (what `transform_observation` claims to show)."""
    grid, contents = np.asarray(state.grid), np.asarray(state.contents)
    height, width = grid.shape
    x, y = np.asarray(state.agent_pos) % width, np.asarray(state.agent_pos) // width
    if symmetry & 1:
        grid, contents, x = grid[:, ::-1], contents[:, ::-1], width - 1 - x
    if symmetry & 2:
        grid, contents, y = grid[::-1], contents[::-1], height - 1 - y
    if symmetry & 4:
        grid, contents, x, y = grid.T, contents.T, y, x
    facing = np.asarray(direction_map(symmetry))[np.asarray(state.agent_dir)]
    return state.replace(grid=np.ascontiguousarray(grid), contents=np.ascontiguousarray(contents),
                         agent_pos=(y * grid.shape[1] + x).astype(np.int32), agent_dir=facing.astype(np.int32))


def _same(a: State, b: State) -> bool:
    return all(np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_every_symmetry_of_a_kitchen_plays_out_as_the_mirror_image_of_the_game():
    """Generated kitchens, random play: the mirrored state's observation is the mirrored observation, and the
    mirrored state stepped with the mirrored actions is the mirror of the next state, with the same rewards."""
    env = Overcooked("infinite", max_steps=256)
    step, observe = jax.jit(env.step_env), jax.jit(env.get_obs)
    rng = np.random.default_rng(0)
    _, state = env.reset(jax.random.PRNGKey(0))
    checked = 0
    for t in range(120):
        actions = rng.integers(0, 6, size=2).astype(np.int32)
        symmetry = t % NUM_SYMMETRIES
        mirrored = _mirrored(state, symmetry)
        observation = torch.from_numpy(np.array(observe(state)))
        assert torch.equal(torch.from_numpy(np.array(observe(mirrored))), transform_observation(observation, symmetry))
        moved = np.asarray([*direction_map(symmetry), 4, 5])[actions].astype(np.int32)
        next_state, reward, _, info = step(state, actions)
        next_mirrored, mirrored_reward, _, mirrored_info = step(mirrored, moved)
        assert _same(next_mirrored, _mirrored(next_state, symmetry)), (t, symmetry)
        assert np.array_equal(reward, mirrored_reward)
        assert np.array_equal(info["shaped_reward"], mirrored_info["shaped_reward"])
        checked += int(not np.array_equal(np.asarray(next_state.contents), np.asarray(state.contents)))
        state = next_state
    assert checked > 0  # some steps changed what the kitchen holds, not only where the cooks stand


@pytest.mark.parametrize("symmetry", range(NUM_SYMMETRIES))
def test_action_probabilities_follow_the_moves_they_belong_to(symmetry):
    probs = torch.tensor([0.1, 0.2, 0.3, 0.15, 0.05, 0.2])
    mirrored = transform_action_probs(probs, symmetry)
    for action, mapped in enumerate([*direction_map(symmetry), 4, 5]):
        assert mirrored[mapped] == probs[action]
