"""Partners from outside the population: teams that were trained apart from the conditions evaluated, played
with every team of theirs in either seat. The human proxies of the test grids (`kitchen-humans train`), each
played on its own grid only; the held-out strangers of a zoo (`trainers.zoo`), scripted cooks of conventions no
shipped config trains with, played on every grid and scored against two of their own kind. The scripted cook, the
`partner` of a config, is a team of `teams` (`scripted_cook_team`) played by `make_matchups`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jax_env import Layout
from trainers.config import ConfigError
from trainers.evaluation.intervals import interval, iqm
from trainers.evaluation.pairs import HUMAN, SP, STRANGER, Matchup, Outcomes, play
from trainers.evaluation.tables import at_home, grid_groups
from trainers.evaluation.teams import HUMAN_PROXY_RUN, Team, load_team


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
                       seed: int, device: str, collector: str = "kitchen") -> Outcomes:
    """`outcomes` and, on each grid with a proxy, every team of theirs with the proxy in either seat (kind HUMAN)
    and the proxy with itself (SP): played on that grid only, absent (NaN) on the others."""
    teams, matchups = list(outcomes.teams), list(outcomes.matchups)
    grid_names = [grid.name for grid in outcomes.grids]
    deliveries, visits, events = [outcomes.deliveries], [outcomes.visits], [outcomes.events]
    population = len(outcomes.teams)  # the proxy's seat among the teams its grid is played with
    with_proxy = [m for team in range(population) for m in (Matchup(team, population, HUMAN),
                                                           Matchup(population, team, HUMAN))]
    with_proxy.append(Matchup(population, population, SP))
    for grid_name, proxy in proxies.items():
        g = grid_names.index(grid_name)
        played = play([*outcomes.teams, proxy], with_proxy, [outcomes.grids[g]], rollouts, max_steps, max_envs,
                      seed, device, collector=collector)
        on_grid = np.full((len(with_proxy), len(grid_names), rollouts), np.nan, np.float32)
        on_grid[:, g] = played.deliveries[:, 0]
        seen = np.zeros((len(with_proxy), *outcomes.visits.shape[1:]), np.float32)
        seen[:, g] = played.visits[:, 0]
        happened = np.zeros((len(with_proxy), *outcomes.events.shape[1:]), np.float32)
        happened[:, g] = played.events[:, 0]
        seat = {population: len(teams)}  # the proxy's seat among all the teams; the others keep theirs
        matchups += [Matchup(seat.get(m.seat0, m.seat0), seat.get(m.seat1, m.seat1), m.kind) for m in with_proxy]
        teams.append(proxy)
        deliveries.append(on_grid)
        visits.append(seen)
        events.append(happened)
    return Outcomes(teams, matchups, outcomes.grids, np.concatenate(deliveries), np.concatenate(visits),
                    np.concatenate(events))


# ------------------------------------------------------------------------------------------------- strangers
@dataclass
class StrangerOutcomes:
    """Every team beside every held-out stranger, both seats, and each stranger with itself, per grid group.

    with_team float [T, S, 2, G]: mean deliveries of team t with stranger s, the team in seat 0 or 1 (index 2);
    alone float [S, G]: two of stranger s; best float [S, G]: stranger s with its best response, both seats
    averaged (NaN where none was given); groups: (name, its grids' names) of each grid group (each classic layout,
    then the held-out levels together); teams and strangers: as played."""

    teams: list[Team]
    strangers: list[Team]
    groups: list[tuple[str, list[str]]]
    with_team: np.ndarray
    alone: np.ndarray
    best: np.ndarray | None = None

    @property
    def normalised(self) -> np.ndarray:
        """float [T, S, 2, G]: deliveries with the stranger divided by two of that stranger's (1.0: as good a
        partner to it as its own kind); NaN where the stranger alone never delivers."""
        alone = np.where(self.alone > 0, self.alone, np.nan)[None, :, None]
        return self.with_team / alone

    @property
    def over_best(self) -> np.ndarray:
        """float [T, S, 2, G]: deliveries with the stranger over its best response's with it (ZSC-Eval's BR-Prox);
        NaN where the stranger has no best response or it never delivers."""
        best = np.full_like(self.alone, np.nan) if self.best is None else self.best
        return self.with_team / np.where(best > 0, best, np.nan)[None, :, None]


def play_with_strangers(teams: list[Team], strangers: list[Team], grids: list[Layout], rollouts: int,
                        max_steps: int, max_envs: int, seed: int, device: str, progress: bool = False,
                        workers: int = 1, best_responses: dict[int, Team] | None = None,
                        collector: str = "kitchen") -> StrangerOutcomes:
    """Each team beside each stranger in both seats, each stranger with itself, and with its best response where
    `best_responses` has one (stranger index -> team), `rollouts` episodes per grid."""
    best_responses = best_responses or {}
    everyone = [*teams, *strangers, *best_responses.values()]
    first, last = len(teams), len(teams) + len(strangers)
    matchups = [m for t in range(first) for s in range(first, last)
                for m in (Matchup(t, s, STRANGER), Matchup(s, t, STRANGER))]
    matchups += [Matchup(s, s, SP) for s in range(first, last)]
    for b, s in enumerate(best_responses, start=last):
        matchups += [Matchup(b, first + s, STRANGER), Matchup(first + s, b, STRANGER)]
    outcomes = play(everyone, matchups, grids, rollouts, max_steps, max_envs, seed, device, progress, workers,
                    collector)
    groups = grid_groups(outcomes)
    per_grid = outcomes.deliveries.mean(-1)  # [M, G]
    by_group = np.stack([per_grid[:, [g for g, grid in enumerate(grids) if grid.name in names]].mean(1)
                         for _, names in groups], axis=1)  # [M, groups]
    pairs = len(teams) * len(strangers) * 2
    with_team = by_group[:pairs].reshape(len(teams), len(strangers), 2, len(groups))
    alone = by_group[pairs:pairs + len(strangers)]
    best = np.full_like(alone, np.nan)
    for b, s in enumerate(best_responses):
        best[s] = by_group[pairs + len(strangers) + 2 * b: pairs + len(strangers) + 2 * b + 2].mean(0)
    return StrangerOutcomes(teams, strangers, groups, with_team, alone, best)


def seeds_interval(scores: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """(IQM, low, high) of scores [teams, strangers, seats] over the strangers where every team has a score in
    every seat (seats averaged: a task is a stranger), with rliable's stratified bootstrap over the teams (seeds)
    within each stranger; NaN where no stranger has scores."""
    per_stranger = scores.mean(axis=2)
    per_stranger = per_stranger[:, ~np.isnan(per_stranger).any(axis=0)]
    if per_stranger.size == 0:
        return math.nan, math.nan, math.nan
    return tuple(interval(per_stranger, iqm, seed=seed))


def stranger_pair_rows(outcomes: StrangerOutcomes) -> list[dict]:
    """One row per team, stranger, seat and grid group: deliveries together, two of the stranger's, the ratio."""
    normalised, over_best = outcomes.normalised, outcomes.over_best
    rows = []
    for t, team in enumerate(outcomes.teams):
        for s, stranger in enumerate(outcomes.strangers):
            for seat in (0, 1):
                for g, (group, names) in enumerate(outcomes.groups):
                    if not all(at_home(team, name) for name in names):
                        continue
                    rows.append({
                        "team": team.name, "condition": team.condition, "stranger": stranger.name,
                        "team_seat": seat, "grids": group,
                        "deliveries": round(float(outcomes.with_team[t, s, seat, g]), 4),
                        "stranger_alone": round(float(outcomes.alone[s, g]), 4),
                        "normalised": round(float(normalised[t, s, seat, g]), 4),
                        "over_best_response": round(float(over_best[t, s, seat, g]), 4),
                    })  # fmt: skip
    return rows


def stranger_rows(outcomes: StrangerOutcomes, seed: int = 0) -> list[dict]:
    """Per condition and grid group (where its teams are at home): mean deliveries with every stranger; then, over
    the strangers that deliver with themselves on that group (the others are left out of the normalised score, and
    named), mean deliveries with them, two of them alone, and the normalised score as a ratio of those two means,
    with the IQM over teams x those strangers of each team's ratio (`seeds_interval`; `pairs` counts teams x
    strangers x seats); and the IQM over the strangers' best responses where they have one (BR-Prox)."""
    over_best = outcomes.over_best
    rows = []
    for condition in dict.fromkeys(team.condition for team in outcomes.teams):
        members = [t for t, team in enumerate(outcomes.teams) if team.condition == condition]
        for g, (group, names) in enumerate(outcomes.groups):
            if not all(at_home(outcomes.teams[members[0]], name) for name in names):
                continue
            scored = np.flatnonzero(outcomes.alone[:, g] > 0)
            left_out = [stranger.name for s, stranger in enumerate(outcomes.strangers) if s not in scored]
            together = outcomes.with_team[members][:, scored][..., g]  # [teams, strangers, seats]
            alone = outcomes.alone[scored, g]
            ratios = together / alone[None, :, None]
            middle, low, high = seeds_interval(ratios, seed)
            proximity = over_best[members][..., g]
            br_middle, br_low, br_high = seeds_interval(proximity, seed)
            scored_deliveries = float(together.mean()) if scored.size else math.nan
            scored_alone = float(alone.mean()) if scored.size else math.nan
            rows.append({
                "condition": condition, "grids": group, "pairs": int(ratios.size),
                "deliveries": float(outcomes.with_team[members, :, :, g].mean()),
                "strangers_alone": float(outcomes.alone[:, g].mean()),
                "scored_deliveries": scored_deliveries, "scored_alone": scored_alone,
                "normalised": scored_deliveries / scored_alone if scored.size else math.nan,
                "left_out": " ".join(left_out),
                "iqm": middle, "iqm_low": low, "iqm_high": high, "br_pairs": int((~np.isnan(proximity)).sum()),
                "br_iqm": br_middle, "br_iqm_low": br_low, "br_iqm_high": br_high,
            })  # fmt: skip
    return rows


def markdown_strangers(rows: list[dict], strangers: Sequence[str], rollouts: int, kind: str = "held-out strangers"
                       ) -> str:
    with_best = any(row["br_pairs"] for row in rows)
    lines = [
        f"With the {kind} ({len(strangers)}: {', '.join(strangers)}), the team in either seat, "
        f"{rollouts} rollouts per pair and grid. With every stranger: mean deliveries over the condition's teams x "
        "strangers x seats. The normalised score leaves out, per grid group, the strangers that never deliver with "
        "themselves there (named): over the others, mean deliveries with them, two of them alone, and normalised, "
        "the first over the second (a ratio of means: 1.0 is as good a partner to them as their own kind); IQM: the "
        "interquartile mean over teams x those strangers of each team's ratio beside each (seats averaged; pairs: "
        "teams x strangers x seats), [95% interval: rliable's stratified bootstrap over the teams, the seeds, within "
        "each stranger]."
        + (" Over the best response: deliveries with a stranger over its best response's with it (ZSC-Eval's "
           "BR-Prox), IQM over the pairs of the strangers that have one." if with_best else ""),
        "",
        "| condition | grids | with every stranger | with those that cook | those alone | normalised | "
        "IQM normalised | pairs | left out |" + (" over the best response (IQM) |" if with_best else ""),
        "|---|---|---:|---:|---:|---:|---:|---:|---|" + ("---:|" if with_best else ""),
    ]
    for row in rows:
        best = (f" {row['br_iqm']:.2f} [{row['br_iqm_low']:.2f}, {row['br_iqm_high']:.2f}] ({row['br_pairs']}) |"
                if with_best else "")
        lines.append(f"| {row['condition']} | {row['grids']} | {row['deliveries']:.2f} | "
                     f"{row['scored_deliveries']:.2f} | {row['scored_alone']:.2f} | {row['normalised']:.2f} | "
                     f"{row['iqm']:.2f} [{row['iqm_low']:.2f}, {row['iqm_high']:.2f}] | {row['pairs']} | "
                     f"{row['left_out'] or '-'} |" + best)
    return "\n".join(lines) + "\n"
