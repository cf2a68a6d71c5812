"""Simulated participants: a client that speaks the study pages' protocol (`web_apps.study.server`: HTTP for the
stages, a WebSocket for the games), through FastAPI's TestClient in this process or against a real server (httpx
and websockets), and a `kitchen-study run` server in a subprocess to run them against. The tests drive studies with
it, `benchmarks/study_load.py` loads a server with it, and `kitchen-study simulate` (`web_apps.study.simulate`) runs a
pilot by proxies with it."""

from __future__ import annotations

import json
import os
import random
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from web_apps.play.game import ACTIONS
from web_apps.play.server import listening_socket
from web_apps.study.config import FORCED_CHOICE


class ProtocolError(RuntimeError):
    """The server answered a participant otherwise than the protocol says it would."""


def expect(response, status: int = 200):
    """`response`, if it has `status`; a ProtocolError with the server's answer otherwise."""
    if response.status_code != status:
        raise ProtocolError(f"{response.request.method} {response.request.url.path}: {response.status_code} "
                            f"{response.text[:300]}")
    return response


class Socket:
    """A game's WebSocket: send a text message, receive one JSON message, close."""

    def __init__(self, send: Callable[[str], None], receive: Callable[[], dict], close: Callable[[], None]):
        self.send, self.receive, self.close = send, receive, close


class InProcessTransport:
    """The protocol through FastAPI's TestClient (in this process)."""

    def __init__(self, client):
        self.client = client

    def get(self, path: str):
        return self.client.get(path, follow_redirects=False)

    def post(self, path: str, body: dict):
        return self.client.post(path, json=body)

    def socket(self, path: str) -> Socket:
        session = self.client.websocket_connect(path)
        socket = session.__enter__()
        return Socket(socket.send_text, socket.receive_json, lambda: session.__exit__(None, None, None))


class ServerTransport:
    """The protocol against a server at `base` (httpx, websockets); one per thread."""

    def __init__(self, base: str, timeout: float = 60.0):
        import httpx

        self.base, self.timeout = base, timeout
        self.http = httpx.Client(base_url=base, timeout=timeout)

    def get(self, path: str):
        return self.http.get(path)

    def post(self, path: str, body: dict):
        return self.http.post(path, json=body)

    def socket(self, path: str) -> Socket:
        from websockets.sync.client import connect

        session = connect(self.base.replace("http", "ws", 1) + path)
        socket = session.__enter__()
        return Socket(socket.send, lambda: json.loads(socket.recv(timeout=self.timeout)),
                      lambda: session.__exit__(None, None, None))


class Participant:
    """One participant of the platform's id `external_id`: a random key on every state of a game, every Likert item
    answered high after a game with `preferred`'s condition and low after the others, and in the forced choice
    `preferred`'s game where one of the last two was with it (else the latest). `on_view(stage, view)`, if given, is
    called as each state of a game arrives (a load benchmark times them)."""

    def __init__(self, transport, external_id: str, token: str, preferred: str = "team",
                 on_view: Callable[[int, dict], None] | None = None):
        self.transport, self.external_id, self.token = transport, external_id, token
        self.preferred, self.on_view = preferred, on_view
        self.key = None
        self.socket = None
        self.opened: dict[int, float] = {}  # stage -> when its game's socket was opened (perf_counter)
        self.actions = random.Random(external_id)
        self.answered: dict[int, dict[str, int]] = {}  # stage -> the answers posted and taken

    def enter(self, participant_param: str = "participant") -> None:
        """Opens the study's link, as the recruiting platform gives it, and keeps the participant's own key."""
        response = expect(self.transport.get(f"/?token={self.token}&{participant_param}={self.external_id}"), 303)
        self.key = response.headers["location"].split("/p/")[1].split("?")[0]

    def where(self) -> dict:
        return expect(self.transport.get(f"/api/p/{self.key}?token={self.token}")).json()

    def post(self, stage: int, body: dict):
        return self.transport.post(f"/api/p/{self.key}/stages/{stage}?token={self.token}", body)

    def open_game(self, stage: int) -> tuple[Socket, dict]:
        self.opened[stage] = time.perf_counter()
        socket = self.transport.socket(f"/ws/p/{self.key}/stages/{stage}?token={self.token}")
        return socket, socket.receive()

    def play(self, stage: int, steps: int | None = None) -> dict:
        """Plays the game of `stage` to its end, or `steps` steps and then leaves it open (in `self.socket`);
        returns the last state."""
        self.socket, view = self.open_game(stage)
        if view["type"] != "state":
            self.socket.close()
            raise ProtocolError(f"the game of stage {stage} was refused: {view.get('reason')}")
        taken = 0
        while True:
            if self.on_view is not None:
                self.on_view(stage, view)
            if view["over"] or (steps is not None and taken >= steps):
                break
            self.socket.send(json.dumps({"type": "action", "action": self.actions.choice(list(ACTIONS))}))
            view = self.socket.receive()
            taken += 1
        if view["over"]:
            self.socket.close()
        return view

    def answers(self, where: dict, conditions: list[str] | None) -> dict[str, int]:
        """The answers to what a questions stage `asks` (its "asks": each answer's allowed values), given the
        participant's assigned `conditions` in order (None: none of them preferred)."""
        position = where["position"]
        liked = conditions is not None and conditions[position] == self.preferred
        values = {item: allowed[-2] if liked else allowed[1] for item, allowed in where["asks"].items()
                  if item != FORCED_CHOICE}
        if FORCED_CHOICE in where["asks"]:
            previous_liked = conditions is not None and conditions[position - 1] == self.preferred
            values[FORCED_CHOICE] = position - 1 if previous_liked and not liked else position
        return values

    def take_stage(self, conditions: list[str] | None = None) -> str:
        """Does the participant's current stage; returns its kind."""
        where = self.where()
        kind, stage = where["kind"], where["stage"]
        if kind == "consent":
            expect(self.post(stage, {"consent": True}))
        elif kind == "instructions":
            expect(self.post(stage, {}))
        elif kind in ("practice", "game"):
            if not self.play(stage)["over"]:
                raise ProtocolError(f"the game of stage {stage} closed before it was over")
        elif kind == "questions":
            answers = self.answers(where, conditions)
            expect(self.post(stage, {"answers": answers}))
            self.answered[stage] = answers
        return kind


def loopback_listener() -> socket.socket:
    """A socket listening on a free loopback port, for a server started here to serve on (`start_server`): the port
    is held from now on, so no other process can take it before the server starts."""
    return listening_socket("127.0.0.1", 0)


def base_url(listener: socket.socket) -> str:
    host, port = listener.getsockname()[:2]
    return f"http://{host}:{port}"


def start_server(config_path: str | Path, listener: socket.socket, token: str, log: str | Path,
                 env: dict[str, str] | None = None, cwd: str | Path | None = None) -> subprocess.Popen:
    """`kitchen-study run CONFIG` on `listener` (handed to it, and closed here) with the participants' `token`, in a
    subprocess whose output goes to the end of `log` (`env`: more environment variables; `cwd`: where the config's
    relative paths start, by default the repository's root)."""
    command = [sys.executable, "-m", "web_apps.study.command", "run", str(config_path), "--fd",
               str(listener.fileno()), "--token", token]
    with open(log, "a") as output:
        server = subprocess.Popen(command, cwd=cwd or Path(__file__).resolve().parents[2], stdout=output,
                                  stderr=subprocess.STDOUT, text=True, env={**os.environ, **(env or {})},
                                  pass_fds=(listener.fileno(),))
    listener.close()  # the server's own copy is the only one: if it exits, a connection is refused, not kept waiting
    return server


def wait_until_serving(server: subprocess.Popen, transport: ServerTransport, token: str, log: str | Path,
                       timeout_s: float = 60.0) -> None:
    """Returns once `server` answers; a ProtocolError with the end of its `log` if it exits or stays silent."""
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.poll() is not None:
            said = Path(log).read_text()
            last = ([line for line in said.splitlines() if line.strip()] or ["its log is empty"])[-1]
            raise ProtocolError(f"the study's server exited ({server.returncode}): {last}\n{said[-3000:]}")
        try:
            if transport.get(f"/api/p/nobody?token={token}").status_code == 404:
                return
        except httpx.TransportError:
            time.sleep(0.05)
    raise ProtocolError(f"the study's server did not answer within {timeout_s:g} s")
