"""`kitchen-study analyse STUDY_DIR`: the study's games and answers, checked against their records, as a report.

Only finished assigned games count (practice games and cut attempts never do), and each only if its record is
there, has the checksum the database stored, replays exactly through the JAX env (kitchen-play's replay) and
replays to the score the database stored; any other is listed with its reason and left out, with its questions.
Written into STUDY_DIR/analysis/:

    report.md      participants, games counted and left out; the headline, a mixed model of deliveries (condition,
                   kitchen and position, a random intercept per participant: `web_apps.study.inference`) with the
                   primary contrast first and the other pairs Holm-corrected; deliveries per condition and kitchen
                   over participants (intervals resampling participants); paired differences within participants;
                   the Likert answers per participant; the forced choice with a sign test per pair
    games.csv      every counted game: participant, position, condition, kitchen, seed, record, sha256, deliveries
    answers.csv    every counted answer: participant, position, condition, item, value, and for the forced choice
                   the condition chosen and the one not chosen
    deliveries.png deliveries per game by condition and kitchen, with the intervals
"""

from __future__ import annotations

import csv
import itertools
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from trainers.evaluation.tables import bootstrap_interval
from web_apps.play.game import file_sha256, replay
from web_apps.study.assignment import QUESTIONS
from web_apps.study.config import FORCED_CHOICE, StudyConfig, StudyError, config_from_dict
from web_apps.study.database import DATABASE, FINISHED, StudyDatabase
from web_apps.study.inference import (
    CONFIDENCE,
    RESAMPLES,
    Observation,
    fit_mixed_model,
    holm,
    participant_interval,
    per_participant,
    sign_test,
)


@dataclass
class CountedGame:
    participant: int
    position: int
    condition: str
    kitchen: str
    seed: int
    record: str
    sha256: str
    deliveries: int


def interval(values, statistic=np.mean, seed: int = 0) -> tuple[float, float]:
    """The 95% percentile bootstrap interval of `statistic` over `values` (`bootstrap_interval`; NaN for fewer than
    two, the value itself where all are equal)."""
    if len(values) < 2:
        return float("nan"), float("nan")
    _, low, high = bootstrap_interval(values, statistic, CONFIDENCE, RESAMPLES, seed)
    return low, high


def wilcoxon_p(differences) -> float:
    """The two-sided p-value of Wilcoxon's signed-rank test that the differences centre on 0 (NaN where it cannot
    be computed: fewer than two, or all zero)."""
    differences = np.asarray(differences, dtype=float)
    if len(differences) < 2 or np.all(differences == 0):
        return float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(stats.wilcoxon(differences).pvalue)


def checked_games(database: StudyDatabase, folder: Path) -> tuple[list[CountedGame], list[tuple[dict, str]]]:
    """(games counted, [(game row, why left out)]) of the finished assigned games (see the module docstring)."""
    counted, left_out = [], []
    for row in database.rows("SELECT * FROM games WHERE status = ? AND practice = 0 ORDER BY participant, position",
                             FINISHED):
        row = dict(row)
        path = folder / row["record"]
        if not path.is_file():
            left_out.append((row, "the record is missing"))
            continue
        if file_sha256(path) != row["sha256"]:
            left_out.append((row, "the record's checksum differs from the database's (changed after the game)"))
            continue
        try:
            replayed = replay(path)
        except ValueError as error:
            left_out.append((row, f"does not replay: {str(error).removeprefix(f'{path}: ')}"))
            continue
        if replayed["score"] != row["score"] or replayed["steps"] != row["steps"]:
            left_out.append((row, f"replays to {replayed['score']} deliveries in {replayed['steps']} steps, the "
                                  f"database says {row['score']} in {row['steps']}"))
            continue
        counted.append(CountedGame(row["participant"], row["position"], row["condition"], row["kitchen"],
                                   row["seed"], row["record"], row["sha256"], row["score"]))
    return counted, left_out


def number(value: float, digits: int = 2) -> str:
    return "n/a" if value != value else f"{value:.{digits}f}"


def span(low: float, high: float) -> str:
    return "n/a (n < 2)" if low != low else f"[{low:.2f}, {high:.2f}]"


def study_config_of(folder: str | Path) -> StudyConfig:
    """The config a study in `folder` started with; a StudyError if the folder holds no study."""
    database = None
    try:
        database = StudyDatabase(Path(folder) / DATABASE, create=False)
        return config_from_dict(database.config())
    except FileNotFoundError:
        raise StudyError(f"{folder} holds no study (no {DATABASE} with a config): give the study's folder, "
                         "e.g. studies/<name>") from None
    finally:
        if database is not None:
            database.close()


def analyse(folder: str | Path) -> Path:
    """Writes the report of the study in `folder` (see the module docstring); returns the report's path."""
    folder = Path(folder)
    config = study_config_of(folder)
    database = StudyDatabase(folder / DATABASE, create=False)
    try:
        return write_report(config, database, folder)
    finally:
        database.close()


def write_report(config: StudyConfig, database: StudyDatabase, folder: Path) -> Path:
    """analysis/report.md with games.csv, answers.csv and deliveries.png: the games that replay exactly and the
    answers that follow them, by condition, kitchen and participant."""
    out = folder / "analysis"
    out.mkdir(exist_ok=True)
    conditions = list(config.conditions)
    counted, left_out = checked_games(database, folder)
    condition_of = {(game.participant, game.position): game.condition for game in counted}
    answers = counted_answers(config, database, condition_of)
    write_tables(counted, answers, condition_of, out)
    observations = [Observation(g.participant, g.condition, g.kitchen, g.position, g.deliveries) for g in counted]
    cells = {(condition, kitchen): participant_interval([o for o in observations if kitchen in ("all", o.kitchen)],
                                                        condition)
             for condition in conditions for kitchen in [*config.kitchens, "all"]}
    lines = [*count_lines(config, folder, database.progress(config.abandon_after), counted, left_out, answers),
             *model_lines(config, observations), *delivery_lines(cells, len(counted)),
             *within_lines(counted, conditions), *question_lines(config, answers),
             *choice_lines(config, forced_choices(answers, condition_of)), *left_out_lines(left_out)]
    plot(cells, conditions, config.kitchens, out / "deliveries.png")
    report = out / "report.md"
    report.write_text("\n".join(lines), encoding="utf-8")
    return report


def counted_answers(config: StudyConfig, database: StudyDatabase, condition_of: dict) -> list[tuple]:
    """(participant, position, condition, item, value) of every answer that follows a counted game: stage rows
    tell which game a questions stage followed."""
    answers = []
    for row in database.rows("SELECT a.participant, a.stage, a.item, a.value, s.kind FROM answers a JOIN stages s "
                             "ON a.participant = s.participant AND a.stage = s.stage ORDER BY a.participant, a.stage"):
        if row["kind"] != QUESTIONS:
            continue
        position = position_of_questions(config, row["stage"])
        if (row["participant"], position) in condition_of:
            answers.append((row["participant"], position, condition_of[row["participant"], position], row["item"],
                            row["value"]))
    return answers


def write_tables(counted: list, answers: list[tuple], condition_of: dict, out: Path) -> None:
    """games.csv and answers.csv (the forced choice's rows naming the condition chosen and the one not chosen)."""
    with open(out / "games.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["participant", "position", "condition", "kitchen", "seed", "record", "sha256", "deliveries"])
        writer.writerows([g.participant, g.position, g.condition, g.kitchen, g.seed, g.record, g.sha256, g.deliveries]
                         for g in counted)
    with open(out / "answers.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["participant", "position", "condition", "item", "value", "chosen", "not_chosen"])
        for participant, position, condition, item, value in answers:
            chosen = not_chosen = ""
            if item == FORCED_CHOICE:
                offered = [condition_of.get((participant, position - 1)), condition_of.get((participant, position))]
                chosen = condition_of.get((participant, value), "")
                not_chosen = next((other for other in offered if other != chosen), chosen) if chosen else ""
            writer.writerow([participant, position, condition, item, value, chosen, not_chosen])


def count_lines(config: StudyConfig, folder: Path, progress: dict, counted: list, left_out: list, answers: list
                ) -> list[str]:
    return [f"# Study {config.name}: report", "",
            f"From `{folder / DATABASE}` and the records under `{folder / 'records'}`. Every game counted is listed "
            "in `games.csv` (its record and SHA-256), every answer counted in `answers.csv`.", "",
            "## Counts", "",
            "| | count |", "|---|---:|",
            f"| participants started | {progress['started']} |",
            f"| participants finished | {progress['finished']} |",
            f"| assigned games finished (database) | {progress['games_finished']} |",
            f"| games counted (replayed exactly) | {len(counted)} |",
            f"| games left out | {len(left_out)} |",
            f"| attempts cut and played again (never counted) | {progress['games_cut']} |",
            f"| answers counted | {len(answers)} |", ""]


def model_lines(config: StudyConfig, observations: list[Observation]) -> list[str]:
    """The headline: the mixed model's contrasts, the primary one first."""
    first, second = config.primary_contrast
    lines = ["## The headline: a mixed model of deliveries", "",
             "deliveries ~ condition + kitchen + position, a random intercept per participant (statsmodels' MixedLM, "
             f"REML): each contrast first - second in deliveries per game, its {CONFIDENCE:.0%} interval and p-value. "
             f"The primary contrast ({first} - {second}, the config's `primary`) answers the study's question and is "
             "not corrected; the other pairs are Holm-corrected among themselves.", "",
             "| contrast | estimate | 95% interval | p | p (Holm) |", "|---|---:|---|---:|---:|"]
    contrasts = fit_mixed_model(observations, list(config.conditions), (first, second))
    if not contrasts:
        return [*lines, "| (not fitted: too few participants, or conditions confounded with kitchens or positions) "
                        "| | | | |", ""]
    for index, contrast in enumerate(contrasts):
        label = f"{contrast.first} - {contrast.second}" + (" (primary)" if index == 0 else "")
        lines.append(f"| {label} | {contrast.estimate:+.2f} | {span(contrast.low, contrast.high)} | "
                     f"{number(contrast.p, 3)} | {'-' if index == 0 else number(contrast.p_holm, 3)} |")
    return [*lines, ""]


def delivery_lines(cells: dict[tuple[str, str], tuple], games: int) -> list[str]:
    lines = ["## Deliveries per condition, over participants", "",
             "Each participant's mean deliveries per game beside the condition (on the kitchen, or on all), their "
             "mean, "
             f"and its {CONFIDENCE:.0%} percentile bootstrap interval resampling participants, each with all its games "
             f"({RESAMPLES} resamples); n: participants ({games} games in all).", "",
             "| condition | kitchen | n | mean | 95% interval |", "|---|---|---:|---:|---|"]
    for (condition, kitchen), (mean, low, high, participants) in cells.items():
        if participants:
            lines.append(f"| {condition} | {kitchen} | {participants} | {mean:.2f} | {span(low, high)} |")
    return [*lines, ""]


def within_lines(counted: list, conditions: list[str]) -> list[str]:
    lines = ["## Within participants", "",
             "Per participant, the mean deliveries with the first condition minus those with the second, over the "
             "participants who played both; its mean with a 95% bootstrap interval over participants, and the "
             "two-sided p-value of the Wilcoxon signed-rank test (`scipy.stats.wilcoxon`) that the differences centre "
             "on 0, Holm-corrected over the pairs.", "",
             "| first | second | participants | mean difference | 95% interval | Wilcoxon p | p (Holm) |",
             "|---|---|---:|---:|---|---:|---:|"]
    per_participant_games = {}
    for game in counted:
        per_participant_games.setdefault((game.participant, game.condition), []).append(game.deliveries)
    participants = sorted({game.participant for game in counted})
    rows = []
    for first, second in itertools.combinations(conditions, 2):
        differences = [np.mean(per_participant_games[p, first]) - np.mean(per_participant_games[p, second])
                       for p in participants
                       if (p, first) in per_participant_games and (p, second) in per_participant_games]
        if differences:
            rows.append((first, second, differences, wilcoxon_p(differences)))
    for (first, second, differences, p), adjusted in zip(rows, holm([row[3] for row in rows])):
        low, high = interval(differences)
        lines.append(f"| {first} | {second} | {len(differences)} | {np.mean(differences):.2f} | {span(low, high)} | "
                     f"{number(p, 3)} | {number(adjusted, 3)} |")
    return [*lines, ""]


def question_lines(config: StudyConfig, answers: list[tuple]) -> list[str]:
    scale = config.likert.scale
    first, second = config.primary_contrast
    lines = ["## Questions", "",
             f"Likert items on 1 ({scale[0]}) to {len(scale)} ({scale[-1]}), per participant: each participant's mean "
             "answer to the item after its games beside the condition; the median and mean of those, n: "
             f"participants. Then, per item, the participants' mean answers beside {first} minus beside {second}, "
             "and the Wilcoxon signed-rank test that they centre on 0.", "",
             "| condition | item | n | median | mean |", "|---|---|---:|---:|---:|"]
    by_item = {}
    for condition in config.conditions:
        for item in config.likert.items:
            values = [Observation(a[0], a[2], "", a[1], a[4]) for a in answers if a[3] == item]
            means = per_participant(values, condition)
            by_item[condition, item] = means
            if means:
                lines.append(f"| {condition} | {item} | {len(means)} | {np.median(list(means.values())):g} | "
                             f"{np.mean(list(means.values())):.2f} |")
    lines += ["", f"| item | participants | mean {first} - {second} | Wilcoxon p |", "|---|---:|---:|---:|"]
    for item in config.likert.items:
        a, b = by_item.get((first, item), {}), by_item.get((second, item), {})
        differences = [a[p] - b[p] for p in a if p in b]
        if differences:
            lines.append(f"| {item} | {len(differences)} | {np.mean(differences):+.2f} | "
                         f"{number(wilcoxon_p(differences), 3)} |")
    return [*lines, ""]


def choice_lines(config: StudyConfig, choices: list) -> list[str]:
    if not config.forced_choice or len(config.conditions) < 2:
        return []
    lines = ["## Forced choice", "", f"\"{config.forced_choice}\", asked after every game but the first, "
             "between the last two partners: per pair of conditions offered, how often each was chosen over the "
             "other, and the two-sided sign test (a binomial test against one half) that people choose as a coin "
             "would; choices between two games of one condition do not count.", "",
             "| first | second | offered | first chosen | second chosen | sign test p |",
             "|---|---|---:|---:|---:|---:|"]
    for first, second in itertools.combinations(config.conditions, 2):
        offered = [choice for pair, choice in choices if set(pair) == {first, second}]
        won, lost = offered.count(first), offered.count(second)
        if offered:
            p = number(sign_test(won, lost), 3)
            lines.append(f"| {first} | {second} | {len(offered)} | {won} | {lost} | {p} |")
    return [*lines, ""]


def left_out_lines(left_out: list) -> list[str]:
    lines = ["## Games left out", ""]
    if left_out:
        lines += ["| participant | position | condition | record | reason |", "|---:|---:|---|---|---|"]
        lines += [f"| {row['participant']} | {row['position']} | {row['condition']} | `{row['record']}` | {why} |"
                  for row, why in left_out]
    else:
        lines.append("None: every finished game replayed exactly to the score the database holds.")
    return [*lines, "", "![deliveries per game](deliveries.png)", ""]


def position_of_questions(config: StudyConfig, stage: int) -> int:
    """The position of the game a questions stage follows: consent, instructions and the practice games come
    first, then a game and its questions per position."""
    return (stage - 2 - config.practice_games) // 2


def forced_choices(answers, condition_of) -> list[tuple[tuple[str, str], str]]:
    """((the two conditions offered), the one chosen) of each forced choice counted (both games counted)."""
    found = []
    for participant, position, _, item, value in answers:
        if item != FORCED_CHOICE:
            continue
        pair = (condition_of.get((participant, position - 1)), condition_of.get((participant, position)))
        if None not in pair and (participant, value) in condition_of:
            found.append((pair, condition_of[participant, value]))
    return found


def plot(cells: dict, conditions: list[str], kitchens: list[str], path: Path) -> None:
    """Mean deliveries over participants per condition and kitchen, with the intervals resampling participants."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [*kitchens, "all"]
    width = 0.8 / len(conditions)
    figure, axes = plt.subplots(figsize=(max(5, 1.4 * len(groups) * len(conditions) / 2 + 2), 3.6))
    for c, condition in enumerate(conditions):
        means, lows, highs = [], [], []
        for group in groups:
            mean, low, high, _ = cells.get((condition, group), (float("nan"),) * 3 + (0,))
            means.append(mean)
            lows.append(mean - low if low == low else 0)
            highs.append(high - mean if high == high else 0)
        axes.bar(np.arange(len(groups)) + c * width - 0.4 + width / 2, means, width, yerr=[lows, highs], capsize=3,
                 label=condition)
    axes.set_xticks(np.arange(len(groups)), groups, rotation=20, ha="right")
    axes.set_ylabel("deliveries per game")
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
