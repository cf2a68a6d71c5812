"""A study's load: N participants at once through one `kitchen-study run` server, each a whole visit in real time.

Each participant is a simulated one (`web_apps.study.client.Participant`: the pages' own protocol, HTTP for the
stages and a WebSocket for the games; a thread each, in this process) that enters by the study's link, consents,
reads the instructions, plays the practice game and its assigned games, sending a random key on every state it
gets, and answers the questions after each game. The study: an MLP team of the paper's width (hidden 256, as
`play_load.py`) and the scripted cook, one game with each on 7x7 kitchens after a practice game with the scripted
cook. The server is a subprocess (torch on `--torch-threads`, as `play_load.py` runs kitchen-play's), which warms its
kitchens and partners up before it serves; then all N start at once. Reported, measured as `play_load.py` measures
kitchen-play's 40 games: the gaps between a game's states across all games (p50, p90, p99, max), how long a game's
first state took from the opening of its page's socket (p50, p99, max), how late games ended against their
schedule, the server's start (to its first answer) and resident memory idle and at its peak; and whether every
participant finished with the answers it posted stored in the database, each game finished once, none cut.

    python benchmarks/study_load.py [--participants 40] [--tick-ms 150] [--game-steps 200] [--practice-steps 200]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import yaml
from play_load import GAPS_HEADER, gaps_row, quantile, resident_mb, save_team, schedule_lag, state_gaps

from trainers.machine import machine_name
from web_apps.study.client import (
    Participant,
    ServerTransport,
    base_url,
    loopback_listener,
    start_server,
    wait_until_serving,
)
from web_apps.study.config import load_study
from web_apps.study.database import CUT, DATABASE, FINISHED, StudyDatabase

TOKEN = "study-load"
KITCHENS = ["cramped_room_7x7", "coord_ring_7x7"]


def write_study(folder: Path, team: str, tick_ms: int, game_steps: int, practice_steps: int) -> Path:
    """The benchmark's study config: the team and the scripted cook, one real-time game each after a practice."""
    values = {
        "name": "load", "seed": 0, "out_dir": str(folder / "study"), "conditions": {"team": team, "cook":
        "scripted_cook"}, "kitchens": KITCHENS, "practice_games": 1, "pace": "realtime", "tick_ms": tick_ms,
        "max_steps": game_steps, "practice_steps": practice_steps,
    }  # fmt: skip
    path = folder / "study.yaml"
    path.write_text(yaml.safe_dump(values))
    return path


class Visit:
    """One participant's visit on its own thread: the times its games' states arrived, and how it went."""

    def __init__(self, base: str, external_id: str, start: threading.Barrier):
        self.arrivals: dict[int, list[float]] = defaultdict(list)  # stage -> arrival times of its states
        self.steps: dict[int, int] = {}  # stage -> the game's last step seen
        self.person = Participant(ServerTransport(base), external_id, TOKEN, on_view=self.seen)
        self.start, self.failure = start, None
        self.thread = threading.Thread(target=self.run)

    def seen(self, stage: int, view: dict) -> None:
        self.arrivals[stage].append(time.perf_counter())
        self.steps[stage] = view["t"]

    def run(self) -> None:
        self.start.wait()
        try:
            self.person.enter()
            while self.person.take_stage() != "complete":
                pass
        except Exception as error:  # reported with the others', not raised on a thread
            self.failure = f"{type(error).__name__}: {error}"


def stored_as_posted(database: StudyDatabase, visit: Visit, games_each: int) -> str | None:
    """Why a participant's visit is not in the database as it went (None: it is)."""
    if visit.failure is not None:
        return visit.failure
    row = database.rows("SELECT * FROM participants WHERE key = ?", visit.person.key)[0]
    if row["finished"] is None:
        return "not finished"
    stored = defaultdict(dict)
    for answer in database.rows("SELECT * FROM answers WHERE participant = ?", row["number"]):
        stored[answer["stage"]][answer["item"]] = answer["value"]
    if stored != visit.person.answered:
        return f"answers stored {dict(stored)}, posted {visit.person.answered}"
    games = database.rows("SELECT status FROM games WHERE participant = ?", row["number"])
    if [game["status"] for game in games] != [FINISHED] * games_each:
        return f"games {[game['status'] for game in games]}"
    return None


def report(args, visits: list, serving_s: float, idle: float, peak: float, problems: dict, cut: int) -> int:
    """Prints the run's state gaps, schedule lags, first states and memory, and whether every participant finished
    with its answers stored as posted; returns the exit status (1 where not)."""
    tick = args.tick_ms / 1000
    gaps = sorted(gap for visit in visits for arrivals in visit.arrivals.values() for gap in state_gaps(arrivals))
    lags = sorted(schedule_lag(arrivals, visit.steps[stage], tick) for visit in visits
                  for stage, arrivals in visit.arrivals.items() if len(arrivals) > 1)
    firsts = sorted(arrivals[0] - visit.person.opened[stage] for visit in visits
                    for stage, arrivals in visit.arrivals.items())
    print(f"\n{args.participants} participants at once: a practice game of {args.practice_steps} steps, then 2 games "
          f"of {args.game_steps} (the team's, the scripted cook's), a key on every state, questions after each")
    print(f"{'games':>6s} {GAPS_HEADER} {'lag median s':>12s} {'lag max s':>9s} {'idle MB':>8s} {'peak MB':>8s}")
    if gaps:
        print(f"{len(lags):6d} {gaps_row(gaps)} {statistics.median(lags):12.2f} {lags[-1]:9.2f} {idle:8.0f} "
              f"{peak:8.0f}")
    if firsts:
        print(f"a game's first state after its socket opened: p50 {statistics.median(firsts):.3f} s, p99 "
              f"{quantile(firsts, 0.99):.3f} s, max {firsts[-1]:.3f} s "
              f"({len(firsts)} games); the server answered {serving_s:.1f} s after its start")
    finished = args.participants - len(problems)
    print(f"every participant finished, its answers stored as posted, each game finished once: "
          f"{'yes' if not problems and not cut else 'no'} ({finished} of {args.participants}; {cut} games cut)")
    for external_id, why in list(problems.items())[:5]:
        print(f"  {external_id}: {why[:300]}")
    return 0 if not problems and not cut else 1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--participants", type=int, default=40)
    parser.add_argument("--tick-ms", type=int, default=150)
    parser.add_argument("--game-steps", type=int, default=200, help="steps of each assigned game")
    parser.add_argument("--practice-steps", type=int, default=200)
    parser.add_argument("--torch-threads", type=int, default=1, help="the server's (OMP_NUM_THREADS)")
    args = parser.parse_args(argv)
    print(f"{machine_name()}, server torch threads {args.torch_threads}, tick {args.tick_ms} ms, kitchens "
          f"{', '.join(KITCHENS)}")
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        team = save_team(scratch / "runs" / "mlp" / "seed0", "mlp")
        config = write_study(scratch, team, args.tick_ms, args.game_steps, args.practice_steps)
        listener, log = loopback_listener(), scratch / "server.log"
        base = base_url(listener)
        server = start_server(config, listener, TOKEN, log,
                              env={"OMP_NUM_THREADS": str(args.torch_threads)})
        try:
            started = time.perf_counter()
            wait_until_serving(server, ServerTransport(base), TOKEN, log, timeout_s=180)
            serving_s = time.perf_counter() - started
            idle = resident_mb(server.pid)
            start = threading.Barrier(args.participants)
            visits = [Visit(base, f"P{number}", start) for number in range(args.participants)]
            for visit in visits:
                visit.thread.start()
            peak = idle
            while any(visit.thread.is_alive() for visit in visits):
                peak = max(peak, resident_mb(server.pid))
                time.sleep(0.25)
        finally:
            server.terminate()
            server.wait(timeout=60)
        database = StudyDatabase(scratch / "study" / DATABASE, create=False)
        study = load_study(config, check=False)
        games_each = study.practice_games + study.games
        problems = {visit.person.external_id: why for visit in visits
                    if (why := stored_as_posted(database, visit, games_each)) is not None}
        cut = len(database.rows("SELECT 1 FROM games WHERE status = ?", CUT))
        database.close()
    return report(args, visits, serving_s, idle, peak, problems, cut)


if __name__ == "__main__":
    sys.exit(main())
