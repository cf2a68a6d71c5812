"""kitchen-study simulate: a pilot by proxies through the study's real server, then its report; the observation a
state message gives, the response model, and a real-time game that never waits for a plan."""

import csv
import json
import random
import sqlite3
import tempfile
import threading
import time
from pathlib import Path

import pytest
import torch
import yaml

pytest.importorskip("fastapi", reason="kitchen-study needs the play extra: pip install .[play]")
from tiny_study import study_config, tiny_team  # noqa: E402

from torch_kitchen.keys import OBSERVATION  # noqa: E402
from torch_kitchen.partners.conventions import Convention  # noqa: E402
from web_apps.play.game import SCRIPTED, Game, load_partner  # noqa: E402
from web_apps.study.client import Socket  # noqa: E402
from web_apps.study.command import main  # noqa: E402
from web_apps.study.config import kitchen_of, load_study  # noqa: E402
from web_apps.study.simulate import (  # noqa: E402
    CHOICE_P,
    PROXIES,
    Draw,
    ProxyParticipant,
    forced_choice_answer,
    likert_answer,
    observation_of,
    play_in_time,
    reference_of,
)


def test_a_state_message_gives_the_observation_the_env_gives():
    with tempfile.TemporaryDirectory() as folder:
        # 44 steps: the urgency layer (the last 40) switches on along the way
        game = Game(kitchen_of("coord_ring_7x7", 0), load_partner(SCRIPTED), 1, Path(folder) / "game.jsonl", seed=5,
                    max_steps=44)
        keys = random.Random(0)
        while not game.over:
            assert torch.equal(observation_of(game.view()), game.tensordict[OBSERVATION]), game.t
            game.step(keys.randrange(6))


def test_the_response_model_rises_with_deliveries_and_picks_the_better_game_mostly():
    rng = random.Random(0)
    for points in (3, 5, 7):
        means = [sum(likert_answer(4 + above, 4.0, 0.0, points, rng) for _ in range(2000)) / 2000
                 for above in (-3, 0, 3)]
        assert means[0] < means[1] < means[2], (points, means)
        assert abs(means[1] - (points + 1) / 2) < 0.15  # no leaning, used to it: the middle
    assert {likert_answer(d, 0.0, 2.0, 5, rng) for d in range(20)} <= set(range(1, 6))  # clipped to the scale
    assert sum(likert_answer(4, 4.0, 0.5, 5, rng) for _ in range(2000)) > 2000 * 3.5  # a leaning lifts every answer
    picks = [forced_choice_answer(1, 3, [2, 3], rng) for _ in range(4000)]
    assert abs(picks.count(3) / 4000 - CHOICE_P) < 0.03
    ties = [forced_choice_answer(2, 2, [2, 3], rng) for _ in range(4000)]
    assert abs(ties.count(3) / 4000 - 0.5) < 0.03
    # what a participant is used to: its earlier games' deliveries per step, at this game's length
    assert reference_of([(2, 200)], 7, 400) == 4.0 and reference_of([(2, 200), (8, 400)], 0, 300) == 5.0
    assert reference_of([], 3, 400) == 3.0


def test_a_participant_answers_from_the_game_just_played_against_its_earlier_ones():
    better_after_first, first_chosen, draws = 0, 0, 300
    for index in range(draws):
        person = ProxyParticipant(None, "token", Draw(index, 0.0, 0.0, Convention(), index), None)
        # a practice of 2 soups in 200 steps, then 6 and 2 soups in games of 400 steps
        person.played = [("practice", 2, 200), ("game", 6, 400), ("game", 2, 400)]
        likert = {"helpful": [1, 2, 3, 4, 5], "predictable": [1, 2, 3, 4, 5]}
        first = person.answers({"position": 0, "asks": likert})
        second = person.answers({"position": 1, "asks": {**likert, "forced_choice": [0, 1]}})
        better_after_first += sum(first.values()) > sum(v for k, v in second.items() if k != "forced_choice")
        first_chosen += second["forced_choice"] == 0
    assert better_after_first > draws * 0.7  # 6 soups where it is used to 4, then 2 where it is used to 5.3
    assert abs(first_chosen / draws - CHOICE_P) < 0.08


class TickingSocket:
    """A real-time game's socket: a state every `tick` seconds whatever the player sends; each key sent is kept with
    the index of the latest state at that time."""

    def __init__(self, states: int, tick: float):
        self.states = [{"type": "state", "t": t, "over": t == states - 1} for t in range(states)]
        self.tick, self.latest, self.sent = tick, 0, []

    def receive(self) -> dict:
        time.sleep(self.tick)
        self.latest += 1
        return self.states[self.latest]

    def send(self, text: str) -> None:
        self.sent.append((self.latest, json.loads(text)["action"]))


def test_a_real_time_game_gets_a_key_on_every_tick_while_a_plan_slower_than_a_tick_runs():
    socket, planned, tick = TickingSocket(30, 0.02), [], 0.02

    def slow_plan(view: dict) -> str:  # four ticks per plan
        time.sleep(4 * tick)
        key = ("up", "down", "left", "right")[view["t"] % 4]
        planned.append((threading.current_thread().name, key))
        return key

    last = play_in_time(Socket(socket.send, socket.receive, lambda: None), socket.states[0], slow_plan)
    assert last["over"] and last["t"] == 29
    assert {latest for latest, _ in socket.sent} >= set(range(29))  # every state answered while it was the latest
    assert 2 <= len(planned) < 15  # plans on some of the states only, none on this thread
    assert all(name != threading.current_thread().name for name, _ in planned)
    keys = [key for _, key in socket.sent]
    assert set(keys) <= {"stay"} | {key for _, key in planned}  # the last key planned until the next plan is done
    assert keys.count("stay") >= 2  # the first state's plan took more than a tick: the last key stood in


def test_simulate_runs_proxies_through_the_server_into_a_study_that_analyse_reads(tmp_path, capsys):
    config_path = study_config(tmp_path)
    config = load_study(config_path, check=False)
    proxy = tiny_team(tmp_path / "runs" / "bc_cramped_room_7x7" / "seed0")  # a human proxy for one kitchen only
    out = tmp_path / "pilot"
    assert main(["simulate", str(config_path), "--participants", "4", "--out", str(out), "--seed", "1",
                 "--proxy", str(tmp_path / "runs" / "bc_{kitchen}" / "seed0"), "--max-steps", "4"]) == 0
    served = yaml.safe_load((out / "study.yaml").read_text())
    assert (served["max_steps"], served["practice_steps"], served["pace"]) == (4, 3, "turns")  # games cut, not grown
    printed = capsys.readouterr().out
    visits = [line for line in printed.splitlines() if line.startswith("  [")]
    assert len(visits) == 4 and all(" finished in " in line for line in visits), printed
    assert f"kitchen-study analyse {out}" in printed
    assert f"kitchen-study power {out}" in printed

    posted = {row["participant"]: row for row in json.loads((out / PROXIES).read_text())}
    for row in posted.values():  # the proxy where there is one, a zoo convention's cook elsewhere
        assert row["policies"]["cramped_room_7x7"] == f"proxy {proxy}"
        assert row["policies"]["coord_ring_7x7"].startswith("stand-in cook_")
        assert 0 <= row["noise"] <= 0.3
    assert len({row["noise"] for row in posted.values()}) == 4  # each its own skill
    with sqlite3.connect(out / "study.sqlite") as db:
        people = dict(db.execute("SELECT external_id, number FROM participants WHERE finished IS NOT NULL"))
        stored = db.execute("SELECT participant, stage, item, value FROM answers a JOIN stages s "
                            "USING (participant, stage) WHERE s.kind = 'questions'").fetchall()
        scores = db.execute("SELECT participant, score FROM games WHERE status = 'finished' AND practice = 0 "
                            "ORDER BY participant, position").fetchall()
    assert sorted(people) == sorted(posted)  # every participant finished
    for external_id, number in people.items():  # the response model's answers stored as posted, in the scale
        answers = {(stage, item): value for participant, stage, item, value in stored if participant == number}
        assert answers == {(int(stage), item): value for stage, items in posted[external_id]["answers"].items()
                           for item, value in items.items()}
        assert len(answers) == config.games * 2 + config.games - 1  # two items per game, a choice from the second
        assert all(1 <= value <= 5 for (_, item), value in answers.items() if item != "forced_choice")
        assert [score for participant, score in scores if participant == number] == posted[external_id]["deliveries"]

    assert main(["analyse", str(out)]) == 0
    report = (out / "analysis" / "report.md").read_text()
    assert "| participants finished | 4 |" in report and "| games counted (replayed exactly) | 8 |" in report
    with open(out / "analysis" / "games.csv") as handle:
        counted = [int(row["participant"]) for row in csv.DictReader(handle)]
    assert {number: counted.count(number) for number in people.values()} == {n: config.games for n in range(4)}
    assert f"| answers counted | {len(stored)} |" in report


def test_simulate_refuses_bad_input_in_one_line(tmp_path, capsys):
    config_path = study_config(tmp_path)
    for argv, expected in (
        (["simulate", str(tmp_path / "none.yaml"), "--participants", "2"], "no study config at"),
        (["simulate", str(config_path), "--participants", "0"], "--participants must be 1 or more, got 0"),
        (["simulate", str(config_path), "--participants", "2", "--out", str(tmp_path / "study")], "own folder"),
        (["simulate", str(config_path), "--participants", "2", "--stand-in", "nobody"], "no convention 'nobody'"),
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert expected in err and err.count("\n") == 1, (expected, err)
    assert not (tmp_path / "study-simulated").exists()
