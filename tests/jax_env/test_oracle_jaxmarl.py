"""Step-for-step equality with JaxMARL's Overcooked (the pip package jaxmarl==0.2.0) on the classic layouts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxmarl.environments.overcooked.layouts import overcooked_layouts
from jaxmarl.environments.overcooked.overcooked import Overcooked as ReferenceOvercooked

from jax_env import CLASSIC_LAYOUTS, POT, Overcooked, State, get_layout

# JaxMARL's object codes for the items an agent or counter can hold.
_REF_ITEM_TO_OURS = np.zeros(16, dtype=np.int32)
_REF_ITEM_TO_OURS[[3, 5, 9]] = [1, 2, 3]  # onion, plate, dish; everything else empty


def _ref_obs(obs):
    return jnp.stack([obs["agent_0"], obs["agent_1"]])


def _ref_actions(actions):
    return {"agent_0": actions[0], "agent_1": actions[1]}


def _state_from_reference(ref_state, layout) -> State:
    """Our state equal to a JaxMARL state (unbatched, jittable)."""
    height, width = layout.shape
    pad = (ref_state.maze_map.shape[0] - height) // 2
    inner = ref_state.maze_map[pad : pad + height, pad : pad + width]
    grid = jnp.asarray(layout.grid)
    items = jnp.asarray(_REF_ITEM_TO_OURS)[inner[..., 0].astype(jnp.int32)]
    contents = jnp.where(grid == POT, inner[..., 2].astype(jnp.int32), items).astype(jnp.uint8)
    xy = ref_state.agent_pos.astype(jnp.int32)
    return State(
        grid=grid,
        contents=contents,
        agent_pos=xy[:, 1] * width + xy[:, 0],
        agent_dir=ref_state.agent_dir_idx.astype(jnp.int32),
        agent_inv=jnp.asarray(_REF_ITEM_TO_OURS)[ref_state.agent_inv.astype(jnp.int32)],
        step=ref_state.step.astype(jnp.int32),
    )


def _first_mismatch(matches: np.ndarray) -> str:
    t, e = np.argwhere(~matches)[0]
    return f"first mismatch at step {t}, env {e}"


@pytest.mark.parametrize("name", CLASSIC_LAYOUTS)
def test_random_rollouts_match_reference_through_auto_resets(name):
    """Same keys and random actions: identical obs, rewards, shaped rewards and dones, including auto-resets."""
    num_envs, num_steps, max_steps = 32, 250, 80  # 8,000 steps, 3 auto-resets per env
    ref = ReferenceOvercooked(layout=overcooked_layouts[name], max_steps=max_steps)
    env = Overcooked(name, max_steps=max_steps)

    keys = jax.random.split(jax.random.PRNGKey(7), num_envs)
    ref_obs, ref_state = jax.jit(jax.vmap(ref.reset))(keys)  # compiled whole: op by op, each op compiles alone
    obs, state = jax.jit(jax.vmap(env.reset))(keys)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(jax.vmap(_ref_obs)(ref_obs)))

    def one_step(carry, key):
        ref_state, state = carry
        key_act, key_step = jax.random.split(key)
        actions = jax.random.randint(key_act, (num_envs, 2), 0, 6, dtype=jnp.int32)
        step_keys = jax.random.split(key_step, num_envs)
        r_obs, ref_state, r_rew, r_done, r_info = jax.vmap(ref.step)(
            step_keys, ref_state, jax.vmap(_ref_actions)(actions)
        )
        obs, state, rew, done, info = jax.vmap(env.step)(step_keys, state, actions)
        r_shaped = jnp.stack([r_info["shaped_reward"]["agent_0"], r_info["shaped_reward"]["agent_1"]], -1)
        r_reward = jnp.stack([r_rew["agent_0"], r_rew["agent_1"]], -1)
        checks = jnp.stack(
            [
                jnp.all(obs == jax.vmap(_ref_obs)(r_obs), axis=(1, 2, 3, 4)),
                jnp.all(rew == r_reward, axis=1),
                jnp.all(info["shaped_reward"] == r_shaped, axis=1),
                done == r_done["__all__"],
            ]
        )
        return (ref_state, state), (checks, done)

    step_keys = jax.random.split(jax.random.PRNGKey(11), num_steps)
    _, (checks, dones) = jax.jit(lambda c: jax.lax.scan(one_step, c, step_keys))((ref_state, state))
    checks = np.asarray(checks)
    for index, what in enumerate(["observation", "reward", "shaped reward", "done"]):
        assert checks[:, index].all(), f"{name}: {what} differs, {_first_mismatch(checks[:, index])}"
    assert int(np.asarray(dones).sum()) == num_envs * (num_steps // max_steps)


@pytest.mark.parametrize("name", CLASSIC_LAYOUTS)
def test_every_transition_from_random_states_matches_reference(name):
    """From JaxMARL's randomised states (random cells, pot statuses, inventories), every single transition
    gives the same next state, observation, rewards and done. Deliveries and soup pick-ups happen here."""
    num_envs, num_steps, max_steps = 128, 120, 60
    layout = get_layout(name)
    ref = ReferenceOvercooked(layout=overcooked_layouts[name], max_steps=max_steps, random_reset=True)
    env = Overcooked(layout, max_steps=max_steps)

    keys = jax.random.split(jax.random.PRNGKey(3), num_envs)
    _, ref_state = jax.jit(jax.vmap(ref.reset))(keys)

    def one_transition(ref_state, key):
        key_act, key_step = jax.random.split(key)
        # Interact more often than uniform to visit more interaction outcomes.
        actions = jax.random.choice(
            key_act, 6, (num_envs, 2), p=jnp.asarray([0.14, 0.14, 0.14, 0.14, 0.04, 0.4])
        ).astype(jnp.int32)
        step_keys = jax.random.split(key_step, num_envs)
        ref_actions = jax.vmap(_ref_actions)(actions)

        state = jax.vmap(_state_from_reference, in_axes=(0, None))(ref_state, layout)
        r_obs, r_next, r_rew, r_done, r_info = jax.vmap(ref.step_env)(step_keys, ref_state, ref_actions)
        next_state, rew, done, info = jax.vmap(env.step_env)(state, actions)
        obs = jax.vmap(env.get_obs)(next_state)
        expected = jax.vmap(_state_from_reference, in_axes=(0, None))(r_next, layout)
        same_state = jnp.all(
            jnp.stack(
                [
                    jnp.all(a.reshape(num_envs, -1) == b.reshape(num_envs, -1), axis=1)
                    for a, b in zip(jax.tree_util.tree_leaves(next_state), jax.tree_util.tree_leaves(expected))
                ]
            ),
            axis=0,
        )
        r_shaped = jnp.stack([r_info["shaped_reward"]["agent_0"], r_info["shaped_reward"]["agent_1"]], -1)
        checks = jnp.stack(
            [
                same_state,
                jnp.all(obs == jax.vmap(_ref_obs)(r_obs), axis=(1, 2, 3, 4)),
                jnp.all(rew == jnp.stack([r_rew["agent_0"], r_rew["agent_1"]], -1), axis=1),
                jnp.all(info["shaped_reward"] == r_shaped, axis=1),
                done == r_done["__all__"],
            ]
        )
        # Continue along JaxMARL's own trajectory (with its random auto-resets).
        _, ref_state, _, _, _ = jax.vmap(ref.step)(step_keys, ref_state, ref_actions)
        return ref_state, (checks, r_rew["agent_0"], r_shaped)

    step_keys = jax.random.split(jax.random.PRNGKey(5), num_steps)
    _, (checks, rewards, shaped) = jax.jit(lambda s: jax.lax.scan(one_transition, s, step_keys))(ref_state)
    checks = np.asarray(checks)
    for index, what in enumerate(["next state", "observation", "reward", "shaped reward", "done"]):
        assert checks[:, index].all(), f"{name}: {what} differs, {_first_mismatch(checks[:, index])}"
    shaped = np.asarray(shaped)
    assert (np.asarray(rewards) > 0).any(), "no delivery happened; the comparison tests too little"
    assert (shaped == 5).any() and (shaped == 3).any(), "soup or onion/plate shaping never paid"
