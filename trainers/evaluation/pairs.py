"""Playing the pairs: who plays with whom (`make_matchups`), the test grids (`evaluation_grids`), and `play`, which
plays every pair on every grid in batches of kitchens, in one process or in `workers` spawned ones."""

from __future__ import annotations

import math
import multiprocessing
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import jax
import numpy as np
import torch
from tqdm import tqdm

from jax_env import GeneratorConfig, Layout, heldout_levels, layout_from_state, load_layout
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.events import EVENTS
from torch_kitchen.partners.pairing import make_seated_actor
from trainers.checkpoint import CheckpointError
from trainers.evaluation.teams import Team
from trainers.ppo.collection import play_episodes

SP, XP, CROSS, PARTNER, HUMAN, STRANGER = "SP", "XP", "cross", "partner", "human proxy", "stranger"


# --------------------------------------------------------------------------------------------- matchups
@dataclass(frozen=True)
class Matchup:
    """Agent 0 of teams[seat0] with agent 1 of teams[seat1]; kind SP, XP (same condition) or cross."""

    seat0: int
    seat1: int
    kind: str


def make_matchups(population: dict[str, list[Team]], cross: Sequence[Sequence[str]] = (), partner: Team | None = None):
    """(teams, matchups): every ordered pair within each condition, both orders across each `cross` pair, and with
    a `partner`: every team with it in both seats (kind "partner") and the partner's own self-play."""
    teams = [team for members in population.values() for team in members]
    index = {id(team): i for i, team in enumerate(teams)}
    matchups = []
    for members in population.values():
        for a in members:
            for b in members:
                matchups.append(Matchup(index[id(a)], index[id(b)], SP if a is b else XP))
    for first, second in cross:
        for a in population[first]:
            for b in population[second]:
                matchups += [Matchup(index[id(a)], index[id(b)], CROSS), Matchup(index[id(b)], index[id(a)], CROSS)]
    if partner is not None:
        seat = len(teams)
        teams.append(partner)
        for team in range(seat):
            matchups += [Matchup(team, seat, PARTNER), Matchup(seat, team, PARTNER)]
        matchups.append(Matchup(seat, seat, SP))
    return teams, matchups


def evaluation_grids(layouts: Sequence[str], num_heldout: int = 100, size: int = 7) -> list[Layout]:
    """The given layouts (names or text-grid files), then the first `num_heldout` of the 100 held-out generated
    levels of `size` x `size`, named heldout_000, heldout_001, ..."""
    generated = heldout_levels(GeneratorConfig(size=size))
    heldout = [
        layout_from_state(jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], generated), name=f"heldout_{i:03d}")
        for i in range(min(num_heldout, int(generated.grid.shape[0])))
    ]
    return [load_layout(name) for name in layouts] + heldout


def cross_condition(first: str, second: str) -> str:
    """The summary's name of the cross-play between two conditions, whichever order they are given in."""
    return " x ".join(sorted((first, second)))


def is_heldout(grid_name: str) -> bool:
    return grid_name.startswith("heldout_")


# ------------------------------------------------------------------------------------------------ playing
@dataclass
class Outcomes:
    """deliveries float32 [M, G, R] of every matchup, grid and rollout; visits float32 [M, G, 2, H, W], the steps
    each seat spent on each cell, and events float32 [M, G, 2, E], how often each seat made each of
    `torch_kitchen.events.EVENTS` happen, both summed over rollouts."""

    teams: list[Team]
    matchups: list[Matchup]
    grids: list[Layout]
    deliveries: np.ndarray
    visits: np.ndarray
    events: np.ndarray


@dataclass(frozen=True)
class Batches:
    """How `play` cuts every matchup's rollouts on every grid into batches of kitchens: a unit is one matchup's
    one rollout on every grid, `per_batch` units a batch; batch b plays with seed `seed + b`, whichever process
    plays it, so that the numbers do not depend on how many do."""

    teams: list[Team]
    matchups: list[Matchup]
    grids: list[Layout]
    rollouts: int
    max_steps: int
    per_batch: int
    seed: int
    device: str
    collector: str = "kitchen"  # `trainers.ppo.collection.make_collector`'s kind: "xla" plays inside XLA where it can

    @property
    def units(self) -> int:
        return len(self.matchups) * self.rollouts

    def __len__(self) -> int:
        return math.ceil(self.units / self.per_batch)


class BatchPlayer:
    """Plays the batches of a `Batches` one at a time in one kitchen env of `per_batch` x grids kitchens."""

    def __init__(self, batches: Batches):
        self.batches = batches
        num_kitchens = batches.per_batch * len(batches.grids)
        self.kitchen = KitchenEnv(num_kitchens, levels=batches.grids, max_steps=batches.max_steps,
                                  device=batches.device, seed=batches.seed, pin_levels=True)
        self.actor = make_seated_actor([team.actor_critic.actor for team in batches.teams])
        self.seated = self.actor.module[0]
        self.env = with_transforms(self.kitchen, self.seated.env_transforms())
        self.seat_of_matchup = torch.tensor([[m.seat0, m.seat1] for m in batches.matchups], device=batches.device)

    def __call__(self, batch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Batch `batch`'s units [n], their deliveries [n, G], the cells their seats visited [n, G, 2, H, W] and
        their seats' events [n, G, 2, E]."""
        b = self.batches
        num_grids = len(b.grids)
        torch.manual_seed(b.seed + batch)
        self.kitchen.set_seed(b.seed + batch)
        # Kitchen k plays unit first + k // G on grid k % G; the last batch repeats its last unit to stay full.
        unit = (torch.arange(b.per_batch, device=b.device) + batch * b.per_batch).clamp(max=b.units - 1)
        self.seated.seat(self.seat_of_matchup[unit.repeat_interleave(num_grids) // b.rollouts])
        with torch.no_grad():
            outcome = play_episodes(self.env, self.actor, b.max_steps, kind=b.collector)
        fresh = min(b.per_batch, b.units - batch * b.per_batch)
        deliveries = outcome.deliveries.reshape(b.per_batch, num_grids)[:fresh]
        visits = outcome.visits.reshape(b.per_batch, num_grids, *outcome.visits.shape[1:])[:fresh]
        events = outcome.events.reshape(b.per_batch, num_grids, *outcome.events.shape[1:])[:fresh]
        return unit[:fresh].cpu().numpy(), deliveries.cpu().numpy(), visits.cpu().numpy(), events.cpu().numpy()


_worker_player: BatchPlayer | None = None  # a worker process's player (`play` with workers > 1)


def _start_worker(batches: Batches) -> None:
    global _worker_player
    torch.set_num_threads(1)
    _worker_player = BatchPlayer(batches)


def _play_in_worker(batch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return _worker_player(batch)


def play(
    teams: list[Team],
    matchups: list[Matchup],
    grids: list[Layout],
    rollouts: int,
    max_steps: int = 256,
    max_envs: int = 8192,
    seed: int = 0,
    device: str = "cpu",
    progress: bool = False,
    workers: int = 1,
    collector: str = "kitchen",
) -> Outcomes:
    """Every matchup plays `rollouts` episodes on every grid, in batches of at most `max_envs` kitchens, played by
    `workers` processes at once (the same numbers with any), by the `collector` (`make_collector`'s kind: "xla"
    plays a batch inside one XLA program where its teams allow, its actions drawn by JAX)."""
    shapes = {(*grid.shape, 26) for grid in grids}
    if len(shapes) != 1:
        raise ValueError(f"the test grids must share one size, got {sorted(shapes)}")
    (obs_shape,) = shapes
    for team in teams:
        if team.obs_shape != obs_shape:
            raise CheckpointError(
                f"{team.name} ({team.checkpoint}) was built for {team.obs_shape[0]}x{team.obs_shape[1]} kitchens, "
                f"the test grids are {obs_shape[0]}x{obs_shape[1]}: evaluate it on grids of its own size"
            )
    num_grids, units = len(grids), len(matchups) * rollouts
    # As few batches as `max_envs` allows, of equal size: processes that share them finish together.
    per_batch = math.ceil(units / math.ceil(units / max(1, max_envs // num_grids)))
    batches = Batches(teams, matchups, grids, rollouts, max_steps, per_batch, seed, device, collector)
    height, width = obs_shape[:2]
    deliveries = np.zeros((units, num_grids), np.float32)
    visits = np.zeros((len(matchups), num_grids, 2, height, width), np.float32)
    events = np.zeros((len(matchups), num_grids, 2, len(EVENTS)), np.float32)
    bar = tqdm(total=units * num_grids, unit="episode", unit_scale=True, disable=not progress, desc="evaluating")
    workers = min(workers, len(batches))
    if workers > 1:
        # Spawned, not forked: a fork of a process that has started JAX's threads may hang.
        pool = ProcessPoolExecutor(workers, multiprocessing.get_context("spawn"), _start_worker, (batches,))
        played = pool.map(_play_in_worker, range(len(batches)))
    else:
        pool, played = None, map(BatchPlayer(batches), range(len(batches)))
    try:
        for unit, got, seen, happened in played:
            deliveries[unit] = got
            np.add.at(visits, unit // rollouts, seen)
            np.add.at(events, unit // rollouts, happened)
            bar.update(got.size)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
    deliveries = deliveries.reshape(len(matchups), rollouts, num_grids).transpose(0, 2, 1)
    return Outcomes(teams, matchups, grids, deliveries, visits, events)
