"""`kitchen-play`: a local web server where a person cooks with a trained team, in a browser tab.

    kitchen-play                                   # partners: runs/*/seed*, the scripted cook, a random agent
    kitchen-play runs/main/seed0 --port 8000       # this run too; prints the URL
    kitchen-play replay games/<game>.jsonl --gif game.gif

The lobby (`/`) lists the partners and the kitchens; `POST /api/games` checks a choice (an unknown kitchen, a
partner that cannot be loaded or cannot play that kitchen's size are refused with the reason) and makes the game;
the page then plays it over the WebSocket `/ws/games/<id>`. In real time the server ticks every `tick_ms` and the
person's latest key applies to the next tick (STAY if none); in turns mode the kitchen steps when the person acts.
Each game has its own kitchen, partner and record (`web_apps.play.game`); any message other than an action (malformed,
too long, binary) is answered with a one-line error and logged, and the game goes on; a closed tab ends its game
with the record complete, as does a turns-mode game left without an action for `--idle-s` seconds ("idle") and
every game when the server stops (SIGTERM or SIGINT). Game ids are random keys, games nobody connects to expire,
and only the server's own Host and Origin are answered. Needs the `play` extra:
`pip install .[play]`.
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import ctypes.util
import functools
import glob
import itertools
import logging
import queue
import secrets
import socket
import sys
import threading
import time
import typing
from pathlib import Path

import jax

from jax_env import (
    CLASSIC_LAYOUTS,
    EXPANDED_LAYOUTS,
    PADDED_LAYOUTS,
    STAY,
    GeneratorConfig,
    Layout,
    heldout_grids,
    layout_from_state,
    load_layout,
)
from jax_env.generator import sample_training_level
from trainers.checkpoint import CheckpointError, checkpoint_file
from trainers.evaluation import evaluation_grids
from web_apps.play.game import ACTIONS, RANDOM, SCRIPTED, Game, Partner, load_partner, replay, step_games

try:
    from fastapi import FastAPI, HTTPException, WebSocket, WebSocketDisconnect
    from fastapi.responses import HTMLResponse
    from pydantic import BaseModel, Field, ValidationError

    class Choice(BaseModel):
        """A lobby choice: who partners the person, where, in which seat, at which pace (and the kitchen's seed)."""

        partner: str
        kitchen: str
        seat: int = 0
        mode: str = "realtime"
        seed: int | None = Field(None, ge=0, le=2**32 - 1)

    class ActionMessage(BaseModel):
        """The one message a player sends: {"type": "action", "action": "left"}."""

        type: typing.Literal["action"]
        action: typing.Literal[tuple(ACTIONS)]
except ImportError:  # the optional extra
    FastAPI = None

STATIC = Path(__file__).parent / "static"
GENERATED = "a freshly generated Infinite Kitchen level"
MODES = ("realtime", "turns")
NO_TOKEN = "this server's games are for a study's participants: open the link you were given (it carries a token)"
log = logging.getLogger("kitchen-play")


@functools.cache
def _malloc_trim():
    """glibc's malloc_trim, or None (another C library)."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


class GameStepper:
    """Every game's steps, on one thread, in rounds: the steps waiting when the thread comes free are taken
    together (`step_games`), so that games sharing a partner run its forward passes together, 8 games a pass. A step
    is hundreds of small torch and JAX calls, each giving the GIL up and taking it back: steps on several threads at
    once hand it to one another at every call (40 games on two cores: p99 189 ms between states with one thread
    against 345 with a thread per step), and a round of 20 games with the scripted cook costs 0.79 ms a game against
    2.16 one game after another (BENCHMARKS.md, "kitchen-play under load")."""

    def __init__(self):
        self.requests: queue.SimpleQueue = queue.SimpleQueue()
        self.thread: threading.Thread | None = None
        self.starting = threading.Lock()

    async def step(self, game: Game, action: int) -> dict:
        """`game.step(action)`, taken in the stepping thread's next round."""
        loop = asyncio.get_running_loop()
        future = loop.create_future()
        with self.starting:
            if self.thread is None:
                self.thread = threading.Thread(target=self.run, name="game-steps", daemon=True)
                self.thread.start()
        self.requests.put((game, action, loop, future))
        return await future

    def run(self) -> None:
        while True:
            self.take_round()

    def take_round(self) -> None:
        """The steps waiting (the first awaited), as one round; each caller handed its game's view or error."""
        requests = [self.requests.get()]
        while True:
            try:
                requests.append(self.requests.get_nowait())
            except queue.Empty:
                break
        try:
            results = step_games([game for game, *_ in requests], [action for _, action, *_ in requests])
        except Exception as error:  # noqa: BLE001 - every caller of the round is told
            results = [error] * len(requests)
        for (_, _, loop, future), result in zip(requests, results):
            loop.call_soon_threadsafe(settle, future, result)


def settle(future: asyncio.Future, result: dict | Exception) -> None:
    """A step's future given its view or its exception (unless its game's coroutine stopped waiting)."""
    if future.cancelled():
        return
    if isinstance(result, Exception):
        future.set_exception(result)
    else:
        future.set_result(result)


GAME_STEPS = GameStepper()


def release_freed_memory() -> None:
    """Hands the memory of ended games back to the system. Games step on a worker thread, and glibc keeps what a
    thread freed in that thread's arena: without this a server's resident memory only grows (measured: idle 811 MB,
    994 MB after 40 games of 200 steps had ended, 772 MB once trimmed)."""
    if (trim := _malloc_trim()) is not None:
        trim(0)


def find_runs(root: str = "runs") -> list[str]:
    """Run directories with a checkpoint under `root`."""
    return sorted(str(Path(path).parents[1]) for path in glob.glob(f"{root}/*/seed*/checkpoints/latest.pt"))


def kitchen_names(level_files: list[str]) -> list[str]:
    return [*level_files, *EXPANDED_LAYOUTS, *CLASSIC_LAYOUTS, *PADDED_LAYOUTS, GENERATED,
            *(f"heldout_{i:03d}" for i in range(100))]


@functools.cache
def heldout_layouts() -> dict[str, Layout]:
    """The 100 held-out levels as layouts by name, built once (not at every game)."""
    return {grid.name: grid for grid in evaluation_grids([], 100)}


def checkpoint_version(name: str) -> tuple[int, int] | None:
    """The modification time and size of the checkpoint a partner's name loads (a run directory's latest), None
    for the scripted cook, the random agent or a name with no checkpoint file (which `load_partner` refuses)."""
    try:
        status = checkpoint_file(name).stat()
    except OSError:
        return None
    return status.st_mtime_ns, status.st_size


class Lobby:
    """The server's games made and not yet connected, and how a new one is made: its partner (shared between games,
    `SharedPartners`), its kitchen, its record. A game nobody connects to within `connect_s` seconds expires."""

    def __init__(self, runs: list[str], records: Path, tick_ms: int, device: str, level_files: list[str],
                 max_steps: int, runs_root: str, connect_s: float):
        self.runs, self.records, self.tick_ms, self.device = runs, records, tick_ms, device
        self.level_files, self.max_steps, self.runs_root, self.connect_s = level_files, max_steps, runs_root, connect_s
        self.games: dict[str, tuple[Game, str, float]] = {}  # game id -> (game, mode, made at)
        self.counter = itertools.count()
        self.shared_partner = SharedPartners(device)

    def partners(self) -> list[str]:
        return [*dict.fromkeys([*self.runs, *find_runs(self.runs_root)]), SCRIPTED, RANDOM]

    def expire_unconnected(self) -> None:
        for game_id, (game, _, made) in list(self.games.items()):
            if time.monotonic() - made > self.connect_s and self.games.pop(game_id, None) is not None:
                game.end("never connected")
                log.info("game %s expired: nobody connected within %g s", game_id, self.connect_s)

    def new_game(self, choice: Choice) -> dict:
        """A game as `choice` asks (an HTTP 400 saying why not), waiting for its player under a key nobody can
        guess: {"id", "record"}."""
        self.expire_unconnected()
        if choice.mode not in MODES:
            raise HTTPException(400, f"unknown mode {choice.mode!r}; one of {', '.join(MODES)}")
        if choice.seat not in (0, 1):
            raise HTTPException(400, f"seat must be 0 or 1, got {choice.seat}")
        if choice.partner not in self.partners():
            raise HTTPException(400, f"unknown partner {choice.partner!r}; one of {', '.join(self.partners())}")
        number = next(self.counter)
        seed = choice.seed if choice.seed is not None else int(time.time()) % 100_000 + number
        try:
            layout = make_kitchen(choice.kitchen, self.level_files, seed)
            partner = self.shared_partner(choice.partner)
            record = self.records / f"{time.strftime('%Y%m%d-%H%M%S')}-{number}.jsonl"
            game = Game(layout, partner, choice.seat, record, seed=seed, max_steps=self.max_steps,
                        tick_ms=self.tick_ms, mode=choice.mode, device=self.device)
        except (ValueError, CheckpointError) as error:
            raise HTTPException(400, str(error)) from None
        game_id = secrets.token_urlsafe(16)  # the game's key: whoever holds it plays it, so nobody can guess it
        self.games[game_id] = (game, choice.mode, time.monotonic())
        log.info("game %s: %s with %s on %s, seat %d", game_id, choice.mode, partner.name, layout.name, choice.seat)
        return {"id": game_id, "record": str(game.recorder.path)}


class SharedPartners:
    """The partners of a server's games, each loaded once per version of its checkpoint (a run still training
    writes a new latest one): games with one partner then share it, and its forward pass runs once a round
    (`GameStepper`), and a new game costs a kitchen, not a checkpoint read."""

    def __init__(self, device: str):
        self.device, self.loaded, self.lock = device, {}, threading.Lock()

    def __call__(self, name: str) -> Partner:
        version = checkpoint_version(name)
        with self.lock:
            cached = self.loaded.get(name)
            if cached is None or cached[0] != version:
                self.loaded[name] = (version, load_partner(name, self.device))
            return self.loaded[name][1]


def make_kitchen(name: str, level_files: list[str], seed: int) -> Layout:
    """The layout of a lobby choice; ValueError naming the choices otherwise."""
    if name == GENERATED:
        level = sample_training_level(jax.random.PRNGKey(seed), GeneratorConfig(), heldout_grids())
        return layout_from_state(level, name=f"generated_{seed}")
    if name.startswith("heldout_"):
        if name in heldout_layouts():
            return heldout_layouts()[name]
    elif name in kitchen_names(level_files):
        return load_layout(name)
    raise ValueError(f"unknown kitchen {name!r}: choose a layout name ({', '.join(EXPANDED_LAYOUTS)}, ...), "
                     f"heldout_000..heldout_099, {GENERATED!r} or a level file given on the command line")


MAX_MESSAGE = 256  # characters: an action message is about 40
EXPECTED = f'expected {{"type": "action", "action": ...}} with the action one of {", ".join(ACTIONS)}'


def parse_action(text: str) -> int:
    """The action index of a client message {"type": "action", "action": "left"}; ValueError says, in one short
    line, what is wrong (never echoing more than a few characters of the message)."""
    if len(text) > MAX_MESSAGE:
        raise ValueError(f"message of {len(text):,} characters; {EXPECTED}")
    try:
        return ACTIONS[ActionMessage.model_validate_json(text).action]
    except ValidationError as error:  # bad JSON, too deep, wrong fields or values
        first = error.errors()[0]
        where = f" at {'.'.join(map(str, first['loc']))}" if first["loc"] else ""
        raise ValueError(f"{first['msg']}{where}; {EXPECTED}"[:300]) from None


def drawing_script() -> str:
    """The script that draws a game's state and maps keys to actions (static/kitchen.js), shared by every page that
    shows a game."""
    return (STATIC / "kitchen.js").read_text(encoding="utf-8")


def page_html(name: str) -> str:
    """A page of static/ with the drawing script inlined where it names it, so that a page is one request, answered
    behind the same host and token checks as the rest."""
    return (STATIC / name).read_text(encoding="utf-8").replace('<script src="kitchen.js"></script>',
                                                              f"<script>\n{drawing_script()}</script>")


def token_admits(token: str | None, given: str | None) -> bool:
    """Whether a request carrying `given` may be answered by a server whose key is `token` (None: any request)."""
    return token is None or (given is not None and secrets.compare_digest(given.encode(), token.encode()))


def guard(app: FastAPI, hosts: list[str] | None, token: str | None):
    """Answers only `hosts` as Host (None: any) and, with a `token`, only requests carrying `?token=<token>`, on
    every HTTP request of `app`; returns the same check for a WebSocket, which also needs its page's own origin."""

    def known(host: str | None) -> bool:
        return hosts is None or host in hosts

    @app.middleware("http")
    async def known_host(request, call_next):
        if not known(request.headers.get("host")):
            return HTMLResponse(f"unknown host {request.headers.get('host')!r}", status_code=400)
        if not token_admits(token, request.query_params.get("token")):
            return HTMLResponse(NO_TOKEN, status_code=403)
        return await call_next(request)

    def admits(websocket: WebSocket) -> bool:
        host, origin = websocket.headers.get("host"), websocket.headers.get("origin")
        if known(host) and same_origin(origin, host) and token_admits(token, websocket.query_params.get("token")):
            return True
        log.warning("refused a connection from origin %r to host %r (or without the token)", origin, host)
        return False

    return admits


class AddressError(RuntimeError):
    """No server can serve on the address asked for; its message is the one line the command prints."""


def listening_socket(host: str, port: int) -> socket.socket:
    """A socket listening on host:port (port 0: a free port, `getsockname()` says which), taken before a server's
    slow start so that no other process can take the address meanwhile (a connection made during the start waits
    to be answered) and a busy one is said before any address is printed. Bound as uvicorn binds: a server started
    again at once after a kill finds its port's old connections in TIME_WAIT, which do not keep it."""
    listener = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        listener.bind((host, port))
        listener.listen(2048)
    except OSError as failure:
        listener.close()
        raise AddressError(f"cannot serve on {host}:{port}: {failure.strerror} "
                           "(another server there? choose another --port)") from None
    return listener


def serve(app, listener: socket.socket) -> None:
    """uvicorn serving `app` on `listener` until SIGTERM or SIGINT; a handler still running 5 s after is cancelled."""
    import uvicorn

    uvicorn.Server(uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=5)).run(sockets=[listener])


def served_hosts(host: str, port: int, allowed: list[str]) -> list[str]:
    """The Host headers a server on host:port answers: its own address, this machine's names, and `allowed`."""
    return [*(f"{name}:{port}" for name in dict.fromkeys([host, "127.0.0.1", "localhost"])), *allowed]


def same_origin(origin: str | None, host: str | None) -> bool:
    """Whether a browser's Origin header names the server it connects to (a client outside a browser sends
    none): a page served from anywhere else may not play, or take over, a game."""
    return origin is None or (host is not None and origin in (f"http://{host}", f"https://{host}"))


async def receive_actions(websocket: WebSocket, game_id: str, pending: asyncio.Queue, latest: list[int]) -> None:
    """Reads the player's messages until the socket closes: each action into `pending` and `latest[0]`; a message
    it cannot use is answered with an error and logged, and the game goes on. None into `pending` at the end."""
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                break
            try:
                if message.get("text") is None:
                    raise ValueError(f"a binary frame; {EXPECTED}, as text")
                action = parse_action(message["text"])
            except ValueError as error:
                log.warning("game %s: refused message %r: %s", game_id, str(message.get("text"))[:80], error)
                await websocket.send_json({"type": "error", "reason": str(error)})
                continue
            latest[0] = action
            await pending.put(action)
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        await pending.put(None)


async def play_game(websocket: WebSocket, game_id: str, game: Game, mode: str, tick_ms: int, idle_s: float) -> None:
    """Plays `game` with the player connected on `websocket` until it ends: in "turns" mode a step per action (the
    game ends after `idle_s` seconds without one), else a step every `tick_ms` with the player's latest action.
    Ends the game with its reason (finished, idle, disconnected) and hands its memory back."""
    pending: asyncio.Queue[int | None] = asyncio.Queue()
    latest = [STAY]
    receiver = asyncio.create_task(receive_actions(websocket, game_id, pending, latest))
    loop = asyncio.get_running_loop()
    reason = "disconnected"
    try:
        await websocket.send_json(game.view())
        next_tick = loop.time()
        while not game.over:
            if mode == "turns":
                try:
                    action = await asyncio.wait_for(pending.get(), idle_s)
                except TimeoutError:
                    reason = "idle"
                    await websocket.send_json({"type": "error", "reason": f"no action for {idle_s:g} s: "
                                                                          "the game ended"})
                    break
                if action is None:
                    break
            else:  # ticks on a fixed schedule: the time a step takes does not delay the next one
                next_tick += tick_ms / 1000
                await asyncio.sleep(max(0.0, next_tick - loop.time()))
                if receiver.done():
                    break
                action, latest[0] = latest[0], STAY
            # The step runs on the one stepping thread, in a round with the other games' (`GameStepper`): the event
            # loop keeps serving the other games meanwhile, and no two steps contend for the GIL.
            await websocket.send_json(await GAME_STEPS.step(game, action))
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        receiver.cancel()
        reason = "finished" if game.t >= game.max_steps else reason
        game.end(reason)
        log.info("game %s ended (%s) after %d steps, score %d", game_id, reason, game.t, game.score)
    del game  # its kitchen and tensors freed, then handed back
    await asyncio.to_thread(release_freed_memory)
    if reason in ("finished", "idle"):
        try:
            await websocket.close()
        except (WebSocketDisconnect, RuntimeError):
            pass  # the player left first


def create_app(runs: list[str] = (), records: str | Path = "games", tick_ms: int = 150, device: str = "cpu",
               level_files: list[str] = (), max_steps: int = 400, runs_root: str = "runs",
               idle_s: float = 600.0, hosts: list[str] | None = None, connect_s: float = 120.0,
               token: str | None = None) -> FastAPI:
    """The web app: lobby, game creation and the games' WebSockets. A turns-mode game whose player sends no
    action for `idle_s` seconds ends ("idle"); a game nobody connects to within `connect_s` seconds expires
    ("never connected"). `hosts`: the Host headers the server answers to (against DNS rebinding; None: any).
    `token`: a study's participants' key; when set, every page, request and game needs `?token=<token>`."""
    if FastAPI is None:
        raise ImportError("kitchen-play needs the play extra: pip install .[play]")
    app = FastAPI(title="kitchen-play")
    admits = guard(app, hosts, token)
    lobby = Lobby(list(runs), Path(records), tick_ms, device, list(level_files), max_steps, runs_root, connect_s)

    @app.get("/", response_class=HTMLResponse)
    def index() -> str:
        return page_html("index.html")

    @app.get("/api/options")
    def options() -> dict:
        return {"partners": lobby.partners(), "kitchens": kitchen_names(lobby.level_files), "modes": list(MODES),
                "tick_ms": tick_ms}

    @app.post("/api/games")
    def new_game(choice: Choice) -> dict:
        return lobby.new_game(choice)

    @app.websocket("/ws/games/{game_id}")
    async def play(websocket: WebSocket, game_id: str) -> None:
        if not admits(websocket):
            await websocket.close(code=1008)  # policy violation, before accepting: the game stays its owner's
            return
        await websocket.accept()
        lobby.expire_unconnected()
        if game_id not in lobby.games:
            await websocket.send_json({"type": "error", "reason": "no such game waiting (ended, expired or taken)"})
            await websocket.close()
            return
        # One connection per game; the game is held by `play_game` alone, which frees it when it ends.
        await play_game(websocket, game_id, *lobby.games.pop(game_id)[:2], tick_ms, idle_s)

    return app


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["replay"]:
        parser = argparse.ArgumentParser(prog="kitchen-play replay",
                                         description="Replay a recorded game through the JAX env and check it.")
        parser.add_argument("record")
        parser.add_argument("--gif", help="also write the game as an animated GIF")
        args = parser.parse_args(argv[1:])
        try:
            result = replay(args.record, args.gif)
        except (ValueError, OSError) as error:
            print(f"kitchen-play: error: {error}", file=sys.stderr)
            return 1
        print(f"{args.record}: {result['steps']} steps replayed exactly, score {result['score']}"
              + (f", gif {args.gif}" if args.gif else ""))
        return 0
    parser = argparse.ArgumentParser(prog="kitchen-play", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="*", help="run directories or checkpoints to offer as partners")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000, help="0: any free port (the link says which)")
    parser.add_argument("--records", default="games", help="folder of the games' JSON Lines records")
    parser.add_argument("--tick-ms", type=int, default=150, help="milliseconds per step in real time")
    parser.add_argument("--max-steps", type=int, default=400, help="steps per game")
    parser.add_argument("--idle-s", type=float, default=600.0,
                        help="seconds without an action after which a turns-mode game ends")
    parser.add_argument("--allow-host", action="append", default=[], metavar="HOST[:PORT]",
                        help="another Host header to answer to (a study behind a proxy); the server's own address "
                             "and localhost are always allowed")
    parser.add_argument("--token", help="a key for a study's participants: the server answers only links carrying "
                             "it (?token=...); 'random' makes one, printed in the link")
    parser.add_argument("--levels", nargs="*", default=[], help="level files to offer as kitchens")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    for flag, value in (("--tick-ms", args.tick_ms), ("--max-steps", args.max_steps), ("--idle-s", args.idle_s)):
        if value <= 0:
            parser.error(f"{flag} must be positive, got {value:g}")
    try:
        listener = listening_socket(args.host, args.port)
    except AddressError as busy:
        print(f"kitchen-play: error: {busy}", file=sys.stderr)
        return 2
    port = listener.getsockname()[1]
    token = secrets.token_urlsafe(16) if args.token == "random" else args.token
    try:
        app = create_app(args.runs, args.records, args.tick_ms, args.device, args.levels, args.max_steps,
                         idle_s=args.idle_s, hosts=served_hosts(args.host, port, args.allow_host), token=token)
    except ImportError as error:
        listener.close()
        print(f"kitchen-play: error: {error}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    link = f"http://{args.host}:{port}/" + (f"?token={token}" if token else "")
    print(f"kitchen-play: open {link} (records in {args.records}/)", flush=True)
    # On SIGTERM or SIGINT every game's socket is closed, which ends its game with the record complete; a handler
    # still running after 5 s is cancelled, which ends its game too.
    serve(app, listener)
    return 0


if __name__ == "__main__":
    sys.exit(main())
