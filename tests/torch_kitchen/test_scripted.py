import pytest
import torch
from tiny import infinite_observations

from jax_env import EXPANDED_LAYOUTS
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.scripted_cook import (
    SCRIPTED_COOK,
    UNREACHABLE,
    FloorDistances,
    ScriptedCook,
    distance_from,
    scripted_actor_critic,
)
from trainers.ppo.collection import play_episodes


def test_floor_tables_hold_the_shortest_paths_between_every_two_cells_once_per_floor_plan():
    walkable = torch.tensor([
        [1, 1, 1, 1],
        [1, 0, 0, 1],
        [1, 1, 0, 1],
        [0, 0, 0, 1],
    ], dtype=torch.bool)[None]  # fmt: skip
    start = torch.zeros_like(walkable)
    start[0, 2, 0] = True
    expected = torch.tensor([
        [2, 3, 4, 5],
        [1, -1, -1, 6],
        [0, 1, -1, 7],
        [-1, -1, -1, 8],
    ], dtype=torch.float32)  # fmt: skip
    expected = torch.where(expected < 0, UNREACHABLE, expected)
    assert torch.equal(distance_from(start, walkable)[0], expected)
    walled = walkable.clone()
    walled[0, 1, 0] = walled[0, 2, 1] = False  # (2, 0) is cut off from the rest
    floor = FloorDistances()
    tables, plan = floor(torch.cat([walkable, walled, walkable]))
    assert tables.shape == (2, 16, 16) and plan[0] == plan[2] != plan[1]  # two plans, each computed once
    cell = 2 * 4 + 0  # the start's row of a table
    assert torch.equal(tables[plan[0], cell].view(4, 4), expected)
    cut_off = tables[plan[1], cell].view(4, 4)
    assert cut_off[2, 0] == 0 and (cut_off.flatten().sort().values[1:] == UNREACHABLE).all()
    every_cell = torch.eye(16, dtype=torch.bool).view(16, 4, 4)
    assert torch.equal(tables[plan[0]], distance_from(every_cell, walkable.expand(16, -1, -1)).flatten(1))


def _episodes(levels, num_envs=4, seed=0):
    env = KitchenEnv(num_envs, levels=levels, max_steps=256, seed=seed, pin_levels=not isinstance(levels, str))
    torch.manual_seed(seed)
    with torch.no_grad():
        return play_episodes(env, scripted_actor_critic().actor, 256).deliveries


def test_two_scripted_cooks_deliver_on_every_expanded_layout():
    """forced_coord_7x7 needs hand-overs across the counter: neither cook reaches both the onions and the pots."""
    deliveries = _episodes(list(EXPANDED_LAYOUTS), num_envs=4 * len(EXPANDED_LAYOUTS))  # kitchen b: layout b % 5
    per_layout = deliveries.view(4, len(EXPANDED_LAYOUTS)).sum(0)
    assert (per_layout >= 2).all(), dict(zip(EXPANDED_LAYOUTS, per_layout.tolist()))


def test_the_scripted_cook_plans_its_way_on_generated_levels():
    assert _episodes("heldout", num_envs=10).mean() >= 3


def test_each_seat_gets_its_plan_a_coin_flip_or_any_action_and_it_builds_like_a_trained_team():
    env = KitchenEnv(8, levels="infinite", max_steps=64, seed=3)
    cook = ScriptedCook()
    td = env.reset()
    choices = []
    for _ in range(64):
        logits = cook(td["agents", "observation"])
        assert logits.shape == (8, 2, 6)
        choices.append((logits == 0).sum(-1))
        td["agents", "action"] = torch.distributions.Categorical(logits=logits).sample()
        td = env.step(td)["next"]
    choices = torch.stack(choices)
    assert set(choices.unique().tolist()) <= {1, 2, 6}  # planned, step-or-wait, stuck
    assert (choices == 1).float().mean() > 0.5
    ac = make_actor_critic(SCRIPTED_COOK, (7, 7, 26))
    assert not list(ac.actor.parameters()) and ac.acting is None


def test_cooks_with_another_move_order_take_other_equally_short_ways_and_plan_alike_otherwise():
    observation = infinite_observations(64, seed=0)  # test_sparse_linear's: made once per process
    planned = {order: ScriptedCook(order)(observation) for order in ("NSEW", "EWSN")}
    assert torch.equal(planned["NSEW"], ScriptedCook()(observation))
    certain = (planned["NSEW"] == 0).sum(-1).eq(1) & (planned["EWSN"] == 0).sum(-1).eq(1)
    first, second = planned["NSEW"].argmax(-1)[certain], planned["EWSN"].argmax(-1)[certain]
    differ = first != second
    assert differ.any() and (first[differ] < 4).all() and (second[differ] < 4).all()  # only the moves differ
    # Both ways are equally short, so each cook took the one that comes first in its own order.
    rank = torch.tensor(["EWSN".index(direction) for direction in "NSEW"])
    assert (first[differ] < second[differ]).all() and (rank[second[differ]] < rank[first[differ]]).all()
    with pytest.raises(ValueError, match="move_order must be a permutation of 'NSEW', got 'NNEW'"):
        ScriptedCook("NNEW")
