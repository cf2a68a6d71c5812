"""A game's partner keeps its memory between ticks (an LSTM team's state, an E3T team's partner context), and
games sharing a partner act in one forward pass."""

import torch

import torch_kitchen.partners.scripted_cook as scripted_cook
from jax_env import load_layout
from jax_env.render import AGENT_COLOURS
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.e3t_partner import CONTEXT_ACTION
from torch_kitchen.models.recurrence import recurrent_states
from torch_kitchen.records import read_record
from web_apps.play.game import ROUND_BATCH, SCRIPTED, Game, Partner, load_partner, replay, step_games
from web_apps.play.server import GameStepper, page_html

PERSON = [1, 2, 3, 4, 5, 0, 1, 2, 4, 4]  # the person's keys, seat 0


def play(tmp_path, architecture: str) -> tuple[Game, torch.nn.Module]:
    actor_critic = make_actor_critic(architecture, (7, 7, 26), 16, True)
    partner = Partner(architecture, actor_critic, (7, 7, 26))
    game = Game(load_layout("cramped_room_7x7"), partner, 0, tmp_path / "game.jsonl", seed=3, max_steps=30)
    for action in PERSON:
        game.step(action)
    return game, actor_critic


def test_an_lstm_partner_acts_from_the_state_carried_through_the_game(tmp_path):
    game, actor_critic = play(tmp_path, "mlp_lstm")
    carried = game.tensordict
    states = recurrent_states(actor_critic.actor)
    assert states and all(carried["agents", name][0, 1].abs().sum() > 0 for name in states)
    fresh = carried.clone()
    for name in states:
        fresh["agents", name].zero_()
    with torch.no_grad():
        assert not torch.allclose(actor_critic.actor(carried.clone())["agents", "logits"][0, 1],
                                  actor_critic.actor(fresh)["agents", "logits"][0, 1])
    game.end("disconnected")
    assert replay(tmp_path / "game.jsonl")["steps"] == len(PERSON)


def test_an_e3t_partner_reads_the_persons_last_actions_as_its_context(tmp_path):
    game, _ = play(tmp_path, "e3t_mlp")
    _, steps, _ = read_record(tmp_path / "game.jsonl")
    context = game.tensordict[CONTEXT_ACTION][0]  # [2, k]: agent i's context holds agent 1 - i's actions
    length = context.shape[-1]
    assert context[1].tolist() == PERSON[-length:]
    assert context[0].tolist() == [line["actions"][1] for line in steps][-length:]
    game.end("disconnected")
    assert replay(tmp_path / "game.jsonl")["steps"] == len(PERSON)


def test_the_page_colours_the_cooks_as_the_recorded_gifs_do():
    page = page_html("index.html")  # as served: the drawing script inlined
    colours = ", ".join('"#%02x%02x%02x"' % colour for colour in AGENT_COLOURS)
    assert f"const SEAT_COLOURS = [{colours}];" in page


def test_a_new_game_compiles_nothing_its_kitchen_steps_with_the_first_games_programs(tmp_path):
    """Games on kitchens of one size share one compiled reset and step, so starting a game never stalls the others
    with a compilation; each plays and records its own kitchen."""
    partner = Partner("random", make_actor_critic("mlp", (7, 7, 26), 8, True), (7, 7, 26))
    first = Game(load_layout("cramped_room_7x7"), partner, 0, tmp_path / "first.jsonl", max_steps=12)
    for _ in range(10):
        first.step(4)
    second = Game(load_layout("coord_ring_7x7"), partner, 1, tmp_path / "second.jsonl", max_steps=12)
    while not second.over:
        second.step(5)
    programs = first.kitchen._programs
    assert second.kitchen._programs is programs
    assert programs.step._cache_size() == 1 and programs.reset_all._cache_size() == 1
    assert replay(tmp_path / "second.jsonl")["steps"] == 12
    assert read_record(tmp_path / "second.jsonl")[0]["layout"] == load_layout("coord_ring_7x7").to_text()


def test_games_sharing_a_partner_act_in_one_forward_pass_each_row_as_it_would_alone(tmp_path):
    """`step_games` (the server's round of steps): one forward pass per partner and kitchen size, each game's row
    the logits and LSTM state its own tensordict gives alone; a game already over gets its error, the others
    step and record as they would one by one."""
    team = Partner("mlp_lstm", make_actor_critic("mlp_lstm", (7, 7, 26), 16, True), (7, 7, 26))
    cook = load_partner(SCRIPTED)
    layouts = ["cramped_room_7x7", "coord_ring_7x7", "cramped_room_7x7", "coord_ring_7x7"]
    games = [Game(load_layout(name), partner, 0, tmp_path / f"{index}.jsonl", seed=index, max_steps=6)
             for index, (name, partner) in enumerate(zip(layouts, [team, team, cook, team]))]
    over = Game(load_layout("cramped_room_7x7"), team, 0, tmp_path / "over.jsonl", max_steps=1)
    over.step(4)
    games[0].step(3)  # a tick ahead: its tensordict holds what a first tick's does not
    passes = []
    team.actor_critic.actor.register_forward_hook(lambda module, args, out: passes.append(out.clone()))
    states = recurrent_states(team.actor_critic.actor)
    for tick in range(3):
        alone = {index: team.actor_critic.actor(games[index].tensordict.clone()) for index in (0, 1, 3)}
        passes.clear()
        with torch.no_grad():
            views = step_games([*games, over], [tick, 5 - tick, 4, 1, 0])
        assert len(passes) == 1 and passes[0].batch_size == (ROUND_BATCH,)  # the team's three games, once
        for row, index in enumerate((0, 1, 3)):
            torch.testing.assert_close(passes[0]["agents", "logits"][row], alone[index]["agents", "logits"][0])
            for name in states:
                torch.testing.assert_close(games[index].tensordict["agents", name][0],
                                           alone[index]["next", "agents", name][0])
        assert isinstance(views[-1], RuntimeError)
        assert [view["t"] for view in views[:-1]] == [tick + 2, tick + 1, tick + 1, tick + 1]
    for index, game in enumerate(games):
        game.end("disconnected")
        _, steps, _ = read_record(tmp_path / f"{index}.jsonl")
        assert [line["actions"][0] for line in steps] == [[3, 0, 1, 2], [5, 4, 3], [4, 4, 4], [1, 1, 1]][index]
        assert replay(tmp_path / f"{index}.jsonl")["steps"] == len(steps)


def test_rounds_of_any_number_of_games_run_the_scripted_cook_as_it_was_compiled_for_the_first(tmp_path):
    """A round's games act in passes of one batch size, and the cook's floor plans are padded to one count: rounds
    of 1 to 11 games on two kitchens run the cook's program compiled for the first round, not one per size."""
    cook = load_partner(SCRIPTED)
    games = [Game(load_layout(name), cook, index % 2, tmp_path / f"{index}.jsonl", seed=index, max_steps=20)
             for index, name in enumerate(["cramped_room_7x7", "coord_ring_7x7"] * 6)]
    step_games(games[:1], [4])
    compiled = scripted_cook._COOK._cache_size()
    for count in (2, 3, 5, 8, 9, 11, 1):
        views = step_games(games[:count], [4] * count)
        assert all(isinstance(view, dict) for view in views)
    assert scripted_cook._COOK._cache_size() == compiled


class Settled:
    """What the stepping thread hands back to an event loop, in order (a stand-in for the loop)."""

    def __init__(self, log):
        self.log = log

    def call_soon_threadsafe(self, settle, future, result):
        self.log.append((future, result))


def test_the_stepping_thread_takes_every_waiting_step_as_one_round_each_caller_its_own_result(tmp_path):
    stepper, handed = GameStepper(), []
    loop = Settled(handed)
    cook = load_partner(SCRIPTED)
    games = [Game(load_layout("cramped_room_7x7"), cook, 0, tmp_path / f"{index}.jsonl", max_steps=5, seed=index)
             for index in range(3)]
    games[2].end("disconnected")  # over: its caller gets the error, the others step
    for index, game in enumerate(games):
        stepper.requests.put((game, 4, loop, f"game {index}"))
    stepper.take_round()
    assert [future for future, _ in handed] == ["game 0", "game 1", "game 2"]
    assert handed[0][1]["t"] == handed[1][1]["t"] == 1 and isinstance(handed[2][1], RuntimeError)
    assert stepper.requests.empty()
