import dataclasses
import random
from pathlib import Path

import pytest
import torch

from jax_env import STAY, Channel
from jax_env.layouts import parse_layout
from torch_kitchen.env import KitchenEnv
from torch_kitchen.events import EVENTS, kitchen_events
from torch_kitchen.partners.conventions import (
    ROLES,
    SPLITS,
    STRANGER,
    ZOO_FILE,
    Convention,
    ConventionError,
    draw_convention,
    load_zoo,
)
from torch_kitchen.partners.scripted_cook import ScriptedCook
from trainers.zoo import stranger_by_content

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


def _planned(convention: Convention, observation: torch.Tensor, seat: int = 0) -> int:
    logits = ScriptedCook(convention)(observation)[0, seat]
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


def test_a_split_by_side_plays_each_seat_the_role_of_its_place_and_a_strict_one_keeps_to_it():
    kitchen = _kitchen(cooking_pot=True)  # the cooks share a column: cook 0, the northern, is the first
    loader, server = Convention(name="l", role="loader"), Convention(name="s", role="server")
    assert _planned(loader, kitchen) != _planned(server, kitchen)
    swapped = kitchen[:, [1, 0]]  # the seats' views swapped: seat 0 sees as the southern cook, the second
    for split, first, second in [("west_loads", loader, server), ("west_serves", server, loader)]:
        by_side = ScriptedCook(Convention(name=split, role=split))
        for view, roles in [(kitchen, (first, second)), (swapped, (second, first))]:
            assert torch.equal(by_side(view), torch.stack([ScriptedCook(role)(view)[:, seat] for seat, role in
                                                           enumerate(roles)], 1))
    # With no pot cooking no plate is wanted: a server fills pots meanwhile, a strict one fetches a plate for later.
    idle_kitchen = _kitchen(cooking_pot=False)
    first_serves = Convention(name="first_serves", role="west_serves")
    assert _planned(first_serves, idle_kitchen) == WEST
    assert _planned(dataclasses.replace(first_serves, strict_role=True), idle_kitchen) == EAST


def test_a_split_by_seat_plays_seat_0_its_role_wherever_the_cooks_stand():
    kitchen = _kitchen(cooking_pot=True)
    loader, server = Convention(name="l", role="loader"), Convention(name="s", role="server")
    swapped = kitchen[:, [1, 0]]  # seat 0 now stands where seat 1 stood: a split by side would swap the roles
    for split, roles in [("seat0_loads", (loader, server)), ("seat0_serves", (server, loader))]:
        by_seat = ScriptedCook(Convention(name=split, role=split))
        for view in (kitchen, swapped):
            assert torch.equal(by_seat(view), torch.stack([ScriptedCook(role)(view)[:, seat] for seat, role in
                                                           enumerate(roles)], 1))


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
    assert {c.role for c in drawn} == set(ROLES) and len({c.move_order for c in drawn}) > 5
    assert any(c.strict_role for c in drawn) and all(c.role in SPLITS for c in drawn if c.strict_role)
    assert Convention.from_dict(first[0].as_dict()) == first[0]


def test_the_shipped_zoo_is_drawn_again_with_the_roles_of_its_command_and_keeps_its_fingerprints():
    zoo = load_zoo(ZOO_FILE)
    command = Path(ZOO_FILE).with_suffix(".md").read_text().split("`")[1]  # the draw's command line, as zoo.md gives it
    roles = tuple(command.split("--roles ")[1].split(" --")[0].split())
    rng = random.Random(zoo.seed)
    drawn = [draw_convention(rng, f"cook_{zoo.seed}_{i:03d}", roles) for i in range(zoo.drawn)]
    by_name = {convention.name: convention for convention in drawn}
    assert all(by_name[member.name] == member.convention for member in zoo.members)
    # The knobs added since count in a fingerprint only where set, so the split by content still holds.
    assert all(stranger_by_content(member.convention) == (member.split == STRANGER) for member in zoo.members)


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
