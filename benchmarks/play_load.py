"""How many real-time games of `kitchen-play` one CPU core holds: the server's work per tick, then games at once.

Per partner (an MLP and a GNN team of the paper's width, hidden 256; untrained weights time the same): the
latency of one tick of one game (`play.game.Game.step`: the partner's forward pass, the kitchen's step, the record
line), its median and 95th percentile, and the games one core could tick every `--tick-ms` from that; then that
many games (and more) at once, each a WebSocket client of a real `kitchen-play` server in this process (one event
loop, torch on one thread), reporting the mean and the 95th percentile of the interval between a game's ticks
against the target.

    python benchmarks/play_load.py [--tick-ms 150] [--seconds 10] [--partners mlp gnn]
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
from play.game import Game, Partner
from play.server import create_app
from torch_kitchen.models import make_actor_critic
from trainers.checkpoint import model_identity, save_checkpoint
from trainers.config import TrainConfig
from trainers.machine import machine_name

KITCHEN = "cramped_room_7x7"


def save_team(path: Path, architecture: str) -> str:
    actor_critic = make_actor_critic(architecture, (7, 7, 26), 256, True)
    save_checkpoint(path / "checkpoints" / "latest.pt", {
        "config": TrainConfig(architecture=architecture).to_dict(),
        "model": model_identity(architecture, (7, 7, 26), 256, True),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
    return str(path)


def tick_latency(architecture: str, records: Path, ticks: int = 300) -> list[float]:
    """Seconds per `Game.step` of one game, after 20 warm-up ticks."""
    partner = Partner(architecture, make_actor_critic(architecture, (7, 7, 26), 256, True), (7, 7, 26))
    game = Game(load_layout(KITCHEN), partner, 0, records / f"latency_{architecture}.jsonl", max_steps=ticks + 20)
    times = []
    for t in range(ticks + 20):
        started = time.perf_counter()
        game.step(t % 6)
        if t >= 20:
            times.append(time.perf_counter() - started)
    return times


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
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    tick = args.tick_ms / 1000
    print(f"{machine_name()}, torch threads 1, "
          f"tick {args.tick_ms} ms, kitchen {KITCHEN}")
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        runs = {architecture: save_team(scratch / "runs" / architecture / "seed0", architecture)
                for architecture in args.partners}
        app = create_app(list(runs.values()), records=scratch / "games", tick_ms=args.tick_ms, max_steps=100_000)
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        import uvicorn

        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        serving = threading.Thread(target=server.run)
        serving.start()
        while not server.started:
            time.sleep(0.05)
        print(f"{'partner':>8s} {'tick p50 ms':>12s} {'tick p95 ms':>12s} {'games/core':>11s} {'games':>6s} "
              f"{'interval mean ms':>17s} {'interval p95 ms':>16s}")
        for architecture, run in runs.items():
            latency = sorted(tick_latency(architecture, scratch))
            p50, p95 = statistics.median(latency), latency[int(0.95 * len(latency))]
            capacity = int(tick / p95)
            for games in sorted({max(1, capacity // 2), max(1, capacity)}):
                intervals = sorted(asyncio.run(play_games(f"http://127.0.0.1:{port}", run, games, args.seconds)))
                mean, late = statistics.mean(intervals), intervals[int(0.95 * len(intervals))]
                print(f"{architecture:>8s} {p50 * 1e3:12.2f} {p95 * 1e3:12.2f} {capacity:11d} {games:6d} "
                      f"{mean * 1e3:17.1f} {late * 1e3:16.1f}", flush=True)
        server.should_exit = True  # and wait for it: a thread still serving at exit aborts the interpreter
        serving.join()


if __name__ == "__main__":
    main()
