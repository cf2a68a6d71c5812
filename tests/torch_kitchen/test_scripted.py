import pytest
import torch
from tiny import infinite_observations

from jax_env import EXPANDED_LAYOUTS
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.scripted import SCRIPTED_COOK, UNREACHABLE, ScriptedCook, distance_to, scripted_actor_critic
from trainers.rollout import play_episodes


def test_distances_are_shortest_paths_to_a_cell_beside_a_target():
    walkable = torch.tensor([
        [1, 1, 1, 1],
        [1, 0, 0, 1],
        [1, 1, 0, 1],
        [0, 0, 0, 1],
    ], dtype=torch.bool)[None]  # fmt: skip
    targets = torch.zeros_like(walkable)
    targets[0, 3, 0] = True  # a tile in the bottom-left corner: beside it only (2, 0)
    expected = torch.tensor([
        [2, 3, 4, 5],
        [1, -1, -1, 6],
        [0, 1, -1, 7],
        [-1, -1, -1, 8],
    ], dtype=torch.float32)  # fmt: skip
    distance = distance_to(targets, walkable)[0]
    expected = torch.where(expected < 0, UNREACHABLE, expected)
    assert torch.equal(distance, expected)
    walled = walkable.clone()
    walled[0, 1, 0] = walled[0, 2, 1] = False  # the cell beside the tile is cut off from the rest
    distance = distance_to(targets, walled)[0]
    assert distance[2, 0] == 0 and distance[0, 0] == UNREACHABLE


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
