"""The kitchen-play server without a browser: lobby checks, games over WebSockets, records and their replay."""

import json
import os
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

pytest.importorskip("fastapi", reason="kitchen-play needs the play extra: pip install .[play]")
from fastapi import WebSocketDisconnect  # noqa: E402
from fastapi.testclient import TestClient  # noqa: E402

from torch_kitchen.keys import OBSERVATION  # noqa: E402
from torch_kitchen.models import make_actor_critic, model_identity  # noqa: E402
from torch_kitchen.records import read_record  # noqa: E402
from trainers.checkpoint import save_checkpoint  # noqa: E402
from trainers.config import TrainConfig  # noqa: E402
from trainers.humans.behaviour_cloning import human_batch  # noqa: E402
from trainers.humans.command import games_from_records  # noqa: E402
from web_apps.play.game import RANDOM, SCRIPTED, replay  # noqa: E402
from web_apps.play.server import SharedPartners, create_app, main  # noqa: E402


@pytest.fixture()
def client(tmp_path):
    app = create_app(records=tmp_path / "games", tick_ms=5, max_steps=30, runs_root=str(tmp_path / "runs"))
    with TestClient(app) as client:
        yield client


def new_game(client, partner=SCRIPTED, kitchen="cramped_room_7x7", mode="turns", seed=1, seat=0):
    response = client.post("/api/games", json={"partner": partner, "kitchen": kitchen, "seat": seat, "mode": mode,
                                               "seed": seed})
    assert response.status_code == 200, response.json()
    return response.json()


def test_the_lobby_offers_partners_and_kitchens_and_refuses_bad_choices_with_the_reason(client, tmp_path):
    assert "<canvas" in client.get("/").text
    options = client.get("/api/options").json()
    assert {SCRIPTED, RANDOM} <= set(options["partners"])
    assert {"cramped_room_7x7", "cramped_room", "heldout_042"} <= set(options["kitchens"])

    def refused(**choice):
        response = client.post("/api/games", json={"partner": SCRIPTED, "kitchen": "cramped_room_7x7", **choice})
        assert response.status_code == 400
        return response.json()["detail"]

    assert "unknown kitchen 'nowhere'" in refused(kitchen="nowhere")
    assert "unknown partner" in refused(partner="runs/none/seed0")
    assert "seat must be 0 or 1" in refused(seat=2)
    for seed in (2**63, -1):  # checked by the request's schema: a 422 naming the field, not a server error
        response = client.post("/api/games", json={"partner": SCRIPTED, "kitchen": "cramped_room_7x7", "seed": seed})
        assert response.status_code == 422 and response.json()["detail"][0]["loc"][-1] == "seed"
    # A trained team offered from runs/ whose networks were built for 4x5 kitchens cannot play a 7x7 one.
    run = tmp_path / "runs" / "small" / "seed0"
    actor_critic = make_actor_critic("mlp", (4, 5, 26), 8, True)
    save_checkpoint(run / "checkpoints" / "latest.pt", {
        "config": TrainConfig(levels="cramped_room").to_dict(), "model": model_identity("mlp", (4, 5, 26), 8, True),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
    assert str(run) in client.get("/api/options").json()["partners"]
    assert "cannot play a 7x7 one" in refused(partner=str(run))
    assert new_game(client, partner=str(run), kitchen="cramped_room")["id"]  # its own size plays


def play_turns(client, game, actions):
    views = []
    with client.websocket_connect(f"/ws/games/{game['id']}") as socket:
        views.append(socket.receive_json())
        for action in actions:
            socket.send_text(json.dumps({"type": "action", "action": action}))
            views.append(socket.receive_json())
        with pytest.raises(WebSocketDisconnect):  # the server closes a finished game
            socket.receive_json()
    return views


def test_two_games_at_once_stay_isolated_and_each_replays_exactly(client):
    first = new_game(client, SCRIPTED, "cramped_room_7x7", seed=1)
    second = new_game(client, RANDOM, "coord_ring_7x7", seed=2, seat=1)
    with client.websocket_connect(f"/ws/games/{first['id']}") as a, client.websocket_connect(
            f"/ws/games/{second['id']}") as b:
        a.receive_json(), b.receive_json()
        for step in range(6):  # interleaved: each game advances only on its own messages
            a.send_text(json.dumps({"type": "action", "action": "left"}))
            assert a.receive_json()["t"] == step + 1
            if step % 2 == 0:
                b.send_text(json.dumps({"type": "action", "action": "interact"}))
                assert b.receive_json()["t"] == step // 2 + 1
    header_a, steps_a, end_a = read_record(first["record"])
    header_b, steps_b, end_b = read_record(second["record"])
    assert (header_a["partner"], header_a["layout_name"], header_a["seat"]) == (SCRIPTED, "cramped_room_7x7", 0)
    assert (header_b["partner"], header_b["layout_name"], header_b["seat"]) == (RANDOM, "coord_ring_7x7", 1)
    assert [s["actions"][0] for s in steps_a] == [3] * 6 and [s["actions"][1] for s in steps_b] == [5] * 3
    assert end_a["reason"] == end_b["reason"] == "disconnected"
    assert replay(first["record"])["steps"] == 6 and replay(second["record"])["steps"] == 3


def test_malformed_messages_are_refused_and_the_game_goes_on(client):
    game = new_game(client)
    with client.websocket_connect(f"/ws/games/{game['id']}") as socket:
        assert socket.receive_json()["t"] == 0
        bad = ["not json", json.dumps({"type": "action", "action": "fly"}), json.dumps({"foo": 1}),
               '{"type":"action","action":[]}', '{"type":"action","action":{}}', "[" * 100_000,
               json.dumps({"type": "action", "action": "x" * 5_000_000}), '{"type": "action"}', "null", "[]"]
        for text in bad:
            socket.send_text(text)
            reply = socket.receive_json()
            assert reply["type"] == "error" and "expected" in reply["reason"] and len(reply["reason"]) <= 300, text
        socket.send_bytes(b"\x00\x01")
        assert "binary frame" in socket.receive_json()["reason"]
        socket.send_text(json.dumps({"type": "action", "action": "up"}))
        assert socket.receive_json()["t"] == 1
    assert [s["t"] for s in read_record(game["record"])[1]] == [1]


def test_a_turns_game_without_actions_ends_idle_with_its_record_closed(tmp_path):
    app = create_app(records=tmp_path / "games", max_steps=30, runs_root=str(tmp_path / "runs"), idle_s=0.3)
    with TestClient(app) as client:
        game = new_game(client)
        with client.websocket_connect(f"/ws/games/{game['id']}") as socket:
            assert socket.receive_json()["t"] == 0
            assert "no action for 0.3 s" in socket.receive_json()["reason"]
            with pytest.raises(WebSocketDisconnect):
                socket.receive_json()
    header, steps, end = read_record(game["record"])
    assert steps == [] and end["reason"] == "idle"


def test_a_closed_tab_ends_a_real_time_game_with_its_record_complete(client):
    game = new_game(client, mode="realtime")
    with client.websocket_connect(f"/ws/games/{game['id']}") as socket:
        for _ in range(4):
            view = socket.receive_json()
        assert view["t"] == 3  # the kitchen ticks without the person: STAY stands in for no key
    header, steps, end = read_record(game["record"])
    assert header["mode"] == "realtime" and end is not None and end["steps"] == len(steps) >= 3
    assert [s["t"] for s in steps] == list(range(1, len(steps) + 1))
    assert all(s["actions"][0] == 4 for s in steps)  # STAY
    assert replay(game["record"])["steps"] == len(steps)


def test_a_finished_game_replays_through_the_command_and_loads_as_a_dataset(client, tmp_path, capsys):
    game = new_game(client, seed=5)
    views = play_turns(client, game, ["up", "interact", "left", "down", "right", "stay"] * 5)
    assert views[-1]["over"] and views[-1]["time_left"] == 0
    header, steps, end = read_record(game["record"])
    assert end["reason"] == "finished" and len(steps) == 30 and header["checkpoint_sha256"] is None

    gif = tmp_path / "game.gif"
    assert main(["replay", game["record"], "--gif", str(gif)]) == 0 and gif.stat().st_size > 0
    assert "30 steps replayed exactly" in capsys.readouterr().out
    lines = Path(game["record"]).read_text().splitlines()
    step = json.loads(lines[5])
    step["positions"][0][0] += 1  # a record that does not match the kitchen
    lines[5] = json.dumps(step)
    tampered = tmp_path / "tampered.jsonl"
    tampered.write_text("\n".join(lines))
    assert main(["replay", str(tampered)]) == 1
    assert "step 5 differs" in capsys.readouterr().err

    # Records that are not a whole game are refused with the reason, never replayed "exactly".
    header_only, cut, wild, bare = (tmp_path / name for name in ("header.jsonl", "cut.jsonl", "wild.jsonl",
                                                                  "bare.jsonl"))
    header_only.write_text(lines[0] + "\n")
    cut.write_text("\n".join(Path(game["record"]).read_text().splitlines()[:-1]))
    step = json.loads(lines[3])
    step["actions"] = [99, 4]
    wild.write_text("\n".join([*lines[:3], json.dumps(step), *lines[4:]]))
    bare.write_text("\n".join([json.dumps({"type": "header"}), *lines[1:]]))
    for path, message in [(header_only, "never ended (no end line after 0 steps)"),
                          (cut, "never ended (no end line after 30 steps)"),
                          (wild, "has actions [99, 4], not two of 0..5"), (bare, "the header lacks layout")]:
        assert main(["replay", str(path)]) == 1
        error = capsys.readouterr().err
        assert message in error and error.count("\n") == 1, error

    # The record is a human game like the 2019 ones: both seats' observations, the person's seat labelled.
    [recorded] = games_from_records([game["record"]], "train")
    assert human_batch([recorded]).get(OBSERVATION).shape == (30, 2, 7, 7, 26) and recorded.human_seats == (True, False)
    assert recorded.actions.tolist() == [s["actions"] for s in steps]


def test_bad_server_options_and_a_busy_port_get_one_line_before_any_address_is_printed(capsys):
    for flag in ("--tick-ms=0", "--tick-ms=-1", "--idle-s=0"):
        with pytest.raises(SystemExit):
            main([flag])
        assert "must be positive" in capsys.readouterr().err
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        assert main(["--port", str(busy.getsockname()[1])]) == 2
    printed = capsys.readouterr()
    assert "cannot serve on 127.0.0.1" in printed.err and "open http" not in printed.out


def test_sigterm_stops_the_server_with_a_waiting_turns_game_and_its_record_closed(tmp_path):
    import signal
    import socket as sockets
    import subprocess
    import sys
    import time

    import httpx
    from websockets.sync.client import connect

    with sockets.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    records = tmp_path / "games"
    command = [sys.executable, "-m", "web_apps.play.server", "--port", str(port), "--records", str(records)]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for _ in range(600):
            try:
                game = httpx.post(f"http://127.0.0.1:{port}/api/games", json={
                    "partner": SCRIPTED, "kitchen": "cramped_room_7x7", "mode": "turns", "seed": 1}).json()
                break
            except httpx.TransportError:
                time.sleep(0.1)
        with connect(f"ws://127.0.0.1:{port}/ws/games/{game['id']}") as socket:
            assert json.loads(socket.recv(timeout=60))["t"] == 0  # the game waits for the person's first action
            socket.send(b"\x00")  # a binary frame once ended the reader, and the server then never stopped
            assert json.loads(socket.recv(timeout=10))["type"] == "error"
            server.send_signal(signal.SIGTERM)
            # uvicorn shuts down gracefully, then ends with the signal it caught
            assert server.wait(timeout=30) in (0, -signal.SIGTERM)
    finally:
        server.kill()
        output = server.communicate()[0]
    header, steps, end = read_record(game["record"])
    assert end is not None and end["reason"] == "disconnected" and steps == [], output


def test_a_page_from_another_origin_cannot_take_a_game_and_its_owner_still_can(client):
    game = new_game(client)
    assert len(game["id"]) >= 20 and game["id"] not in game["record"]  # a random key, not the record's date
    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect(f"/ws/games/{game['id']}", headers={"origin": "http://localhost:9999"}):
            pass
    assert refused.value.code == 1008
    with client.websocket_connect(f"/ws/games/{game['id']}", headers={"origin": "http://testserver"}) as socket:
        assert socket.receive_json()["t"] == 0


def test_unknown_hosts_are_refused_and_games_nobody_joins_expire(tmp_path):
    app = create_app(records=tmp_path / "games", max_steps=30, runs_root=str(tmp_path / "runs"), connect_s=0,
                     hosts=["testserver"])
    with TestClient(app) as client:
        assert client.get("/", headers={"host": "rebound.example:8000"}).status_code == 400
        abandoned = new_game(client)
        new_game(client)  # any later activity ends the games nobody connected to in time
        assert read_record(abandoned["record"])[2]["reason"] == "never connected"
        with client.websocket_connect(f"/ws/games/{abandoned['id']}") as socket:
            assert "no such game" in socket.receive_json()["reason"]


def test_a_study_token_admits_only_links_that_carry_it(tmp_path):
    app = create_app(records=tmp_path / "games", max_steps=30, runs_root=str(tmp_path / "runs"), token="s3cret")
    with TestClient(app) as client:
        for path in ("/", "/api/options", "/?token=guess"):
            response = client.get(path)
            assert response.status_code == 403 and "link you were given" in response.text
        assert client.get("/?token=s3cret").status_code == 200
        choice = {"partner": SCRIPTED, "kitchen": "cramped_room_7x7", "mode": "turns", "seed": 1}
        assert client.post("/api/games", json=choice).status_code == 403
        game = client.post("/api/games?token=s3cret", json=choice).json()
        with pytest.raises(WebSocketDisconnect) as refused:
            with client.websocket_connect(f"/ws/games/{game['id']}"):
                pass
        assert refused.value.code == 1008
        with client.websocket_connect(f"/ws/games/{game['id']}?token=s3cret") as socket:
            assert socket.receive_json()["t"] == 0  # the refused attempt left the game to its player


def save_mlp_team(run: Path, seed: int) -> torch.nn.Module:
    torch.manual_seed(seed)
    actor_critic = make_actor_critic("mlp", (7, 7, 26), 8, True)
    save_checkpoint(run / "checkpoints" / "latest.pt", {
        "config": TrainConfig().to_dict(), "model": model_identity("mlp", (7, 7, 26), 8, True),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
    return actor_critic


def test_games_with_one_partner_share_it_until_its_run_writes_a_new_checkpoint(client, tmp_path):
    """A server's games load a partner once (then they run its forward pass once a round), and a run that is
    still training is read again once its latest checkpoint changes."""
    run = tmp_path / "runs" / "mlp" / "seed0"
    save_mlp_team(run, 0)
    shared = SharedPartners("cpu")
    first, second = shared(str(run)), shared(str(run))
    assert first is second and shared(SCRIPTED) is shared(SCRIPTED)
    newer = save_mlp_team(run, 1)
    stamp = (run / "checkpoints" / "latest.pt").stat().st_mtime_ns + 10**9
    os.utime(run / "checkpoints" / "latest.pt", ns=(stamp, stamp))
    reloaded = shared(str(run))
    assert reloaded is not first
    observation = TensorDict({OBSERVATION: torch.randint(0, 2, (3, 2, 7, 7, 26), dtype=torch.uint8)}, [3])
    with torch.no_grad():
        logits = [network(observation.clone())["agents", "logits"]
                  for network in (reloaded.actor_critic.actor, newer.actor, first.actor_critic.actor)]
    torch.testing.assert_close(logits[0], logits[1])
    assert not torch.allclose(logits[0], logits[2])
    assert new_game(client, partner=str(run))["id"] and new_game(client, partner=str(run))["id"]
