"""The tables of an evaluation: one row per pair and grid (`pair_rows`), the summary per condition and grid group
(`summary_rows`, `markdown_summary`), CSV files, and the shares of steps per cell behind the heat maps."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy import stats

from trainers.evaluation.pairs import CROSS, HUMAN, PARTNER, SP, XP, Outcomes, cross_condition, is_heldout
from trainers.evaluation.teams import Team


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
            for kind in (PARTNER, HUMAN):  # an outside partner's own row would repeat its partners' numbers
                scores = pair_scores(outcomes, lambda m, a, b, kind=kind: m.kind == kind and not team.is_outside_partner
                                     and condition in (a.condition, b.condition), names)
                stats[kind] = (*mean_and_stderr(scores), len(scores))
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


SEED_KINDS = {SP: "sp", XP: "xp", PARTNER: "partner", HUMAN: "human", CROSS: "cross"}


def seed_rows(outcomes: Outcomes) -> list[dict]:
    """One row per team, grid group (where it is at home) and kind of pair (sp, xp, partner, human, cross with
    another condition): the team's mean deliveries over its pairs of that kind, in either seat. A seed is the unit
    the claims' intervals resample (rliable's runs); the outside partners have their self-play row only."""
    rows = []
    for t, team in enumerate(outcomes.teams):
        kinds = dict.fromkeys(
            (m.kind, outcomes.teams[m.seat1 if m.seat0 == t else m.seat0].condition if m.kind == CROSS else "")
            for m in outcomes.matchups
            if t in (m.seat0, m.seat1) and (m.kind == SP or not team.is_outside_partner))  # fmt: skip
        for group, names in grid_groups(outcomes):
            if not all(at_home(team, name) for name in names):
                continue
            for kind, partner in kinds:
                scores = pair_scores(outcomes, lambda m, a, b, kind=kind, partner=partner: (
                    m.kind == kind and t in (m.seat0, m.seat1)
                    and (not partner or partner == (b if m.seat0 == t else a).condition)), names)
                if scores.size:
                    rows.append({"condition": team.condition, "team": team.name, "grids": group,
                                 "kind": SEED_KINDS[kind], "with": partner,
                                 "deliveries": round(float(scores.mean()), 4), "pairs": int(scores.size)})
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


# ------------------------------------------------------------------------------------------------- strangers
def bootstrap_interval(values, statistic, confidence: float = 0.95, resamples: int = 2000, seed: int = 0
                       ) -> tuple[float, float, float]:
    """(statistic, low, high): `statistic` (a function of an array and an `axis`) of the values that are not NaN,
    with a percentile bootstrap interval (scipy.stats.bootstrap); NaN for no values, a point for one value or for
    values all equal."""
    values = np.asarray(values, dtype=np.float64).ravel()
    values = values[~np.isnan(values)]
    if values.size == 0:
        return math.nan, math.nan, math.nan
    middle = float(statistic(values, axis=-1))
    if values.size == 1 or np.all(values == values[0]):
        return middle, middle, middle
    interval = stats.bootstrap((values,), statistic, confidence_level=confidence, n_resamples=resamples,
                               method="percentile", rng=np.random.default_rng(seed)).confidence_interval
    return middle, float(interval.low), float(interval.high)
