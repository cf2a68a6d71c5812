import random

import pytest
import torch

from jax_env import STAY, Channel
from jax_env.layouts import parse_layout
from torch_kitchen.env import KitchenEnv
from torch_kitchen.events import EVENTS, kitchen_events
from torch_kitchen.partners.conventions import Convention, ConventionError, draw_convention
from torch_kitchen.partners.scripted_cook import ScriptedCook

# Two pots at the top, onions on the left, plates on the right of cook 0's row; cook 1 below it.
TWO_POTS = """
WWPWPWW
W     W
O  A  B
W     W
W  A  W
W     W
WWWXWWW
"""
NORTH, SOUTH, EAST, WEST = range(4)


def _kitchen(cooking_pot: bool) -> torch.Tensor:
    """uint8 [1, 2, 7, 7, 26]: both cooks empty-handed at the start; with `cooking_pot` the left pot cooks."""
    env = KitchenEnv(1, levels=[parse_layout(TWO_POTS, "two_pots")], max_steps=32, seed=0, pin_levels=True)
    observation = env.reset()["agents", "observation"].clone()
    if cooking_pot:
        observation[..., 0, 2, Channel.COOKING_OR_SOUP] = 3
        observation[..., 0, 2, Channel.COOK_TIME] = 12
    return observation


def _planned(convention: Convention, observation: torch.Tensor) -> int:
    logits = ScriptedCook(convention)(observation)[0, 0]
    assert (logits == 0).sum() == 1, logits  # a certain plan
    return int(logits.argmax())


def test_a_loader_fills_the_open_pot_where_the_scripted_cook_fetches_a_plate_for_the_cooking_one():
    kitchen = _kitchen(cooking_pot=True)
    assert _planned(Convention(), kitchen) == EAST  # towards the plates: a pot cooks and nobody holds a plate
    assert _planned(Convention(name="loader", role="loader"), kitchen) == WEST  # towards the onions
    # With no pot cooking there is no plate to fetch: the loader's role changes nothing.
    idle_kitchen = _kitchen(cooking_pot=False)
    assert _planned(Convention(name="loader", role="loader"), idle_kitchen) == _planned(Convention(), idle_kitchen)


def test_a_server_fetches_the_plate_whatever_it_prefers_and_preferences_reorder_the_goals():
    kitchen = _kitchen(cooking_pot=True)
    onion_lover = Convention(name="onions", preferences={"onion_pickup": 1.0})
    assert _planned(onion_lover, kitchen) == WEST  # its preference lifts the onions above the wanted plate
    server = Convention(name="server", role="server", preferences={"onion_pickup": 1.0})
    assert _planned(server, kitchen) == EAST  # its role keeps it on the plate while one is wanted
    idler = Convention(name="idler", preferences={"idle": 1.0})
    assert _planned(idler, kitchen) == STAY


def test_temperatures_and_noise_spread_the_actions_and_the_default_is_the_scripted_cook():
    kitchen = _kitchen(cooking_pot=True)
    assert torch.equal(ScriptedCook(Convention())(kitchen), ScriptedCook()(kitchen))
    assert torch.equal(ScriptedCook(Convention(move_order="EWSN"))(kitchen), ScriptedCook("EWSN")(kitchen))
    probs = ScriptedCook(Convention(name="hot", goal_temperature=1.0))(kitchen)[0, 0].softmax(-1)
    assert probs[EAST] > probs[WEST] > 0.05  # plate first, onions likely too
    noisy = ScriptedCook(Convention(name="noisy", noise=0.3))(kitchen)[0, 0].softmax(-1)
    assert noisy[EAST] == pytest.approx(0.7 + 0.05) and noisy.min() == pytest.approx(0.05)


def test_conventions_refuse_unknown_names_in_one_line_and_draws_are_deterministic():
    for bad, words in [({"preferences": {"dance": 1.0}}, "unknown event 'dance'; events: onion_pickup"),
                       ({"role": "chef"}, "unknown role 'chef'; roles: both, loader, server"),
                       ({"preferences": {"serve": 3}}, "lie in [-1, 1]"),
                       ({"colour": "red"}, "unknown key 'colour'")]:
        with pytest.raises(ConventionError, match="^convention 'c'") as error:
            Convention.from_dict({"name": "c", **bad})
        assert words in str(error.value) and "\n" not in str(error.value)
    first = [draw_convention(random.Random(3), f"c{i}") for i in range(5)]
    assert first == [draw_convention(random.Random(3), f"c{i}") for i in range(5)]
    drawn = [draw_convention(random.Random(seed), "c") for seed in range(40)]
    assert all(1 <= sum(w != 0 for w in c.preferences.values()) <= 3 for c in drawn)
    assert {c.role for c in drawn} == {"both", "loader", "server"} and len({c.move_order for c in drawn}) > 5
    assert Convention.from_dict(first[0].as_dict()) == first[0]


def test_events_are_read_off_the_observations_before_and_after_a_step():
    env = KitchenEnv(1, levels=[parse_layout(TWO_POTS, "two_pots")], max_steps=32, seed=0, pin_levels=True)
    td = env.reset()
    # Cook 0 walks to the onion pile and takes an onion, then under the left pot and puts it in.
    plan = [WEST, WEST, WEST, 5, NORTH, EAST, NORTH, 5]
    counts = torch.zeros(len(EVENTS))
    for action in plan:
        td["agents", "action"] = torch.tensor([[action, STAY]])
        stepped = env.step(td)
        counts += kitchen_events(td["agents", "observation"], td["agents", "action"],
                                 stepped["next", "agents", "observation"])[0].sum(0)
        td = stepped["next"]
    held = dict(zip(EVENTS, counts.tolist()))
    assert held["onion_pickup"] == 1 and held["onion_in_pot"] == 1 and held["idle"] == len(plan)  # cook 1 stays
    assert held["plate_pickup"] == held["serve"] == held["counter_place"] == 0
