"""Self-play and cross-play evaluation of trained teams: the paper's matrices, tables, figures and GIFs.

    kitchen-eval configs/eval/paper.yaml                     # the paper's protocol
    kitchen-eval configs/eval/paper.yaml rollouts=5 heldout=10 out_dir=results/quick

A *population* is a set of conditions (e.g. "ippo_mlp_ik"), each a list of trained teams (its seeds). Every
ordered pair (agent 0 of team i, agent 1 of team j) within a condition plays: self-play (SP) when i == j,
cross-play (XP) otherwise; so does every pair across the conditions named in `cross`. Each pair plays
`rollouts` episodes on every test grid: the 5 expanded classic layouts and the held-out generated levels. With
`partner` on, every team also plays with the scripted cook (`torch_kitchen.scripted`), a partner outside every
training population, in both seats; the cook's own self-play is the reference row.

All pairs x grids x rollouts run as batches of up to `max_envs` kitchens through the rollout routine that
training uses (`trainers.rollout`): kitchen b of a batch is pinned to grid b % G, and a `SeatedPolicy` gives
each kitchen's two seats to the teams of its pair. Actions are sampled, recurrent teams carry their state. Batch b
plays with seed + b, so `workers` processes share the batches and give the numbers of one.
"""

from __future__ import annotations

import argparse
import csv
import glob
import math
import multiprocessing
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm import tqdm

from jax_env import (
    EXPANDED_LAYOUTS,
    GeneratorConfig,
    Layout,
    heldout_levels,
    layout_from_state,
    layout_name,
    load_layout,
)
from jax_env.generator import SIZES as GENERATOR_SIZES
from jax_env.layouts import padded_layouts
from jax_env.render import write_gif
from torch_kitchen.cpu_kernels import accelerate_cpu
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.models import ActorCritic, make_actor_critic
from torch_kitchen.pairing import make_seated_actor
from torch_kitchen.scripted import SCRIPTED_COOK, scripted_actor_critic
from trainers.checkpoint import CheckpointError, load_checkpoint
from trainers.composer import config_help, load_config, save_config
from trainers.config import ConfigError, DeviceConfig, EvalConfig, RuntimeConfig, TrainConfig
from trainers.figures import draw_figures, draw_heatmap, draw_learning_curve
from trainers.plugins import PluginError, add_plugin_option, import_plugins
from trainers.rollout import play_episodes

SP, XP, CROSS, PARTNER, HUMAN = "SP", "XP", "cross", "partner", "human proxy"
HUMAN_PROXY_RUN = "human_proxy_{grid}/seed0"  # a test grid's human proxy in the `human_proxies` folder
SCRIPTED_CONDITION = "scripted cook"


# ------------------------------------------------------------------------------------------------ teams
@dataclass
class Team:
    """A trained team: its name ("<condition>/seed<k>"), training config, networks, kitchen size, and the env steps
    it was trained for (None where its file does not say, e.g. a team saved by hand)."""

    name: str
    condition: str
    config: TrainConfig
    actor_critic: ActorCritic
    obs_shape: tuple[int, int, int]
    checkpoint: str
    env_steps: int | None = None

    @property
    def fully_trained(self) -> bool:
        """Whether the team ran its config's whole budget (False for a run stopped early)."""
        return self.env_steps is None or self.env_steps >= self.config.planned_steps

    @property
    def regime(self) -> str:
        """"IK" (trained on the Infinite Kitchen) or "SK" (on fixed layouts)."""
        return "IK" if self.config.levels == "infinite" else "SK"

    @property
    def home(self) -> set[str] | None:
        """The names of the layouts a Single Kitchen team was trained on (None: an Infinite Kitchen team, at home
        anywhere); a layout file counts by its name, as the grids are named."""
        if self.regime == "IK":
            return None
        levels = self.config.levels
        return {layout_name(level) for level in ([levels] if isinstance(levels, str) else levels)}

    @property
    def label(self) -> str:
        """The team's family in the paper's figures, e.g. "IPPO MLP IK", "E3T GNN SK"."""
        if self.config.architecture == SCRIPTED_COOK:
            return SCRIPTED_CONDITION
        algorithm = self.config.algorithm
        architecture = self.config.architecture.removeprefix(f"{algorithm}_")  # e3t_gnn -> GNN
        return f"{algorithm.upper()} {architecture.upper().replace('_', '+')} {self.regime}"


def load_team(checkpoint: str | Path, device: str = "cpu", condition: str = "") -> Team:
    """The trained team of a checkpoint file or run directory (a CheckpointError says why one is unusable)."""
    state = load_checkpoint(checkpoint, map_location=device)
    where = state["path"]
    try:
        config = load_config(base=state["config"], overrides=[f"runtime.device={device}"])
    except ConfigError as error:
        raise CheckpointError(f"{where} was saved with a config this version cannot read ({error})") from None
    model = state["model"]
    try:
        actor_critic = make_actor_critic(
            model["architecture"], tuple(model["obs_shape"]), model["hidden"], model["share_params"]
        )
    except ValueError as error:
        raise CheckpointError(
            f"{where} holds a {model['architecture']!r} model that cannot be built here ({error}); import the "
            "module that registers that architecture before loading it"
        ) from None
    if torch.device(device).type == "cpu":
        accelerate_cpu(actor_critic.actor, actor_critic.critic)
    try:
        actor_critic.actor.load_state_dict(state["actor"])
        actor_critic.critic.load_state_dict(state["critic"])
    except RuntimeError as error:
        raise CheckpointError(
            f"{where}: the weights do not fit the {model['architecture']!r} model its header describes "
            f"({str(error).splitlines()[0][:200]}); the file was written by another version or altered"
        ) from None
    actor_critic.actor.to(device).eval()
    actor_critic.critic.to(device).eval()
    condition = condition or config.name
    return Team(f"{condition}/seed{config.seed}", condition, config, actor_critic, tuple(model["obs_shape"]), where,
                state.get("env_steps"))


def scripted_cook_team(obs_shape: tuple[int, int, int], device: str = "cpu") -> Team:
    """The scripted cook as a team (both seats), for kitchens of `obs_shape`; at home on every grid."""
    config = TrainConfig(name="scripted_cook", architecture=SCRIPTED_COOK, runtime=RuntimeConfig(device=device))
    return Team("scripted cook", SCRIPTED_CONDITION, config, scripted_actor_critic(), tuple(obs_shape), "(scripted)")


def load_population(conditions: dict[str, str | list[str]], device: str = "cpu") -> dict[str, list[Team]]:
    """Condition name -> its teams, from run directories, checkpoint files or glob patterns of them."""
    population = {}
    for condition, patterns in conditions.items():
        paths = []
        for pattern in [patterns] if isinstance(patterns, str) else patterns:
            matched = sorted(glob.glob(pattern)) if glob.has_magic(pattern) else [pattern]
            if not matched:
                raise CheckpointError(f"condition {condition!r}: no run matches {pattern!r}")
            paths += matched
        teams = []
        for path in paths:
            try:
                teams.append(load_team(path, device, condition))
            except CheckpointError as error:
                raise CheckpointError(f"condition {condition!r}: {error}") from None
        names = [team.name for team in teams]
        for team in teams:  # two runs with one seed: tell them apart by position
            if names.count(team.name) > 1:
                team.name = f"{team.name}#{teams.index(team)}"
        population[condition] = teams
    return population


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


def load_human_proxies(folder: str | Path, grids: Sequence[Layout], device: str = "cpu") -> dict[str, Team]:
    """{grid name: its human proxy} for the test grids that have one in `folder` (`kitchen-humans train`)."""
    found = {grid.name: Path(folder) / HUMAN_PROXY_RUN.format(grid=grid.name) for grid in grids}
    proxies = {name: load_team(run, device) for name, run in found.items() if (run / "checkpoints").is_dir()}
    if not proxies:
        raise ConfigError(f"human_proxies: {folder} holds no human proxy of a test grid "
                          f"({', '.join(HUMAN_PROXY_RUN.format(grid=g.name) for g in grids[:3])}, ...): "
                          "`kitchen-humans train` makes them")
    return proxies


def with_human_proxies(outcomes: Outcomes, proxies: dict[str, Team], rollouts: int, max_steps: int, max_envs: int,
                       seed: int, device: str) -> Outcomes:
    """`outcomes` and, on each grid with a proxy, every team of theirs with the proxy in either seat (kind HUMAN)
    and the proxy with itself (SP): played on that grid only, absent (NaN) on the others."""
    teams, matchups = list(outcomes.teams), list(outcomes.matchups)
    grid_names = [grid.name for grid in outcomes.grids]
    deliveries, visits = [outcomes.deliveries], [outcomes.visits]
    population = len(outcomes.teams)  # the proxy's seat among the teams its grid is played with
    with_proxy = [m for team in range(population) for m in (Matchup(team, population, HUMAN),
                                                           Matchup(population, team, HUMAN))]
    with_proxy.append(Matchup(population, population, SP))
    for grid_name, proxy in proxies.items():
        g = grid_names.index(grid_name)
        played = play([*outcomes.teams, proxy], with_proxy, [outcomes.grids[g]], rollouts, max_steps, max_envs,
                      seed, device)
        on_grid = np.full((len(with_proxy), len(grid_names), rollouts), np.nan, np.float32)
        on_grid[:, g] = played.deliveries[:, 0]
        seen = np.zeros((len(with_proxy), *outcomes.visits.shape[1:]), np.float32)
        seen[:, g] = played.visits[:, 0]
        seat = {population: len(teams)}  # the proxy's seat among all the teams; the others keep theirs
        matchups += [Matchup(seat.get(m.seat0, m.seat0), seat.get(m.seat1, m.seat1), m.kind) for m in with_proxy]
        teams.append(proxy)
        deliveries.append(on_grid)
        visits.append(seen)
    return Outcomes(teams, matchups, outcomes.grids, np.concatenate(deliveries), np.concatenate(visits))


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
    each seat spent on each cell, summed over rollouts."""

    teams: list[Team]
    matchups: list[Matchup]
    grids: list[Layout]
    deliveries: np.ndarray
    visits: np.ndarray


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

    def __call__(self, batch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batch `batch`'s units [n], their deliveries [n, G] and the cells their seats visited [n, G, 2, H, W]."""
        b = self.batches
        num_grids = len(b.grids)
        torch.manual_seed(b.seed + batch)
        self.kitchen.set_seed(b.seed + batch)
        # Kitchen k plays unit first + k // G on grid k % G; the last batch repeats its last unit to stay full.
        unit = (torch.arange(b.per_batch, device=b.device) + batch * b.per_batch).clamp(max=b.units - 1)
        self.seated.seat(self.seat_of_matchup[unit.repeat_interleave(num_grids) // b.rollouts])
        with torch.no_grad():
            outcome = play_episodes(self.env, self.actor, b.max_steps)
        fresh = min(b.per_batch, b.units - batch * b.per_batch)
        deliveries = outcome.deliveries.reshape(b.per_batch, num_grids)[:fresh]
        visits = outcome.visits.reshape(b.per_batch, num_grids, *outcome.visits.shape[1:])[:fresh]
        return unit[:fresh].cpu().numpy(), deliveries.cpu().numpy(), visits.cpu().numpy()


_worker_player: BatchPlayer | None = None  # a worker process's player (`play` with workers > 1)


def _start_worker(batches: Batches) -> None:
    global _worker_player
    torch.set_num_threads(1)
    _worker_player = BatchPlayer(batches)


def _play_in_worker(batch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
) -> Outcomes:
    """Every matchup plays `rollouts` episodes on every grid, in batches of at most `max_envs` kitchens, played by
    `workers` processes at once (the same numbers with any)."""
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
    batches = Batches(teams, matchups, grids, rollouts, max_steps, max(1, min(max_envs // num_grids, units)), seed,
                      device)
    height, width = obs_shape[:2]
    deliveries = np.zeros((units, num_grids), np.float32)
    visits = np.zeros((len(matchups), num_grids, 2, height, width), np.float32)
    bar = tqdm(total=units * num_grids, unit="episode", unit_scale=True, disable=not progress, desc="evaluating")
    workers = min(workers, len(batches))
    if workers > 1:
        # Spawned, not forked: a fork of a process that has started JAX's threads may hang.
        pool = ProcessPoolExecutor(workers, multiprocessing.get_context("spawn"), _start_worker, (batches,))
        played = pool.map(_play_in_worker, range(len(batches)))
    else:
        pool, played = None, map(BatchPlayer(batches), range(len(batches)))
    try:
        for unit, got, seen in played:
            deliveries[unit] = got
            np.add.at(visits, unit // rollouts, seen)
            bar.update(got.size)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
    deliveries = deliveries.reshape(len(matchups), rollouts, num_grids).transpose(0, 2, 1)
    return Outcomes(teams, matchups, grids, deliveries, visits)


# ------------------------------------------------------------------------------------------------ metrics
def mean_and_stderr(values: np.ndarray) -> tuple[float, float]:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return float("nan"), float("nan")
    stderr = values.std(ddof=1) / math.sqrt(values.size) if values.size > 1 else 0.0
    return float(values.mean()), float(stderr)


def pair_rows(outcomes: Outcomes) -> list[dict]:
    """One row per matchup and grid: who played which seat, the kind of pair, mean deliveries and s.e."""
    rows = []
    for m, matchup in enumerate(outcomes.matchups):
        first, second = outcomes.teams[matchup.seat0], outcomes.teams[matchup.seat1]
        for g, grid in enumerate(outcomes.grids):
            if np.isnan(outcomes.deliveries[m, g]).all():  # a human proxy's pair, on another grid than its own
                continue
            mean, stderr = mean_and_stderr(outcomes.deliveries[m, g])
            rows.append({
                "agent0": first.name, "agent1": second.name, "condition0": first.condition,
                "condition1": second.condition, "kind": matchup.kind, "grid": grid.name,
                "mean_deliveries": round(mean, 4), "stderr": round(stderr, 4), "episodes": outcomes.deliveries.shape[2],
            })  # fmt: skip
    return rows


def at_home(team: Team, grid_name: str) -> bool:
    """Whether a grid counts for a team in the summaries: any grid for IK, its own layouts and held-out levels for
    SK (the paper evaluates SK teams on the layout they were trained on, and on the held-out levels)."""
    return team.home is None or grid_name in team.home or is_heldout(grid_name)


def pair_scores(outcomes: Outcomes, select, grid_names: Sequence[str]) -> np.ndarray:
    """float [n]: for every matchup `select(matchup, team0, team1)` accepts, its mean deliveries over the grids
    named where it played (pairs are the unit of the paper's error bars)."""
    columns = [g for g, grid in enumerate(outcomes.grids) if grid.name in set(grid_names)]
    scores = []
    for m, matchup in enumerate(outcomes.matchups):
        first, second = outcomes.teams[matchup.seat0], outcomes.teams[matchup.seat1]
        played = outcomes.deliveries[m, columns]
        if columns and select(matchup, first, second) and not np.isnan(played).all():
            scores.append(np.nanmean(played))
    return np.asarray(scores)


def grid_groups(outcomes: Outcomes) -> list[tuple[str, list[str]]]:
    """(group name, grid names): each classic layout alone, then all held-out levels together."""
    groups = [(grid.name, [grid.name]) for grid in outcomes.grids if not is_heldout(grid.name)]
    heldout = [grid.name for grid in outcomes.grids if is_heldout(grid.name)]
    if heldout:
        groups.append((f"held-out ({len(heldout)})", heldout))
    return groups


def summary_rows(outcomes: Outcomes) -> list[dict]:
    """SP, XP and the SP - XP gap per condition and grid group; cross-condition XP per condition pair."""
    rows = []
    conditions = list(dict.fromkeys(team.condition for team in outcomes.teams))
    for condition in conditions:
        team = next(t for t in outcomes.teams if t.condition == condition)
        for group, names in grid_groups(outcomes):
            if not all(at_home(team, name) for name in names):
                continue
            stats = {}
            for kind in (SP, XP):
                scores = pair_scores(
                    outcomes, lambda m, a, b, kind=kind: m.kind == kind and a.condition == condition, names
                )
                stats[kind] = (*mean_and_stderr(scores), len(scores))
            scores = pair_scores(
                outcomes, lambda m, a, b: m.kind == PARTNER and condition in (a.condition, b.condition), names
            )
            stats[PARTNER] = (*mean_and_stderr(scores), len(scores))
            scores = pair_scores(
                outcomes, lambda m, a, b: m.kind == HUMAN and condition in (a.condition, b.condition), names
            )
            stats[HUMAN] = (*mean_and_stderr(scores), len(scores))
            if not any(pairs for _, _, pairs in stats.values()):
                continue  # a human proxy away from its grid
            rows.append({
                "condition": condition, "label": team.label, "grids": group,
                "sp": stats[SP][0], "sp_stderr": stats[SP][1], "sp_pairs": stats[SP][2],
                "xp": stats[XP][0], "xp_stderr": stats[XP][1], "xp_pairs": stats[XP][2],
                "gap": stats[SP][0] - stats[XP][0],
                "partner": stats[PARTNER][0], "partner_stderr": stats[PARTNER][1], "partner_pairs": stats[PARTNER][2],
                "human": stats[HUMAN][0], "human_stderr": stats[HUMAN][1], "human_pairs": stats[HUMAN][2],
            })  # fmt: skip
    crossed = list(dict.fromkeys(
        tuple(sorted((outcomes.teams[m.seat0].condition, outcomes.teams[m.seat1].condition)))
        for m in outcomes.matchups if m.kind == CROSS
    ))  # fmt: skip
    for pair in crossed:
        members = [next(t for t in outcomes.teams if t.condition == c) for c in pair]
        for group, names in grid_groups(outcomes):
            if not all(at_home(member, name) for member in members for name in names):
                continue
            scores = pair_scores(
                outcomes, lambda m, a, b: m.kind == CROSS and tuple(sorted((a.condition, b.condition))) == pair, names
            )
            mean, stderr = mean_and_stderr(scores)
            rows.append({"condition": cross_condition(*pair), "label": "cross", "grids": group, "sp": float("nan"),
                         "sp_stderr": float("nan"), "sp_pairs": 0, "xp": mean, "xp_stderr": stderr,
                         "xp_pairs": len(scores), "gap": float("nan"), "partner": float("nan"),
                         "partner_stderr": float("nan"), "partner_pairs": 0, "human": float("nan"),
                         "human_stderr": float("nan"), "human_pairs": 0})
    return rows


def markdown_summary(rows: list[dict], rollouts: int) -> str:
    def cell(row, kind):
        mean, stderr, pairs = row[kind], row[f"{kind}_stderr"], row[f"{kind}_pairs"]
        return "" if not pairs else f"{mean:.2f} ± {stderr:.2f} ({pairs})"

    with_partner = any(row["partner_pairs"] for row in rows)
    with_human = any(row["human_pairs"] for row in rows)
    lines = [
        f"Mean deliveries per episode ({rollouts} rollouts per pair and grid, actions sampled); ± one standard "
        "error over pairs, (number of pairs). Held-out: the mean over the held-out levels."
        + (" With the scripted cook: the team in either seat, the scripted cook in the other." if with_partner else "")
        + (" With the human proxy: the team in either seat, the grid's behaviour-cloned human proxy (test split) in "
           "the other." if with_human else ""),
        "",
        "| condition | grids | SP | XP | SP - XP |" + (" with the scripted cook |" if with_partner else "")
        + (" with the human proxy |" if with_human else ""),
        "|---|---|---:|---:|---:|" + ("---:|" if with_partner else "") + ("---:|" if with_human else ""),
    ]
    for row in rows:
        gap = "" if math.isnan(row["gap"]) or not row["xp_pairs"] else f"{row['gap']:.2f}"
        line = f"| {row['condition']} | {row['grids']} | {cell(row, 'sp')} | {cell(row, 'xp')} | {gap} |"
        lines.append(line + (f" {cell(row, 'partner')} |" if with_partner else "")
                     + (f" {cell(row, 'human')} |" if with_human else ""))
    return "\n".join(lines) + "\n"


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]) if rows else [])
        writer.writeheader()
        writer.writerows(rows)


def visit_shares(outcomes: Outcomes, grid_name: str) -> list[tuple[str, str, np.ndarray]]:
    """(condition, SP | XP, share of agent steps per cell [H, W]) on one grid, for each condition at home there."""
    g = [grid.name for grid in outcomes.grids].index(grid_name)
    panels = []
    for condition in dict.fromkeys(team.condition for team in outcomes.teams):
        for kind in (SP, XP):
            chosen = [m for m, matchup in enumerate(outcomes.matchups)
                      if matchup.kind == kind and outcomes.teams[matchup.seat0].condition == condition
                      and at_home(outcomes.teams[matchup.seat0], grid_name)]  # fmt: skip
            if chosen:
                visits = outcomes.visits[chosen, g].sum(axis=(0, 1))
                panels.append((condition, kind, visits / max(visits.sum(), 1)))
    return panels


# -------------------------------------------------------------------------------------------------- GIFs
def record_gif(seat0: Team, seat1: Team, grid: Layout | str, path: Path, max_steps: int = 256, seed: int = 0) -> Path:
    """One episode of agent 0 of `seat0` with agent 1 of `seat1` on `grid`, rendered as an animated GIF."""
    kitchen = KitchenEnv(1, levels=grid, max_steps=max_steps, device=seat0.config.runtime.device, seed=seed)
    teams = [seat0] if seat0 is seat1 else [seat0, seat1]
    actor = make_seated_actor([team.actor_critic.actor for team in teams])
    seated = actor.module[0].seat(torch.tensor([[0, len(teams) - 1]], device=kitchen.device))
    env = with_transforms(kitchen, seated.env_transforms())

    def the_kitchen():
        return jax.tree_util.tree_map(lambda leaf: leaf[0], kitchen.states)

    torch.manual_seed(seed)
    tensordict = env.reset()
    frames = [the_kitchen()]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        env.rollout(max_steps, actor, auto_reset=False, tensordict=tensordict,
                    callback=lambda env, td: frames.append(the_kitchen()))
    return Path(write_gif(frames, path))


def parse_gif_request(request: str, teams: list[Team], grids: dict[str, Layout]) -> tuple[Team, Team, Layout]:
    """"cond/seed0+cond/seed1@grid" -> (agent 0's team, agent 1's team, the test grid)."""
    pair, sep, grid = request.partition("@")
    first, plus, second = pair.partition("+")
    if not sep or not plus or not grid:
        raise ConfigError(f"gifs entry {request!r} must look like 'condition/seed0+condition/seed1@grid'")
    by_name = {team.name: team for team in teams}
    for name in (first, second):
        if name not in by_name:
            raise ConfigError(f"gifs entry {request!r} names the team {name!r}; teams: {', '.join(by_name)}")
    if grid not in grids:
        raise ConfigError(f"gifs entry {request!r} names {grid!r}, which is not a test grid: {', '.join(grids)}")
    return by_name[first], by_name[second], grids[grid]


# --------------------------------------------------------------------------------------------- the whole job
def evaluate(config: EvalConfig) -> Path:
    """Loads the population, plays every matchup, writes tables, figures and GIFs to `config.out_dir`."""
    device = config.runtime.device
    torch.set_num_threads(config.runtime.threads)
    if not config.conditions:
        raise ConfigError("no conditions to evaluate: give conditions: {name: run_dir_or_glob, ...}")
    population = load_population(config.conditions, device)
    grids = evaluation_grids(config.layouts, config.heldout, config.kitchen_size)
    partner = scripted_cook_team((*grids[0].shape, 26), device) if config.partner else None
    teams, matchups = make_matchups(population, config.cross, partner)
    proxies = load_human_proxies(config.human_proxies, grids, device) if config.human_proxies else {}
    by_name = {grid.name: grid for grid in grids}
    for heatmap in config.heatmaps:
        if heatmap not in by_name:
            raise ConfigError(f"heatmaps names {heatmap!r}, which is not a test grid: {', '.join(by_name)}")
    gifs = [parse_gif_request(request, teams, by_name) for request in config.gifs]
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_config(config, out / "eval_config.yaml")
    print(f"{len(teams)} teams, {len(matchups)} pairs, {len(grids)} grids, {config.rollouts} rollouts: "
          f"{len(matchups) * len(grids) * config.rollouts:,} episodes")

    outcomes = play(teams, matchups, grids, config.rollouts, config.max_steps, config.max_envs, config.seed,
                    device, config.progress, config.workers)
    if proxies:
        outcomes = with_human_proxies(outcomes, proxies, config.rollouts, config.max_steps, config.max_envs,
                                      config.seed, device)
    write_csv(pair_rows(outcomes), out / "pairs.csv")
    summary = summary_rows(outcomes)
    write_csv(summary, out / "summary.csv")
    table = markdown_summary(summary, config.rollouts)
    (out / "eval.md").write_text(table)
    print(table)
    written = draw_figures(outcomes, summary, out)
    for grid_name in config.heatmaps:
        panels = visit_shares(outcomes, grid_name)
        if panels:
            written.append(draw_heatmap(by_name[grid_name], panels, out / f"heatmap_{grid_name}.png"))
    for first, second, grid in gifs:
        name = f"{first.name}+{second.name}@{grid.name}".replace("/", "-")
        written.append(record_gif(first, second, grid, out / f"{name}.gif", config.max_steps, config.seed))
    for path in written:
        print(f"wrote {path}")
    return out


def report_trained_team(run: str | Path, episodes: int | None = None, num_heldout: int | None = None) -> Path:
    """The self-play evaluation of a finished run, into the run directory: eval.md, pairs.csv, learning_curve.png, a
    team.gif (at home; a held-out level for a team of generated kitchens, where the table has one)."""
    run = Path(run)
    team = load_team(run)
    config = team.config
    size = team.obs_shape[0] if team.obs_shape[0] == team.obs_shape[1] in GENERATOR_SIZES else None
    if team.home:
        layouts = sorted(team.home)
    else:  # a team of generated kitchens: the classic layouts drawn at its size
        layouts = list(EXPANDED_LAYOUTS) if size == 7 else list(padded_layouts(size))
    num_heldout = (config.eval_heldout if num_heldout is None else num_heldout) if size else 0
    out = evaluate(EvalConfig(
        conditions={team.condition: str(run)},
        layouts=layouts,
        heldout=num_heldout,
        kitchen_size=size or 7,
        rollouts=episodes or config.eval_episodes,
        max_steps=config.max_steps,
        seed=config.seed, runtime=DeviceConfig(config.runtime.device, config.runtime.threads), progress=False,
        out_dir=str(run),
    ).check())  # fmt: skip
    if not team.fully_trained:
        note = f"Partly trained: {team.env_steps:,} of {config.planned_steps:,} env steps (the run stopped early).\n\n"
        (out / "eval.md").write_text(note + (out / "eval.md").read_text())
        print(note.strip())
    if curve := draw_learning_curve(run):
        print(f"learning curve: {curve}")
    if config.gif:
        grid = evaluation_grids([], 1, size)[0] if num_heldout and not team.home else load_layout(layouts[0])
        print(f"gif: {record_gif(team, team, grid, run / 'team.gif', config.max_steps, config.seed)}")
    return out / "eval.md"


# -------------------------------------------------------------------------------------------- command line
def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="kitchen-eval",
        description="Self-play and cross-play evaluation of trained teams: tables, figures, heat maps and GIFs.",
        epilog="Overrides: any config key as key=value, e.g. rollouts=5 heldout=10 out_dir=results/quick.\n\n"
               + config_help(EvalConfig),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("config", help="an evaluation config (configs/eval/...)")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    add_plugin_option(parser)
    args = parser.parse_args(argv)
    try:
        import_plugins(args.plugins)
        evaluate(load_config(args.config, args.overrides, schema=EvalConfig))
    except (ConfigError, CheckpointError, ValueError, PluginError) as error:
        print(f"kitchen-eval: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
