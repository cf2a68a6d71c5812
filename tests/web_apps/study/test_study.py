"""kitchen-study end to end: configs refused in one line, a balanced assignment, simulated participants through
the pages' protocol (in this process and against a server killed and started again), the faults, the report."""

import csv
import json
import signal
import sqlite3
import time
from pathlib import Path

import pytest
import yaml

pytest.importorskip("fastapi", reason="kitchen-study needs the play extra: pip install .[play]")
from fastapi import WebSocketDisconnect  # noqa: E402
from fastapi.testclient import TestClient  # noqa: E402
from tiny_study import TOKEN, study_config  # noqa: E402

from torch_kitchen import env as kitchen_env  # noqa: E402
from torch_kitchen.records import read_record  # noqa: E402
from web_apps.play.game import Game, file_sha256, replay  # noqa: E402
from web_apps.play.server import AddressError, listening_socket  # noqa: E402
from web_apps.study.analysis import analyse  # noqa: E402
from web_apps.study.assignment import assign, design_counts  # noqa: E402
from web_apps.study.client import (  # noqa: E402
    InProcessTransport,
    Participant,
    ProtocolError,
    ServerTransport,
    base_url,
    loopback_listener,
    start_server,
    wait_until_serving,
)
from web_apps.study.command import main  # noqa: E402
from web_apps.study.config import StudyError, kitchen_of, load_study, partner_key, study_partners  # noqa: E402
from web_apps.study.database import StudyDatabase  # noqa: E402
from web_apps.study.design import latin_square  # noqa: E402
from web_apps.study.server import create_study_app, open_study, warm_up  # noqa: E402


def conditions_of(database, participant: Participant) -> list[str]:
    number = database.participant(participant.key)["number"]
    return [slot.condition for slot in database.slots(number) if not slot.practice]


def counts(path: Path) -> dict:
    """What the database holds that must never be lost: finished games, stages done, answers, finished participants."""
    with sqlite3.connect(path) as db:
        return {"finished games": db.execute("SELECT participant, stage, score, sha256 FROM games WHERE status = "
                                             "'finished' ORDER BY participant, stage").fetchall(),
                "stages": db.execute("SELECT participant, stage FROM stages ORDER BY 1, 2").fetchall(),
                "answers": db.execute("SELECT * FROM answers ORDER BY 1, 2, 3").fetchall(),
                "finished": db.execute("SELECT number, completion_code FROM participants WHERE finished IS NOT "
                                       "NULL").fetchall()}


def test_a_config_that_cannot_run_is_refused_in_one_line_and_nothing_is_written(tmp_path, capsys):
    good = yaml.safe_load(study_config(tmp_path).read_text())
    cases = {
        "unknown key 'pase'": {"pase": "turns"},
        "no checkpoint at": {"conditions": {"team": str(tmp_path / "runs" / "none"), "cook": "scripted_cook"}},
        "likert scale must be 2 to 11 distinct labels": {"likert": {"scale": ["agree"], "items": {"a": "A."}}},
        "a multiple of the 2 conditions": {"games_per_participant": 3},
        "unknown kitchen 'nowhere'": {"kitchens": ["nowhere"]},
        "cannot play a 4x5 one": {"kitchens": ["cramped_room"]},  # the 7x7 team on a 5x4 kitchen
        "seat must be 0 or 1": {"seat": 2},
        "the zoo has no convention": {"conditions": {"team": "convention:nobody", "cook": "scripted_cook"}},
    }
    for expected, change in cases.items():
        path = tmp_path / "bad.yaml"
        path.write_text(yaml.safe_dump({**good, **change, "out_dir": str(tmp_path / "never")}))
        for command in ("check", "run"):
            assert main([command, str(path), "--port", "1"] if command == "run" else [command, str(path)]) == 2
            err = capsys.readouterr().err
            assert expected in err and err.count("\n") == 1, (expected, err)
    assert not (tmp_path / "never").exists()
    assert main(["check", str(study_config(tmp_path))]) == 0
    assert "participant 1: " in capsys.readouterr().out and not (tmp_path / "study").exists()
    assert main(["analyse", str(tmp_path / "nowhere")]) == 2 and "holds no study" in capsys.readouterr().err


def test_the_design_balances_conditions_kitchens_and_positions_over_every_block(tmp_path):
    for n in range(2, 7):
        square = latin_square(n)
        assert all(sorted(row) == list(range(n)) for row in square)
        follows = [(row[i], row[i + 1]) for row in square for i in range(n - 1)]  # Williams: each pair as often
        assert len(set(follows)) == n * (n - 1) and len(set(map(follows.count, set(follows)))) == 1
    kitchens = ["cramped_room_7x7", "coord_ring_7x7", "asymm_advantages_7x7", "counter_circuit_7x7"]
    for n, k, per_condition in [(2, 1, 1), (2, 2, 2), (2, 3, 2), (3, 2, 1), (3, 4, 2), (4, 3, 1)]:
        conditions = {f"c{i}": "scripted_cook" for i in range(n)}
        config = load_study(study_config(tmp_path / f"{n}{k}{per_condition}", conditions=conditions,
                                         kitchens=kitchens[:k], games_per_participant=n * per_condition), check=False)
        block = config.block_size
        assert block == len(latin_square(n)) * k
        counts = design_counts(config, 2 * block)  # two blocks: every cell of every table the same
        names, positions = list(conditions), [str(p) for p in range(1, n * per_condition + 1)]
        for table, rows, columns in (("condition x kitchen", names, kitchens[:k]),
                                     ("condition x position", names, positions),
                                     ("kitchen x position", kitchens[:k], positions)):
            cells = [counts[table].get((row, column), 0) for row in rows for column in columns]
            assert len(set(cells)) == 1 and cells[0] > 0, (n, k, per_condition, table, cells)
        for number in range(block):  # each kitchen once before any twice; the same again whenever made
            games = [slot for slot in assign(config, number) if not slot.practice]
            seen = [slot.kitchen for slot in games]
            assert all(len(set(seen[i:i + k])) == len(seen[i:i + k]) for i in range(0, len(seen), k))
            assert games == [slot for slot in assign(config, number) if not slot.practice]
    config = load_study(study_config(tmp_path, games_per_participant=4), check=False)
    assert [[slot.condition for slot in assign(config, number) if not slot.practice] for number in range(2)] == [
        ["cook", "team"] * 2, ["team", "cook"] * 2]


def test_a_target_that_fills_no_whole_block_is_refused_with_the_nearest_that_do(tmp_path, capsys):
    refused = study_config(tmp_path, target_participants=10)  # blocks of 2 rows x 2 kitchens
    with pytest.raises(StudyError, match=r"target_participants=10 fills no whole number of the design's blocks of 4 "
                                         r"participants .*: take 8 or 12, or set accept_unbalanced: true$"):
        load_study(refused, check=False)
    assert load_study(study_config(tmp_path, target_participants=10, accept_unbalanced=True), check=False)
    assert load_study(study_config(tmp_path, target_participants=12), check=False).target_participants == 12
    assert main(["check", str(study_config(tmp_path)), "--participants", "6"]) == 0
    out = capsys.readouterr().out
    assert out.count("  participant ") == 6 and "games per condition x kitchen over the 6 participants" in out
    assert "6 participants fill no whole number of blocks of 4: the counts above are unequal" in out


@pytest.fixture()
def study(tmp_path):
    config = load_study(study_config(tmp_path))
    database, token, operator = open_study(config, TOKEN)
    with TestClient(create_study_app(config, database, token, operator)) as client:
        yield client, database, operator, config


def test_a_visit_without_the_platforms_id_is_refused_and_registers_nothing_unless_the_lab_allows_it(tmp_path):
    for allowed in (False, True):
        config = load_study(study_config(tmp_path / str(allowed), allow_without_id=allowed))
        database, token, _ = open_study(config, TOKEN)
        with TestClient(create_study_app(config, database, token, "operator")) as client:
            visits = [client.get(f"/?token={token}", follow_redirects=False) for _ in range(2)]
            listed = client.get(f"/?token={token}&participant=p-1&STUDY_ID=s-9&SESSION_ID=x-3&other=4",
                                follow_redirects=False)
        rows = database.rows("SELECT external_id, link FROM participants ORDER BY number")
        if allowed:  # a lab run: each visit without an id is a new participant, with its own row of the design
            assert [visit.status_code for visit in visits] == [303, 303]
            assert [row["external_id"] for row in rows] == [None, None, "p-1"]
        else:
            assert [visit.status_code for visit in visits] == [400, 400]
            assert "open it from its link" in visits[0].text and "participant parameter" in visits[0].text
            assert [row["external_id"] for row in rows] == ["p-1"]  # the refused visits took no row
        assert listed.status_code == 303
        assert json.loads(rows[-1]["link"]) == {"STUDY_ID": "s-9", "SESSION_ID": "x-3"}  # kept beside the id
        database.close()


def test_a_study_database_of_before_the_links_parameters_opens_with_them(tmp_path):
    path = tmp_path / "study.sqlite"
    with sqlite3.connect(path) as old:  # the participants table as studies made it before
        old.execute("CREATE TABLE participants (number INTEGER PRIMARY KEY, key TEXT NOT NULL UNIQUE, external_id TEXT "
                    "UNIQUE, completion_code TEXT NOT NULL, started TEXT NOT NULL, finished TEXT)")
        old.execute("INSERT INTO participants VALUES (0, 'k', 'p-0', 'CODE', '2026-12-01T00:00:00Z', NULL)")
    database = StudyDatabase(path)
    assert [dict(row) for row in database.rows("SELECT external_id, link FROM participants")] == [
        {"external_id": "p-0", "link": None}]
    database.close()


def test_an_abandoned_row_goes_to_the_next_arrival_and_a_late_return_still_finishes_and_counts(tmp_path):
    config = load_study(study_config(tmp_path, abandon_after=2))  # blocks of 2 rows x 2 kitchens
    database, token, operator = open_study(config, TOKEN)
    with TestClient(create_study_app(config, database, token, operator)) as client:
        first, second, third = (Participant(InProcessTransport(client), f"p-{i}", TOKEN) for i in range(3))

        def row(person: Participant) -> int:
            return database.rows("SELECT row FROM participants WHERE key = ?", person.key)[0]["row"]

        first.enter()
        second.enter()
        assert (row(first), row(second)) == (0, 1)  # by arrival while both are in progress
        time.sleep(3)  # both abandon: nothing done for longer than abandon_after
        second.take_stage()  # the second comes back: in progress again
        third.enter()
        assert row(third) == 0  # the abandoned first's row, not a new one
        assert [slot for slot in database.slots(2) if not slot.practice][0].condition == conditions_of(
            database, first)[0]  # the row's design: its games' conditions and kitchens
        assert database.row_counts(config.abandon_after) == {0: {"finished": 0, "in progress": 1, "abandoned": 1},
                                                             1: {"finished": 0, "in progress": 1, "abandoned": 0}}
        first.enter()  # the late return: the same participant, its own visit, played to the end and counted
        order = conditions_of(database, first)
        while first.take_stage(order) != "complete":
            pass
        finished = database.row_counts(config.abandon_after)[0]  # the third, idle meanwhile, may have abandoned
        assert finished["finished"] == 1 and finished["in progress"] + finished["abandoned"] == 1
        assert "The design's rows" in client.get(f"/operator?token={TOKEN}&key={operator}").text
    database.close()
    reopened = StudyDatabase(config.folder / "study.sqlite")  # a restart changes none of it
    assert [r["row"] for r in reopened.rows("SELECT row FROM participants ORDER BY number")] == [0, 1, 0]
    reopened.close()


def test_reload_second_tab_double_answer_skipped_stage_and_bad_token(study, monkeypatch):
    client, database, operator, config = study

    def load_again(*args, **kwargs):
        raise AssertionError("a game started by loading its partner: the app loads each once, when it is made")

    monkeypatch.setattr("web_apps.study.config.load_partner", load_again)
    person = Participant(InProcessTransport(client), "faults-1", TOKEN)
    person.enter()
    again = Participant(InProcessTransport(client), "faults-1", TOKEN)
    again.enter()
    assert again.key == person.key  # the platform's link again: the same participant, not a second one

    # Stages out of order: a crafted post or game for a later stage is refused in one line.
    refused = person.post(3, {})
    assert refused.status_code == 409 and "not yours yet: you are at stage 0" in refused.json()["detail"]
    socket, reply = person.open_game(2)
    assert reply["type"] == "error" and "not yours now" in reply["reason"]
    socket.close()
    assert person.post(0, {"consent": False}).status_code == 400
    assert person.post(0, {"consent": True}).json() == {"stage": 1}
    assert person.post(0, {"consent": True}).json()["already"]  # posted twice: done once
    person.take_stage([])  # instructions

    # Two tabs: while one plays the practice game, the second tab's game is refused and nothing is counted twice.
    first, view = person.open_game(2)
    assert view["t"] == 0
    second, reply = person.open_game(2)
    assert reply["type"] == "error" and "another tab" in reply["reason"]
    second.close()
    for _ in range(config.practice_steps):
        first.send(json.dumps({"type": "action", "action": "stay"}))
        view = first.receive()
    assert view["over"]
    first.close()

    # A reload mid-game: the attempt is cut (its record closed "disconnected"), the game is played again.
    game_stage = person.where()["stage"]
    person.play(game_stage, steps=2)
    person.socket.close()
    assert person.where()["stage"] == game_stage
    assert person.play(game_stage)["over"]  # once the server has ended the cut one
    games = database.rows("SELECT * FROM games WHERE participant = 0 AND stage = ? ORDER BY attempt", game_stage)
    assert [(g["status"], g["reason"]) for g in games] == [("cut", "disconnected"), ("finished", "finished")]
    assert read_record(config.folder / games[0]["record"])[2]["reason"] == "disconnected"
    assert person.where()["stage"] == game_stage + 1
    conditions = conditions_of(database, person)

    # Questions: missing or off-scale answers refused; a double post stored once.
    where = person.where()
    stage = where["stage"]
    assert where["asks"] == {"helpful": [1, 2, 3, 4, 5], "predictable": [1, 2, 3, 4, 5]}  # no choice after game 1
    assert person.post(stage, {"answers": {"helpful": 9, "predictable": 1}}).status_code == 400
    assert "answer exactly helpful, predictable" in person.post(stage, {"answers": {}}).json()["detail"]
    answers = {"helpful": 5, "predictable": 1}
    assert person.post(stage, {"answers": answers}).status_code == 200
    stored = len(database.rows("SELECT * FROM answers"))
    assert person.post(stage, {"answers": {"helpful": 1, "predictable": 1}}).json()["already"]
    assert len(database.rows("SELECT * FROM answers")) == stored
    assert database.rows("SELECT value FROM answers WHERE stage = ? AND item = 'helpful'", stage)[0][0] == 5
    while person.take_stage(conditions) != "complete":
        pass
    assert person.where()["code"] in client.get(f"/p/{person.key}?token={TOKEN}").text

    # Tokens and keys: a wrong or missing token, an unknown participant, the operator's page without its key.
    for path in ("/", f"/p/{person.key}", f"/api/p/{person.key}", f"/p/{person.key}?token=guess"):
        response = client.get(path, follow_redirects=False)
        assert response.status_code == 403 and "link you were given" in response.text
    assert client.post(f"/api/p/{person.key}/stages/0", json={}).status_code == 403
    with pytest.raises(WebSocketDisconnect) as closed:
        with client.websocket_connect(f"/ws/p/{person.key}/stages/2"):
            pass
    assert closed.value.code == 1008
    assert client.get(f"/p/nobody?token={TOKEN}").status_code == 404
    assert client.get(f"/operator?token={TOKEN}").status_code == 403
    assert client.get(f"/operator?token={TOKEN}&key=guess").status_code == 403
    progress = client.get(f"/api/progress?token={TOKEN}&key={operator}").json()
    assert (progress["started"], progress["finished"], progress["games_finished"]) == (1, 1, 2)
    assert progress["games_cut"] == 1 and sum(progress["per_condition"].values()) == 2
    operator_page = client.get(f"/operator?token={TOKEN}&key={operator}").text
    assert "Per kitchen" in operator_page and "location.reload()" in operator_page  # it refreshes itself


def test_a_restarted_study_refuses_another_config(study, tmp_path):
    _, _, _, config = study
    changed = load_study(study_config(tmp_path, out_dir=str(config.folder), max_steps=7), check=False)
    with pytest.raises(ValueError, match="started with another config"):
        open_study(changed)


def test_a_server_started_here_owns_its_port_from_the_start_and_its_exit_is_said_in_the_errors_first_line(tmp_path):
    listener = loopback_listener()
    host, port = listener.getsockname()[:2]
    with pytest.raises(AddressError, match=f"cannot serve on {host}:{port}"):  # no other server can take it
        listening_socket(host, port)
    config_path = study_config(tmp_path, kitchens=["no_such_kitchen"])
    log = tmp_path / "server.log"
    server = start_server(config_path, listener, TOKEN, log)
    with pytest.raises(ProtocolError) as exited:
        wait_until_serving(server, ServerTransport(f"http://{host}:{port}"), TOKEN, log)
    first = str(exited.value).splitlines()[0]
    assert first.startswith("the study's server exited (2): kitchen-study: error:") and "no_such_kitchen" in first


def test_six_participants_through_a_server_killed_mid_study_and_the_report_traces_to_records(tmp_path):
    config_path = study_config(tmp_path)
    config = load_study(config_path, check=False)
    database_path = config.folder / "study.sqlite"
    listener = loopback_listener()
    transport = ServerTransport(base_url(listener))
    log = tmp_path / "server.log"
    server = start_server(config_path, listener, TOKEN, log)
    try:
        wait_until_serving(server, transport, TOKEN, log)
        people = [Participant(transport, f"P{i}", TOKEN) for i in range(6)]
        for person in people:
            person.enter()
        database = StudyDatabase(database_path, create=False)
        conditions = {person.key: conditions_of(database, person) for person in people}
        for person in people[:4]:  # four finish before the server is killed
            while person.take_stage(conditions[person.key]) != "complete":
                pass
        while people[4].where()["kind"] != "game":  # the fifth is mid-game, the sixth has only consented
            people[4].take_stage(conditions[people[4].key])
        people[4].play(people[4].where()["stage"], steps=2)
        people[5].take_stage(conditions[people[5].key])
        before = counts(database_path)
        assert len(before["finished"]) == 4 and len(before["finished games"]) == 4 * 3 + 1  # + the fifth's practice
        server.send_signal(signal.SIGKILL)
        server.wait(timeout=30)
        people[4].socket.close()
        assert counts(database_path) == before  # nothing finished lost
        playing = database.rows("SELECT * FROM games WHERE status = 'playing'")
        assert len(playing) == 1 and read_record(config.folder / playing[0]["record"])[2] is None  # cut short
    finally:
        server.kill()
        server.wait()

    # Started again (here, in this process, as `kitchen-study run` opens it): everyone resumes at their stage.
    database_again, token, operator = open_study(config, TOKEN)
    assert counts(database_path) == before
    cut = database.rows("SELECT * FROM games WHERE status = 'cut'")
    assert [(g["participant"], g["reason"]) for g in cut] == [(4, "the server stopped mid-game")]
    with TestClient(create_study_app(config, database_again, token, operator)) as client:
        for person in people:  # the cut game played again in its place
            person.transport = InProcessTransport(client)
            while person.take_stage(conditions[person.key]) != "complete":
                pass
        assert [person.where()["code"] for person in people[:4]] == [code for _, code in before["finished"]]
    progress = database.progress()
    database_again.close()
    assert progress["finished"] == 6 and progress["games_finished"] == 12 and progress["games_cut"] == 1
    assert progress["per_condition"] == {"cook": 6, "team": 6}  # balanced
    firsts = [conditions[person.key][0] for person in people]
    assert firsts.count("team") == firsts.count("cook") == 3

    assert main(["analyse", str(config.folder)]) == 0
    report = (config.folder / "analysis" / "report.md").read_text()
    with open(config.folder / "analysis" / "games.csv") as handle:
        games = list(csv.DictReader(handle))
    finished = database.rows("SELECT * FROM games WHERE status = 'finished' AND practice = 0")
    assert len(games) == len(finished) == 12
    assert "| games counted (replayed exactly) | 12 |" in report and "| participants finished | 6 |" in report
    for game in games:  # every counted game traces to its record: checksum and replayed score
        record = config.folder / game["record"]
        assert file_sha256(record) == game["sha256"] and replay(record)["score"] == int(game["deliveries"])
    for condition in ("cook", "team"):
        assert f"| {condition} | all | 6 |" in report
    assert "| cook | team | 6 |" in report  # within participants: all six played both
    answers = len(database.rows("SELECT * FROM answers a JOIN stages s USING (participant, stage) "
                                "WHERE s.kind = 'questions'"))
    assert f"| answers counted | {answers} |" in report and answers == 6 * (2 * 2 + 1)
    assert "| team | helpful | 6 | 4 | 4.00 |" in report and "| cook | helpful | 6 | 2 | 2.00 |" in report  # by person
    assert "| helpful | 6 | -2.00 |" in report  # each participant's answers beside cook minus beside team
    assert "| cook | team | 6 | 0 | 6 | 0.031 |" in report  # the forced choice: the team each time, sign test 2 / 2**6
    assert "| cook - team (primary) |" in report  # the headline: the mixed model's primary contrast
    with open(config.folder / "analysis" / "answers.csv") as handle:
        choices = [row for row in csv.DictReader(handle) if row["item"] == "forced_choice"]
    assert len(choices) == 6 and all((row["chosen"], row["not_chosen"]) == ("team", "cook") for row in choices)
    assert main(["power", str(config.folder), "--studies", "4", "--sizes", "8", "16"]) == 0  # the N a study needs
    sized = (config.folder / "analysis" / "power.md").read_text()
    assert "| 8 |" in sized and "| 16 |" in sized and "The smallest N with 80% power" in sized
    assert (config.folder / "analysis" / "power.png").is_file()
    database.close()

    # A record changed after its game is listed and left out with the reason; the counts follow.
    tampered = config.folder / games[0]["record"]
    lines = tampered.read_text().splitlines()
    step = json.loads(lines[2])
    step["positions"][0][0] += 1
    lines[2] = json.dumps(step)
    tampered.write_text("\n".join(lines) + "\n")
    report = Path(analyse(config.folder)).read_text()
    assert "| games counted (replayed exactly) | 11 |" in report and "| games left out | 1 |" in report
    assert "checksum differs" in report and games[0]["record"] in report


def test_each_stage_page_holds_what_its_participant_needs(study):
    client, database, _, config = study
    person = Participant(InProcessTransport(client), "pages-1", TOKEN)
    person.enter()
    conditions = conditions_of(database, person)
    seen = {}
    while True:
        where = person.where()
        seen[where["label"]] = client.get(f"/p/{person.key}?token={TOKEN}").text
        if person.take_stage(conditions) == "complete":
            break
    assert 'onclick="done({consent: true})"' in seen["consent"] and "You may stop" in seen["consent"]
    assert "<canvas" in seen["practice 1"] and "function draw(state)" in seen["practice 1"]  # kitchen-play's drawing
    assert "/ws/p/${KEY}/stages/${STAGE}" in seen["game 1"] and "Game 1 of 2" in seen["game 1"]
    assert "My partner was helpful." in seen["questions 1"] and "forced_choice" not in seen["questions 1"]
    assert 'name="forced_choice" value="0"' in seen["questions 2"] and 'value="1"' in seen["questions 2"]
    assert person.where()["code"] in seen["complete"]


def test_the_warm_up_plays_every_partner_in_every_kitchen_so_that_a_first_game_compiles_nothing(tmp_path):
    """`kitchen-study run` warms up before it serves: every kitchen's programs at each game length exist when the
    first participant's game starts (its first state came 3 to 5 s late without), and nothing of it is recorded."""
    config = load_study(study_config(tmp_path, max_steps=7, practice_steps=6), check=False)
    partners = study_partners(config)
    games, _ = warm_up(config, partners)
    assert games == len(config.conditions) * len(config.kitchens) + 1  # and the practice game
    assert not config.folder.exists() or not any(config.folder.rglob("*.jsonl"))
    compiled = set(kitchen_env._PROGRAMS._programs)
    for steps, kitchen, spec in ((7, "coord_ring_7x7", config.conditions["cook"]),
                                 (6, config.practice_kitchen, config.practice_partner)):
        game = Game(kitchen_of(kitchen, 5), partners[partner_key(spec, kitchen)], config.seat,
                    tmp_path / f"{steps}.jsonl", seed=5, max_steps=steps)
        game.step(0)
    assert set(kitchen_env._PROGRAMS._programs) == compiled  # no kitchen program built anew
