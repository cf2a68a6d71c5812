"""Hand-made scenarios for each rule of the step: interactions, shaping, movement conflicts, cooking, urgency,
and the auto-reset step."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax_env import (
    DISH,
    EAST,
    EMPTY,
    INTERACT,
    NORTH,
    ONION,
    PLATE,
    POT_EMPTY,
    SOUTH,
    STAY,
    WEST,
    Overcooked,
    make_state,
    parse_layout,
)

# Pot (3,0) on the border, a pot (3,3) in the middle reachable from (2,3) and (4,3),
# onion pile (0,1), plate pile (6,2), goal (0,4), plain counters elsewhere.
KITCHEN = parse_layout(
    "WWWPWWW\n"
    "OA    W\n"
    "W     B\n"
    "W  P  W\n"
    "X     W\n"
    "W    AW\n"
    "WWWWWWW",
    name="scenario",
)
ENV = Overcooked(KITCHEN, max_steps=400)
STEP = jax.jit(ENV.step_env)


def act(state, a0, a1=STAY):
    next_state, reward, done, info = STEP(state, jnp.asarray([a0, a1], dtype=jnp.int32))
    return next_state, np.asarray(reward), bool(done), np.asarray(info["shaped_reward"])


def xy(state, agent):
    return tuple(int(v) for v in np.asarray(state.agent_xy())[agent])


def contents_at(state, x, y):
    return int(state.contents[y, x])


def scenario(**kwargs):
    kwargs.setdefault("agent_pos", [(1, 1), (5, 5)])
    return make_state(KITCHEN, **kwargs)


# ---------------------------------------------------------------------------------------------- interactions
def test_take_onion_from_pile_and_pile_stays():
    state, reward, _, shaped = act(scenario(agent_dir=(WEST, NORTH)), INTERACT)
    assert int(state.agent_inv[0]) == ONION and int(state.grid[1, 0]) == 2
    assert reward.tolist() == [0, 0] and shaped.tolist() == [0, 0]


def test_pile_ignores_a_full_hand():
    state, *_ = act(scenario(agent_dir=(WEST, NORTH), agent_inv=(PLATE, EMPTY)), INTERACT)
    assert int(state.agent_inv[0]) == PLATE


@pytest.mark.parametrize("item", [ONION, PLATE, DISH])
def test_put_down_on_empty_counter_then_pick_up(item):
    start = scenario(agent_pos=[(1, 2), (5, 5)], agent_dir=(WEST, NORTH), agent_inv=(item, EMPTY))
    dropped, *_ = act(start, INTERACT)
    assert contents_at(dropped, 0, 2) == item and int(dropped.agent_inv[0]) == EMPTY
    picked, *_ = act(dropped, INTERACT)
    assert contents_at(picked, 0, 2) == EMPTY and int(picked.agent_inv[0]) == item


def test_occupied_counter_and_full_hand_do_nothing():
    start = scenario(
        agent_pos=[(1, 2), (5, 5)], agent_dir=(WEST, NORTH), agent_inv=(ONION, EMPTY), counter_items={(0, 2): PLATE}
    )
    state, *_ = act(start, INTERACT)
    assert contents_at(state, 0, 2) == PLATE and int(state.agent_inv[0]) == ONION


def test_onions_fill_the_pot_and_the_third_starts_cooking():
    start = scenario(agent_pos=[(3, 1), (5, 5)], agent_dir=(NORTH, NORTH), agent_inv=(ONION, EMPTY))
    state, _, _, shaped = act(start, INTERACT)
    assert contents_at(state, 3, 0) == 22 and int(state.agent_inv[0]) == EMPTY and shaped.tolist() == [3, 0]
    third = state.replace(agent_inv=jnp.asarray([ONION, EMPTY], jnp.int32), contents=state.contents.at[0, 3].set(21))
    state, _, _, shaped = act(third, INTERACT)
    assert contents_at(state, 3, 0) == 19, "20 on the third onion, then the same step's tick"
    assert shaped.tolist() == [3, 0]


@pytest.mark.parametrize("status", [20, 12, 0])
def test_full_cooking_or_ready_pot_refuses_onions(status):
    start = scenario(
        agent_pos=[(3, 1), (5, 5)], agent_dir=(NORTH, NORTH), agent_inv=(ONION, EMPTY), pot_status={(3, 0): status}
    )
    state, _, _, shaped = act(start, INTERACT)
    assert int(state.agent_inv[0]) == ONION and shaped.tolist() == [0, 0]


def test_ready_soup_goes_onto_a_plate():
    start = scenario(
        agent_pos=[(3, 1), (5, 5)], agent_dir=(NORTH, NORTH), agent_inv=(PLATE, EMPTY), pot_status={(3, 0): 0}
    )
    state, _, _, shaped = act(start, INTERACT)
    assert int(state.agent_inv[0]) == DISH and contents_at(state, 3, 0) == POT_EMPTY and shaped.tolist() == [5, 0]


@pytest.mark.parametrize("held, status", [(EMPTY, 0), (PLATE, 5), (PLATE, POT_EMPTY), (PLATE, 21)])
def test_pot_does_nothing_otherwise(held, status):
    start = scenario(
        agent_pos=[(3, 1), (5, 5)], agent_dir=(NORTH, NORTH), agent_inv=(held, EMPTY), pot_status={(3, 0): status}
    )
    state, *_ = act(start, INTERACT)
    assert int(state.agent_inv[0]) == held
    assert contents_at(state, 3, 0) == (status - 1 if 1 <= status <= 20 else status)


def test_delivery_pays_both_agents_sparse_reward():
    start = scenario(agent_pos=[(1, 4), (5, 5)], agent_dir=(WEST, NORTH), agent_inv=(DISH, EMPTY))
    state, reward, _, shaped = act(start, INTERACT)
    assert reward.tolist() == [20, 20] and int(state.agent_inv[0]) == EMPTY and shaped.tolist() == [0, 0]
    refused, reward, *_ = act(start.replace(agent_inv=jnp.asarray([ONION, EMPTY], jnp.int32)), INTERACT)
    assert reward.tolist() == [0, 0] and int(refused.agent_inv[0]) == ONION


def test_two_deliveries_in_one_step_add_up():
    kitchen = parse_layout("WWWPWWW\nO     W\nX A A X\nW     B\nWWWWWWW")
    start = make_state(kitchen, agent_pos=[(1, 2), (5, 2)], agent_dir=(WEST, EAST), agent_inv=(DISH, DISH))
    _, reward, _, _ = Overcooked(kitchen).step_env(start, jnp.asarray([INTERACT, INTERACT]))
    assert np.asarray(reward).tolist() == [40, 40]


def test_plate_shaping_only_when_useful():
    at_pile = dict(agent_pos=[(5, 2), (1, 1)], agent_dir=(EAST, NORTH))
    # No pot has started: the plate is not useful.
    _, _, _, shaped = act(scenario(**at_pile), INTERACT)
    assert shaped.tolist() == [0, 0]
    # A pot with onions and nobody holding a plate: useful.
    _, _, _, shaped = act(scenario(**at_pile, pot_status={(3, 0): 21}), INTERACT)
    assert shaped.tolist() == [3, 0]
    # A plate already lies on a counter: not useful.
    _, _, _, shaped = act(scenario(**at_pile, pot_status={(3, 0): 21}, counter_items={(6, 4): PLATE}), INTERACT)
    assert shaped.tolist() == [0, 0]
    # The partner already holds a plate for the only busy pot: not useful.
    _, _, _, shaped = act(scenario(**at_pile, pot_status={(3, 0): 21}, agent_inv=(EMPTY, PLATE)), INTERACT)
    assert shaped.tolist() == [0, 0]
    # Two busy pots, one plate held: the second plate is useful.
    two_busy = scenario(**at_pile, pot_status={(3, 0): 21, (3, 3): 5}, agent_inv=(EMPTY, PLATE))
    _, _, _, shaped = act(two_busy, INTERACT)
    assert shaped.tolist() == [3, 0]


def test_plate_from_a_counter_never_pays():
    start = scenario(
        agent_pos=[(1, 2), (5, 5)], agent_dir=(WEST, NORTH), pot_status={(3, 0): 10}, counter_items={(0, 2): PLATE}
    )
    state, _, _, shaped = act(start, INTERACT)
    assert int(state.agent_inv[0]) == PLATE and shaped.tolist() == [0, 0]


def test_agent_one_acts_on_the_world_agent_zero_left():
    # Both bring the third onion to the middle pot: only agent 0's goes in.
    start = scenario(
        agent_pos=[(2, 3), (4, 3)], agent_dir=(EAST, WEST), agent_inv=(ONION, ONION), pot_status={(3, 3): 21}
    )
    state, _, _, shaped = act(start, INTERACT, INTERACT)
    assert int(state.agent_inv[0]) == EMPTY and int(state.agent_inv[1]) == ONION
    assert contents_at(state, 3, 3) == 19 and shaped.tolist() == [3, 0]
    # Agent 0 takes the soup; agent 1's plate then meets an empty pot.
    start = scenario(
        agent_pos=[(2, 3), (4, 3)], agent_dir=(EAST, WEST), agent_inv=(PLATE, PLATE), pot_status={(3, 3): 0}
    )
    state, _, _, shaped = act(start, INTERACT, INTERACT)
    assert state.agent_inv.tolist() == [DISH, PLATE] and shaped.tolist() == [5, 0]


def test_interacting_with_floor_or_a_partner_does_nothing():
    start = scenario(agent_pos=[(2, 2), (3, 2)], agent_dir=(EAST, SOUTH), agent_inv=(ONION, PLATE))
    state, *_ = act(start, INTERACT, INTERACT)
    assert state.agent_inv.tolist() == [ONION, PLATE] and np.array_equal(state.contents, start.contents)


# ---------------------------------------------------------------------------------------------- movement
def test_move_into_a_counter_is_refused_but_turns():
    state, *_ = act(scenario(agent_dir=(EAST, NORTH)), NORTH)
    assert xy(state, 0) == (1, 1) and int(state.agent_dir[0]) == NORTH


def test_stay_and_interact_never_turn():
    for action in (STAY, INTERACT):
        state, *_ = act(scenario(agent_pos=[(2, 2), (5, 5)], agent_dir=(SOUTH, NORTH)), action)
        assert int(state.agent_dir[0]) == SOUTH and xy(state, 0) == (2, 2)


def test_moves_into_the_same_cell_both_stay():
    state, *_ = act(scenario(agent_pos=[(2, 2), (4, 2)], agent_dir=(NORTH, NORTH)), EAST, WEST)
    assert (xy(state, 0), xy(state, 1)) == ((2, 2), (4, 2))
    assert state.agent_dir.tolist() == [EAST, WEST]


def test_walking_into_a_standing_agent_both_stay():
    state, *_ = act(scenario(agent_pos=[(2, 2), (3, 2)]), EAST, STAY)
    assert (xy(state, 0), xy(state, 1)) == ((2, 2), (3, 2))


def test_swapping_cells_is_refused():
    state, *_ = act(scenario(agent_pos=[(2, 2), (3, 2)]), EAST, WEST)
    assert (xy(state, 0), xy(state, 1)) == ((2, 2), (3, 2))


def test_following_into_a_vacated_cell_is_allowed():
    state, *_ = act(scenario(agent_pos=[(2, 2), (3, 2)]), EAST, EAST)
    assert (xy(state, 0), xy(state, 1)) == ((3, 2), (4, 2))


def test_interactions_use_the_facing_from_before_the_step():
    # Agent 0 faces the onion pile; this step it interacts while agent 1 walks next to it.
    start = scenario(agent_pos=[(1, 1), (2, 2)], agent_dir=(WEST, NORTH))
    state, *_ = act(start, INTERACT, NORTH)
    assert int(state.agent_inv[0]) == ONION and xy(state, 1) == (2, 1)


# ---------------------------------------------------------------------------------------------- time
def test_soup_is_ready_nineteen_steps_after_the_third_onion():
    start = scenario(
        agent_pos=[(3, 1), (5, 5)], agent_dir=(NORTH, NORTH), agent_inv=(ONION, EMPTY), pot_status={(3, 0): 21}
    )
    state, *_ = act(start, INTERACT)
    statuses = [contents_at(state, 3, 0)]
    for _ in range(20):
        state, *_ = act(state, STAY)
        statuses.append(contents_at(state, 3, 0))
    assert statuses == list(range(19, -1, -1)) + [0]


def test_urgency_layer_turns_on_in_the_last_forty_steps():
    env = Overcooked(KITCHEN, max_steps=100)
    for step, urgent in [(0, 0), (60, 0), (61, 1), (99, 1)]:
        obs = np.asarray(env.get_obs(scenario(step=step)))
        assert (obs[..., 25] == urgent).all(), step


def test_done_after_max_steps_and_auto_reset_returns_the_new_episode():
    env = Overcooked(KITCHEN, max_steps=3)
    start = scenario(agent_pos=[(1, 4), (5, 5)], agent_dir=(WEST, NORTH), agent_inv=(DISH, EMPTY), step=2)
    key = jax.random.PRNGKey(4)
    obs, state, reward, done, _ = jax.jit(env.step)(key, start, jnp.asarray([INTERACT, STAY]))
    assert bool(done) and np.asarray(reward).tolist() == [20, 20], "the terminal step keeps its reward"
    _, fresh = env.reset(jax.random.split(key)[1])
    for new, expected in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(fresh)):
        np.testing.assert_array_equal(new, expected)
    np.testing.assert_array_equal(obs, env.get_obs(fresh))
    assert int(state.step) == 0 and xy(state, 0) == (1, 1)

    _, not_yet, _, done, _ = env.step(key, start.replace(step=jnp.asarray(1)), jnp.asarray([STAY, STAY]))
    assert not bool(done) and int(not_yet.step) == 2


def test_reset_facings_are_uniform_and_positions_fixed():
    env = Overcooked("cramped_room")
    _, states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 4000))
    counts = np.bincount(np.asarray(states.agent_dir).ravel(), minlength=4) / 8000
    assert np.allclose(counts, 0.25, atol=0.03)
    assert (np.asarray(states.agent_pos) == [6, 8]).all()


def test_observation_channels_of_a_busy_kitchen():
    state = scenario(
        agent_pos=[(2, 2), (4, 4)],
        agent_dir=(EAST, SOUTH),
        agent_inv=(DISH, ONION),
        pot_status={(3, 0): 22, (3, 3): 7},
        counter_items={(6, 4): PLATE},
    )
    obs = np.asarray(ENV.get_obs(state))
    me, other = obs[0], obs[1]
    assert me[2, 2, 0] == 1 and me[4, 4, 1] == 1 and other[4, 4, 0] == 1 and other[2, 2, 1] == 1
    assert me[2, 2, 2 + EAST] == 1 and me[4, 4, 6 + SOUTH] == 1 and other[4, 4, 2 + SOUTH] == 1
    assert me[0, 3, 16] == 1 and me[3, 3, 16] == 0 and me[3, 3, 18] == 3 and me[3, 3, 20] == 7
    assert me[2, 2, 18] == 3 and me[2, 2, 21] == 1 and me[4, 4, 23] == 1 and me[4, 6, 22] == 1
    assert me[4, 6, 11] == 0 and me[5, 6, 11] == 1 and me[1, 0, 12] == 1 and me[2, 6, 14] == 1 and me[4, 0, 15] == 1
    np.testing.assert_array_equal(me[..., 10:], other[..., 10:])
    assert obs.dtype == np.uint8 and obs.shape == (2, 7, 7, 26)


def test_make_state_refuses_impossible_scenarios():
    with pytest.raises(ValueError, match="not on a floor cell"):
        make_state(KITCHEN, agent_pos=[(0, 0), (2, 2)])
    with pytest.raises(ValueError, match="not a pot"):
        make_state(KITCHEN, pot_status={(1, 1): 3})
    with pytest.raises(ValueError, match="not a plain counter"):
        make_state(KITCHEN, counter_items={(3, 0): ONION})
    with pytest.raises(ValueError, match="distinct"):
        make_state(KITCHEN, agent_pos=[(2, 2), (2, 2)])
