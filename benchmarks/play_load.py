"""How many real-time games of `kitchen-play` one CPU core holds: the server's work per tick, then games at once.

Per partner (an MLP and a GNN team of the paper's width, hidden 256; untrained weights time the same): the
latency of one tick of one game (`web_apps.play.game.Game.step`: the partner's forward pass, the kitchen's step,
the record line), its median and 95th percentile, and the games one core could tick every `--tick-ms` from that;
then that many games (and more) at once, each a WebSocket client of a real `kitchen-play` server in this process
(one event loop, torch on one thread), reporting the mean and the 95th percentile of the interval between a game's ticks
against the target. Then a study's load (`--games`, 40 by default): that many whole real-time games with the MLP
team at once, each client sending a key on every state it gets: the time to create each game, the gaps between a
game's states (p50, p90, p99, max), how far behind schedule games end, and the server process's resident memory
idle (after one warm-up game), with the games running, and after they ended. With `--rounds N` (20 by default),
first the cost of a game's tick where N games share a partner (each of `--partners` and the scripted cook), stepped
one game after another and as the server's stepping thread takes them, one round (`step_games`).

    python benchmarks/play_load.py [--tick-ms 150] [--seconds 10] [--partners mlp gnn] [--games 40]
        [--game-steps 200] [--skip-capacity] [--rounds 20]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path

import torch

from jax_env import load_layout
from torch_kitchen.models import make_actor_critic, model_identity
from trainers.checkpoint import save_checkpoint
from trainers.config import TrainConfig
from trainers.machine import machine_name
from web_apps.play.game import SCRIPTED, Game, Partner, load_partner, step_games
from web_apps.play.server import create_app

KITCHEN = "cramped_room_7x7"


def save_team(path: Path, architecture: str) -> str:
    actor_critic = make_actor_critic(architecture, (7, 7, 26), 256, True)
    save_checkpoint(path / "checkpoints" / "latest.pt", {
        "config": TrainConfig(architecture=architecture).to_dict(),
        "model": model_identity(architecture, (7, 7, 26), 256, True),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
    return str(path)


def untrained_partner(architecture: str) -> Partner:
    """A team of the paper's width on 7x7 kitchens (untrained weights time the same)."""
    return Partner(architecture, make_actor_critic(architecture, (7, 7, 26), 256, True), (7, 7, 26))


def tick_latency(architecture: str, records: Path, ticks: int = 300) -> list[float]:
    """Seconds per `Game.step` of one game, after 20 warm-up ticks."""
    partner = untrained_partner(architecture)
    game = Game(load_layout(KITCHEN), partner, 0, records / f"latency_{architecture}.jsonl", max_steps=ticks + 20)
    times = []
    for t in range(ticks + 20):
        started = time.perf_counter()
        game.step(t % 6)
        if t >= 20:
            times.append(time.perf_counter() - started)
    return times


def round_cost(partner: Partner, games: int, records: Path, ticks: int = 50) -> tuple[float, float]:
    """Seconds per game tick of `games` games sharing `partner` on 7x7 kitchens, stepped one after another and
    as one round (`step_games`: the partner's forward pass once for all), after 10 warm-up rounds."""
    layouts = [load_layout(KITCHEN), load_layout("coord_ring_7x7")]
    playing = [Game(layouts[index % 2], partner, 0, records / f"round_{partner.name}_{index}.jsonl", seed=index,
                    max_steps=10 * ticks) for index in range(games)]
    for t in range(10):
        step_games(playing, [t % 6] * games)
    seconds = []
    for in_rounds in (False, True):
        started = time.perf_counter()
        for t in range(ticks):
            if in_rounds:
                step_games(playing, [t % 6] * games)
            else:
                for game in playing:
                    game.step(t % 6)
        seconds.append((time.perf_counter() - started) / (ticks * games))
    return seconds[0], seconds[1]


def resident_mb(pid: int | str = "self") -> float:
    """A process's resident memory (Linux's /proc; this one by default), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def state_gaps(arrivals: list[float]) -> list[float]:
    """Seconds between a game's consecutive states as they arrived, from the second on (the first state comes
    when the game connects, the second on the first tick's schedule)."""
    return [b - a for a, b in zip(arrivals[1:], arrivals[2:])]


def schedule_lag(arrivals: list[float], steps: int, tick: float) -> float:
    """How late (s) a game's last state of `steps` came against a tick every `tick` s from its first state."""
    return arrivals[-1] - (arrivals[0] + steps * tick)


GAPS_HEADER = f"{'gap p50 ms':>10s} {'gap p90 ms':>10s} {'gap p99 ms':>10s} {'gap max ms':>10s}"


def gaps_row(gaps: list[float]) -> str:
    """The p50, p90, p99 and max of sorted `gaps` (s) in ms, under GAPS_HEADER."""
    return " ".join(f"{value * 1e3:10.1f}" for value in (quantile(gaps, 0.5), quantile(gaps, 0.9),
                                                          quantile(gaps, 0.99), gaps[-1]))


class Serving:
    """A `kitchen-play` app served by uvicorn on a free loopback port, on a thread of this process."""

    def __init__(self, app):
        import uvicorn

        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            self.url = f"http://127.0.0.1:{probe.getsockname()[1]}"
        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=int(self.url.rsplit(":", 1)[1]),
                                                    log_level="warning"))

    def __enter__(self) -> str:
        self.thread = threading.Thread(target=self.server.run)
        self.thread.start()
        while not self.server.started:
            time.sleep(0.05)
        return self.url

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True  # and wait for it: a thread still serving at exit aborts the interpreter
        self.thread.join()


async def study(url: str, partner: str, games: int, tick: float) -> dict:
    """`games` whole real-time games at once, each client sending a random key on every state it receives."""
    import random

    import httpx
    import websockets

    created = []
    async with httpx.AsyncClient(base_url=url, timeout=120) as client:
        ids = []
        for _ in range(games):
            started = time.perf_counter()
            choice = {"partner": partner, "kitchen": KITCHEN, "mode": "realtime"}
            response = await client.post("/api/games", json=choice)
            response.raise_for_status()
            created.append(time.perf_counter() - started)
            ids.append(response.json()["id"])
    peak = [resident_mb()]

    async def one(game_id: str) -> tuple[list[float], float]:
        keys = random.Random(game_id)
        arrivals, steps = [], 0
        async with websockets.connect(f"{url.replace('http', 'ws')}/ws/games/{game_id}") as ws:
            async for message in ws:
                state = json.loads(message)
                arrivals.append(time.perf_counter())
                steps = state["t"]
                if state["over"]:
                    break
                await ws.send(json.dumps({"type": "action", "action": keys.choice(["up", "down", "left", "right",
                                                                                  "stay", "interact"])}))
                if steps % 50 == 0:
                    peak[0] = max(peak[0], resident_mb())
        return state_gaps(arrivals), schedule_lag(arrivals, steps, tick)

    results = await asyncio.gather(*(one(game_id) for game_id in ids))
    gaps = sorted(gap for intervals, _ in results for gap in intervals)
    lags = sorted(lag for _, lag in results)
    return {"created": sorted(created), "gaps": gaps, "lags": lags, "peak_mb": peak[0]}


def quantile(values: list[float], q: float) -> float:
    return values[min(len(values) - 1, int(q * len(values)))]


def run_study(partner_run: str, games: int, steps: int, tick_ms: int, records: Path) -> None:
    import gc

    app = create_app([partner_run], records=records, tick_ms=tick_ms, max_steps=steps)
    tick = tick_ms / 1000
    with Serving(app) as url:
        asyncio.run(study(url, partner_run, 1, tick))  # warm-up: the partner loaded, the kitchen compiled
        gc.collect()
        idle = resident_mb()
        result = asyncio.run(study(url, partner_run, games, tick))
        gc.collect()
        time.sleep(1.0)
        after = resident_mb()
    created, gaps, lags = result["created"], result["gaps"], result["lags"]
    print(f"\n{games} real-time games at once, mlp team, {steps} steps each, a key on every state")
    print(f"{'create mean s':>13s} {'create max s':>12s} {GAPS_HEADER} {'lag median s':>12s} {'lag max s':>9s} "
          f"{'idle MB':>8s} {'peak MB':>8s} {'after MB':>8s}")
    print(f"{statistics.mean(created):13.3f} {created[-1]:12.3f} {gaps_row(gaps)} {statistics.median(lags):12.2f} "
          f"{lags[-1]:9.2f} {idle:8.0f} {result['peak_mb']:8.0f} {after:8.0f}", flush=True)


async def play_games(url: str, partner: str, games: int, seconds: float) -> list[float]:
    """Intervals (s) between consecutive ticks of `games` real-time games played at once for `seconds`."""
    import httpx
    import websockets

    async with httpx.AsyncClient(base_url=url, timeout=120) as client:
        ids = []
        for _ in range(games):
            choice = {"partner": partner, "kitchen": KITCHEN, "mode": "realtime"}
            response = await client.post("/api/games", json=choice)
            response.raise_for_status()
            ids.append(response.json()["id"])

    async def one(game_id: str) -> list[float]:
        arrivals = []
        async with websockets.connect(f"{url.replace('http', 'ws')}/ws/games/{game_id}") as ws:
            end = time.perf_counter() + seconds
            while time.perf_counter() < end:
                json.loads(await ws.recv())
                arrivals.append(time.perf_counter())
        return [b - a for a, b in zip(arrivals[2:], arrivals[3:])]  # after the first ticks

    results = await asyncio.gather(*(one(game_id) for game_id in ids))
    return [interval for intervals in results for interval in intervals]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tick-ms", type=int, default=150)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--partners", nargs="+", default=["mlp", "gnn"])
    parser.add_argument("--games", type=int, default=40, help="games at once in the study case (0: skip it)")
    parser.add_argument("--game-steps", type=int, default=200, help="steps of each game in the study case")
    parser.add_argument("--skip-capacity", action="store_true", help="only the study case")
    parser.add_argument("--rounds", type=int, default=20,
                        help="games sharing a partner, stepped one by one and as a round, per partner (0: skip)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    tick = args.tick_ms / 1000
    print(f"{machine_name()}, torch threads 1, tick {args.tick_ms} ms, kitchen {KITCHEN}")
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        partners = sorted({*args.partners, "mlp"}) if args.games else args.partners
        runs = {architecture: save_team(scratch / "runs" / architecture / "seed0", architecture)
                for architecture in partners}
        if not args.skip_capacity:
            app = create_app([runs[a] for a in args.partners], records=scratch / "games", tick_ms=args.tick_ms,
                             max_steps=100_000)
            with Serving(app) as url:
                print(f"{'partner':>8s} {'tick p50 ms':>12s} {'tick p95 ms':>12s} {'games/core':>11s} {'games':>6s} "
                      f"{'interval mean ms':>17s} {'interval p95 ms':>16s}")
                for architecture in args.partners:
                    latency = sorted(tick_latency(architecture, scratch))
                    p50, p95 = statistics.median(latency), latency[int(0.95 * len(latency))]
                    capacity = int(tick / p95)
                    for games in sorted({max(1, capacity // 2), max(1, capacity)}):
                        intervals = sorted(asyncio.run(play_games(url, runs[architecture], games, args.seconds)))
                        mean, late = statistics.mean(intervals), intervals[int(0.95 * len(intervals))]
                        print(f"{architecture:>8s} {p50 * 1e3:12.2f} {p95 * 1e3:12.2f} {capacity:11d} {games:6d} "
                              f"{mean * 1e3:17.1f} {late * 1e3:16.1f}", flush=True)
        if args.rounds:
            print(f"\n{args.rounds} games sharing a partner: ms per game tick, one game after another and as one "
                  f"round (step_games)\n{'partner':>14s} {'one by one':>11s} {'a round':>8s}")
            for name in [*args.partners, SCRIPTED]:
                partner = load_partner(SCRIPTED) if name == SCRIPTED else untrained_partner(name)
                alone, together = round_cost(partner, args.rounds, scratch / "rounds")
                print(f"{name:>14s} {alone * 1e3:11.2f} {together * 1e3:8.2f}", flush=True)
        if args.games:
            run_study(runs["mlp"], args.games, args.game_steps, args.tick_ms, scratch / "study")


if __name__ == "__main__":
    main()
