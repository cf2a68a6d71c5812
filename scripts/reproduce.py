"""The paper's experiment as one command: train the conditions of a protocol, evaluate them, write RESULTS.md with
the numbers beside the paper's claims, one section per family of conditions.

    python scripts/reproduce.py configs/protocols/reduced.yaml --sections planner --jobs 4   # 89 min, 2 cores
    python scripts/reproduce.py configs/protocols/reduced.yaml --sections scratch           # several hours
    python scripts/reproduce.py configs/protocols/paper.yaml                                # the paper's budget, a GPU

A protocol file names the conditions (a trainer config each, or a config and the condition's own overrides,
applied after the shared ones), the overrides they share, the seeds trained together per condition (`teams`),
the families compared (an IK condition and the SK conditions of the same architecture and learner, which it
cross-plays; `learner` says how they learn, `paper` whose of the paper's figures apply), further pairs to
cross-play (`cross`), RESULTS.md's `sections` (the conditions evaluated and reported together: a learner's
families, say) and the evaluation's sizes; `evaluation: {human_proxies: true}` also seats a human proxy
(behaviour-cloned from the 2019 human games' test split, `kitchen-humans`) beside every team on the classic
layouts drawn inside a 7x7 kitchen, which join the test grids; a mapping of `ProxySettings` fields in its place sizes
their fitting (`{epochs: 1, candidates: 1, fine_tune_steps: 0}` for a tiny run), `--no-human-proxies` leaves them out.

Training writes `<out>/runs/<condition>/seed<k>`, `--jobs` conditions at a time, each in a process of its own; a
condition already trained is skipped and one that stopped part-way is resumed, so an interrupted reproduction
continues where it stopped. Extra `key=value` arguments override every condition, after its own overrides (e.g.
`total_steps=1e5` for a smoke run); `--sections` and `--conditions` run part of a protocol (the families and cross
pairs of the conditions named). Each section is evaluated on its own (`kitchen-eval`'s code, into
`<out>/eval/<section>`) and rewritten in RESULTS.md with its tables, claims, figures, budget, machine, wall times,
date and command; the sections this run did not touch stay as they were written, and the claims table at the top
gathers every section's claims.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import functools
import math
import multiprocessing
import os
import re
import shutil
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml

from jax_env import EXPANDED_LAYOUTS, PADDED_LAYOUTS
from torch_kitchen.partners.conventions import load_zoo
from trainers.checkpoint import CheckpointError, load_checkpoint
from trainers.config import EVAL_COLLECTORS, PLANNER_START, ConfigError, DeviceConfig, EvalConfig, TrainConfig
from trainers.config.compose import load_config
from trainers.evaluation import HUMAN_PROXY_RUN, SCRIPTED_CONDITION, cross_condition, evaluate
from trainers.evaluation.claims import (
    PAPER_STEPS,
    SeedScores,
    beyond_teacher,
    family_claims,
    shared_teacher,
    stranger_claims,
)
from trainers.humans.behaviour_cloning import ProxySettings
from trainers.humans.command import fetch
from trainers.humans.command import train as train_proxies
from trainers.machine import code_version, machine_name
from trainers.ppo.loop import check_teams
from trainers.ppo.resume import RunStopped, check_same_learning, check_same_partners
from trainers.ppo.team import team_configs
from trainers.train_command import latest_checkpoints, train_config_file

ROOT = Path(__file__).resolve().parents[1]
MAIN_JOB = ROOT / "configs" / "main.yaml"  # the README's planner-guided team, whose budget a section is set beside
SCRATCH = "IPPO from scratch"  # the paper's learner, a family's unless it names another

TITLE = "# Results: the paper's experiment at a reduced budget"
WHOLE = "all"  # the one section of a protocol that names none
SECTION_START, SECTION_END = "<!-- section: {} -->", "<!-- /section: {} -->"
CLAIMS_START, CLAIMS_END = "<!-- claims -->", "<!-- /claims -->"
CLAIMS_HEADER = ["| family | learner | claim | here: aggregate [95% interval over seeds] | at this budget |",
                 "|---|---|---|---|---|"]


def condition_entry(entry: str | dict) -> tuple[str, list[str]]:
    """A protocol's condition -> (its trainer config, its own overrides): a path, or {config:, overrides:}, where
    overrides may hold lists (a YAML alias to another condition's) that count as their items."""
    if isinstance(entry, str):
        return entry, []
    overrides = []
    for item in entry.get("overrides", []):
        overrides += item if isinstance(item, list) else [item]
    return entry["config"], overrides


def with_strangers(protocol: dict, zoo: str | None) -> dict:
    """The protocol with every section that seats strangers seating those of `zoo` (None: as it is)."""
    if not zoo:
        return protocol
    sections = {name: {**section, "strangers": zoo} if section.get("strangers") else section
                for name, section in protocol.get("sections", {}).items()}
    return {**protocol, "sections": sections} if sections else protocol


# The evaluation instruments a strangers section may train, one run per held-out stranger: the overrides that make
# a run of the section's `best_responses` or `learned_strangers` entry ({config:, overrides:}) one for `stranger`.
INSTRUMENTS = {
    "best_responses": ("best_response_{}", lambda stranger: [
        "algorithm=zoo_ippo", f"algorithm_config.best_response_to={stranger}"]),  # IPPO beside it in every kitchen
    "learned_strangers": ("learned_{}", lambda stranger: [
        f"distill.teachers=[{stranger}]", "learned_stranger=true", "snapshots=3"]),  # distilled from it, then IPPO
}


def with_instruments(protocol: dict) -> dict:
    """The protocol with a condition per held-out stranger of each section's `strangers` zoo and instrument it asks
    for (`INSTRUMENTS`: a best response, for BR-Prox; a learned stranger, a policy distilled from the stranger and
    trained on, seated as a stranger at a third, two thirds and the end of its training), one team each; the
    section's entry then names stranger -> condition, and `learned_strangers: {runs: [...]}` adds conditions trained
    elsewhere (SK teams from scratch, say) as learned strangers where they were trained. Instruments train with
    their section and are never among the teams it evaluates."""
    if not any(key in section for section in protocol.get("sections", {}).values() for key in INSTRUMENTS):
        return protocol
    conditions, sections = dict(protocol["conditions"]), {}
    for name, section in protocol["sections"].items():
        sections[name] = section = dict(section)
        for key, (pattern, own) in INSTRUMENTS.items():
            if key not in section:
                continue
            entry = section[key]
            path, overrides = condition_entry(entry)
            zoo = section["strangers"]
            section[key] = {stranger.name: pattern.format(stranger.name) for stranger in load_zoo(zoo).strangers}
            for stranger, condition in section[key].items():
                conditions[condition] = {"config": path, "overrides": [
                    *overrides, *own(stranger), f"zoo={zoo}", "runtime.teams=1"]}
            section[key].update({run: run for run in entry.get("runs", [])})
    return {**protocol, "conditions": conditions, "sections": sections}


def protocol_sections(protocol: dict) -> dict[str, dict]:
    """RESULTS.md's sections of a protocol: name -> {"title", "conditions"}; one section of every condition where
    the protocol names none."""
    return protocol.get("sections") or {WHOLE: {"title": "All conditions", "conditions": list(protocol["conditions"])}}


def named_conditions(protocol: dict, sections: list[str] | None, conditions: list[str] | None) -> list[str] | None:
    """The conditions that `--sections` and `--conditions` name together (None: neither was given, all of them).
    ValueError for a section the protocol does not have."""
    if sections is None and conditions is None:
        return None
    known = protocol_sections(protocol)
    unknown = [name for name in sections or [] if name not in known]
    if unknown:
        raise ValueError(f"--sections: {', '.join(unknown)} not in the protocol, which has {', '.join(known)}")
    return [*(name for section in sections or [] for name in section_conditions(known[section])),
            *(conditions or [])]


def section_conditions(section: dict) -> list[str]:
    """What a section trains and evaluates: its own conditions, those its claims compare it with (trained by another
    section, reused if there) and its instruments (a learned stranger trained elsewhere, where its entry is its own
    name, is reused only)."""
    instruments = [condition for key in INSTRUMENTS for name, condition in section.get(key, {}).items()
                   if name != condition]
    return [*section["conditions"], *section.get("compared", {}).values(), *instruments]


def select_conditions(protocol: dict, names: list[str] | None) -> tuple[dict, list[str]]:
    """The protocol cut to the conditions `names` (None: all): a family keeps its named SK conditions and stays while
    its IK condition is named, a cross pair while both sides are; and the conditions left out."""
    if names is None:
        return protocol, []
    unknown = [name for name in names if name not in protocol["conditions"]]
    if unknown:
        raise ValueError(f"--conditions: {', '.join(unknown)} not in the protocol, which has "
                         f"{', '.join(protocol['conditions'])}")
    selected = {
        **protocol,
        "conditions": {name: entry for name, entry in protocol["conditions"].items() if name in names},
        "families": {family: {**members, "sk": [name for name in members["sk"] if name in names]}
                     for family, members in protocol["families"].items() if members["ik"] in names},
        "cross": [pair for pair in protocol.get("cross", []) if all(name in names for name in pair)],
    }
    return selected, [name for name in protocol["conditions"] if name not in names]


def trained_before(name: str, path: str, overrides: list[str], teams: int, runs: Path) -> bool:
    """Whether every team of a condition has a checkpoint at the end of its budget (an earlier run trained it).
    Its teams' configs are checked as training checks them (`check_teams`); ConfigError, naming the condition,
    where their checkpoints hold other settings than the protocol's now, or met other scripted cooks than its zoo
    file holds now (they would not be resumed): asked of every condition before any trains, so that nothing trains
    for long and then stops at a condition trained before."""
    try:
        configs = check_teams(team_configs(load_config(path, condition_overrides(name, overrides, teams, runs))))
    except ConfigError as error:
        raise ConfigError(f"{name}: {error}") from None
    paths = latest_checkpoints(configs)
    if paths is None:
        return False  # none trained, or some: those start over together
    states = [load_checkpoint(path) for path in paths]
    try:
        for config, state in zip(configs, states):
            check_same_learning(config.run_path, config, state["config"])
            check_same_partners(config.run_path, config, state.get("met"))
    except ConfigError as error:
        raise ConfigError(f"{name}: {error}, or reproduce into another --out") from None
    return all(state["env_steps"] >= config.planned_steps for state, config in zip(states, configs))


def train_condition(name: str, path: str, overrides: list[str], teams: int, runs: Path) -> float:
    """Trains (or resumes, or skips) one condition's teams together; returns the wall seconds."""
    return train_config_file(path, condition_overrides(name, overrides, teams, runs))


def condition_overrides(name: str, overrides: list[str], teams: int, runs: Path) -> list[str]:
    """The protocol's seeds per condition first, so that a condition's own `runtime.teams` (a best response's one)
    keeps its count."""
    return [f"runtime.teams={teams}", *overrides, f"name={name}", f"run_dir={runs}"]


def train_conditions(entries: dict[str, tuple[str, list[str]]], teams: int, runs: Path, jobs: int) -> dict[str, float]:
    """Trains every condition (`entries`: name -> its config and overrides), `jobs` at a time in processes of their
    own (1: here, one after another); returns each one's wall seconds. RunStopped, naming the condition, as soon as
    one is stopped."""
    for name, (path, overrides) in entries.items():
        count = load_config(path, condition_overrides(name, overrides, teams, runs)).runtime.teams  # as it trains
        print(f"== {name}: {count} teams, {path} {' '.join(overrides)}", flush=True)
    if jobs == 1:
        trainings = {name: functools.partial(train_condition, name, path, overrides, teams, runs)
                     for name, (path, overrides) in entries.items()}
        return {name: named_stop(name, training) for name, training in trainings.items()}
    # Spawned, not forked: a fork of a process that has started JAX's threads may hang.
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {name: pool.submit(train_config_file, path, condition_overrides(name, overrides, teams, runs))
                   for name, (path, overrides) in entries.items()}
        return {name: named_stop(name, future.result) for name, future in futures.items()}


def named_stop(name: str, training: Callable[[], float]) -> float:
    """`training()`, whose RunStopped names the condition `name`."""
    try:
        return training()
    except RunStopped as error:
        raise RunStopped(error.exit_code - 128, f"{name}: {error}") from None


def read_summary(path: Path) -> dict[tuple[str, str], dict]:
    with open(path) as handle:
        return {(row["condition"], row["grids"]): row for row in csv.DictReader(handle)}


def value(summary: dict, condition: str, grids: str, key: str) -> float:
    row = summary.get((condition, grids))
    return float(row[key]) if row is not None and row[key] != "" else math.nan


def cross_pairs(summary: dict, pairs: list[list[str]]) -> list[str]:
    """Markdown rows: each pair a protocol adds, its cross-play beside each side's cross-play between its own
    seeds, on every grid group where the pair was measured (n/a where a side has no cross-play there)."""
    rows = []
    for first, second in pairs:
        pair = cross_condition(first, second)
        for condition, grids in summary:
            if condition == pair:
                values = [value(summary, name, grids, "xp") for name in (pair, first, second)]
                cells = " | ".join("n/a" if math.isnan(v) else f"{v:.2f}" for v in values)
                rows.append(f"| {first} | {second} | {grids} | {cells} |")
    return rows


@dataclass(frozen=True)
class Section:
    """A section of RESULTS.md as one run writes it: the conditions it trained of the section, the partners that its
    cross pairs need beside them, its families (name -> IK condition, layout -> SK condition, learner, the paper's
    family) and cross pairs, and its conditions this run left out."""

    name: str
    title: str
    conditions: list[str]
    evaluated: list[str]
    families: dict[str, tuple[str, dict[str, str], str, str | None]]
    cross: list[list[str]]
    left_out: list[str]
    strangers: str = ""  # a zoo file whose held-out strangers every team plays beside
    best_responses: dict[str, str] | None = None  # stranger -> the condition of its best response (BR-Prox)
    learned_strangers: dict[str, str] | None = None  # name -> the condition of a learned stranger
    compared: dict[str, str] | None = None  # one_teacher, diverse_teachers, zoo_partners: conditions of the claims


def sections_run(full: dict, protocol: dict, entries: dict[str, tuple[str, list[str]]]) -> list[Section]:
    """The sections of the `full` protocol that the run of `protocol` (its cut to the conditions named) trained
    conditions of, in the protocol's order."""
    sections = []
    for name, section in protocol_sections(full).items():
        conditions = [condition for condition in section["conditions"] if condition in protocol["conditions"]]
        if not conditions:
            continue
        families = {
            family: (members["ik"],
                     {load_config(entries[sk][0], entries[sk][1]).levels: sk for sk in members["sk"]},
                     members.get("learner", SCRATCH), members.get("paper"))
            for family, members in protocol["families"].items() if members["ik"] in conditions
        }  # fmt: skip
        cross = [pair for pair in protocol.get("cross", []) if pair[0] in conditions]
        partners = [*(sk for _, sks, _, _ in families.values() for sk in sks.values()), *(pair[1] for pair in cross)]
        evaluated = [condition for condition in protocol["conditions"] if condition in {*conditions, *partners}]
        left_out = [condition for condition in section["conditions"] if condition not in conditions]
        responses = {stranger: condition for stranger, condition in section.get("best_responses", {}).items()
                     if condition in protocol["conditions"]}
        sections.append(Section(name, section["title"], conditions, evaluated, families, cross, left_out,
                                section.get("strangers", ""), responses, section.get("learned_strangers", {}),
                                section.get("compared", {})))
    return sections


def proxy_settings(human_proxies: bool | dict) -> ProxySettings | None:
    """How the protocol's human proxies are fitted (`evaluation: {human_proxies: true}`, or a mapping of
    `ProxySettings` fields that sizes them, e.g. `{epochs: 1, candidates: 1, fine_tune_steps: 0}` for a tiny run);
    None: no human proxies."""
    if not human_proxies:
        return None
    settings = human_proxies if isinstance(human_proxies, dict) else {}
    fields = {field.name for field in dataclasses.fields(ProxySettings)}
    unknown = sorted(set(settings) - fields)
    if unknown:
        raise ValueError(f"evaluation.human_proxies: unknown settings {', '.join(unknown)} (the settings are "
                         f"{', '.join(sorted(fields))})")
    return ProxySettings(**settings)


def human_proxies(out: Path, settings: ProxySettings) -> Path:
    """The test split's human proxy of every classic layout drawn inside a 7x7 kitchen, in `out`/runs (fetched and
    fitted the first time: `kitchen-humans fetch`, then `kitchen-humans train --fit-on test`)."""
    runs = out / "runs"
    missing = [g for g in PADDED_LAYOUTS if not (runs / HUMAN_PROXY_RUN.format(grid=g) / "checkpoints").is_dir()]
    if missing:
        if not (out / "data").is_dir():
            fetch(out / "data", out / "cache", progress=False)  # the download stays in --out, as all the rest
        train_proxies(out / "data", runs, missing, settings, 32, out / "proxies.md", fit_on="test")
    return runs


def best_response_runs(section: Section, runs: Path, first_seed: int) -> dict[str, str]:
    """Each stranger's best response: the run of its condition's one team, trained with the protocol's first seed
    (`seed=` on the command line moves it)."""
    return {stranger: str(runs / condition / f"seed{first_seed}")
            for stranger, condition in (section.best_responses or {}).items()}


def evaluate_section(section: Section, out: Path, evaluation: dict, device: str, proxies: Path | None,
                     workers: int, first_seed: int) -> Path:
    """Plays the section's teams (`kitchen-eval`'s code, in `workers` processes): self-play, cross-play between
    each condition's seeds, each family's IK against its SK conditions and the section's cross pairs, beside the
    scripted cook and the human proxies; returns the folder of its tables and figures."""
    config = EvalConfig(
        conditions={name: str(out / "runs" / name / "seed*") for name in section.evaluated},
        cross=[*([ik, name] for ik, sk, _, _ in section.families.values() for name in sk.values()), *section.cross],
        layouts=[*EXPANDED_LAYOUTS, *(PADDED_LAYOUTS if proxies else [])], heldout=evaluation["heldout"],
        human_proxies=str(proxies or ""), strangers=section.strangers,
        best_responses=best_response_runs(section, out / "runs", first_seed),
        learned_strangers={name: str(out / "runs" / condition / "seed*")
                           for name, condition in (section.learned_strangers or {}).items()
                           if any((out / "runs" / condition).glob("seed*/checkpoints/latest.pt"))},
        rollouts=evaluation["rollouts"], max_steps=evaluation.get("max_steps", 256), workers=workers,
        collector=evaluation.get("collector", EvalConfig().collector),
        heatmaps=evaluation.get("heatmaps", []), runtime=DeviceConfig(device=device),
        out_dir=str(out / "eval" / section.name), progress=False,
    ).check()  # fmt: skip
    evaluate(config)
    return Path(config.out_dir)


@dataclass(frozen=True)
class RunFacts:
    """What every section a command writes says of that command."""

    command: str
    protocol: str
    code: str  # the commit the command ran (`code_version`), read when it started
    date: str
    machine: str
    teams: int
    overrides: list[str]
    own_overrides: dict[str, list[str]]
    jobs: int
    eval_workers: int  # the processes playing each section's evaluation
    training_seconds: float  # wall time of all the command's training
    condition_seconds: dict[str, float]  # each condition's, in its own process
    reused: list[str]  # conditions an earlier run had trained already: this one trained nothing of them
    evaluation: dict
    proxies: Path | None


def budget(config: TrainConfig, teams: int) -> str:
    """The budget line of a section whose conditions train as `config` does."""
    distilled = ""
    if config.init_from == PLANNER_START:
        main_job = load_config(MAIN_JOB, [])
        same, multiple = "the same budget", f"{main_job.total_steps / config.total_steps:.2g}x this"
        fitted = "the rounds' data" if config.distill.replay == 0 else \
            f"the newest round and {config.distill.replay:g}x as many earlier kitchens"
        distilled = (f", after the scripted cook is distilled into it ({config.distill.rounds} DAgger rounds of "
                     f"{config.distill.kitchens} kitchens x {config.rollout_steps} steps, {config.distill.epochs} "
                     f"passes over {fitted} after each; the main job, `{MAIN_JOB.relative_to(ROOT)}`, trains "
                     f"{main_job.total_steps:,} steps after {main_job.distill.rounds} rounds of "
                     f"{main_job.distill.epochs} passes, "
                     f"{same if main_job.total_steps == config.total_steps else multiple})")
    return (f"- **Budget:** {config.total_steps:,} env steps per team ({config.num_updates} updates of "
            f"{config.num_envs} kitchens x {config.rollout_steps} steps){distilled}, {teams} teams (seeds "
            f"{config.seed}..{config.seed + teams - 1}) per condition; the paper trains {PAPER_STEPS:.0e} steps per "
            f"team (this is 1/{PAPER_STEPS / config.total_steps:,.0f} of it), 6 seeds. Where a claim does not hold "
            "here, the budget comes first: read the training curves of the runs (`tensorboard --logdir` on the "
            "runs' folder) before the claim.")


def made_lines(section: Section, facts: RunFacts, eval_seconds: float) -> list[str]:
    """The section's machine and times (each condition's training, the evaluation), and what the evaluation seats."""
    return [
        f"- **Machine:** {facts.machine}. **Time:** training {facts.training_seconds / 60:.0f} min of wall time for "
        f"the command's {len(facts.condition_seconds) - len(facts.reused)} conditions trained, {facts.jobs} at a "
        "time, each in its own process (distillation, collection and updates): "
        + ", ".join(f"{name} reused (trained by an earlier run)" if name in facts.reused
                    else f"{name} {facts.condition_seconds[name] / 60:.1f} min"
                    for name in dict.fromkeys([*section.evaluated, *(section.best_responses or {}).values(),
                                               *(section.learned_strangers or {}).values()])
                    if name in facts.condition_seconds)
        + f"; evaluation {eval_seconds / 60:.1f} min ({facts.eval_workers} process"
        f"{'es' if facts.eval_workers > 1 else ''}).",
        f"- **Evaluation:** the 5 expanded layouts and {facts.evaluation['heldout']} held-out levels, "
        f"{facts.evaluation['rollouts']} rollouts of {facts.evaluation.get('max_steps', 256)} steps per pair and grid; "
        "the scripted cook "
        f"(`torch_kitchen/partners/scripted_cook.py`) beside every team; \"{SCRIPTED_CONDITION}\" is its own self-play."
        + (f" The classic layouts that fit a 7x7 kitchen, drawn inside one ({', '.join(PADDED_LAYOUTS)}), with "
           "each one's human proxy beside every team (behaviour-cloned from the 2019 human games' test split, so no "
           f"team is tuned to it; how the proxies play: `{facts.proxies.parent / 'proxies.md'}`); "
           "\"human_proxy_<layout>\" is two proxies together." if facts.proxies else "")
        + (f" Beside every team, both seats, the held-out strangers of `{section.strangers}` (`kitchen-zoo`: scripted "
           "cooks of conventions no shipped config trains with), scored against two of each stranger."
           if section.strangers else ""),
    ]


def section_markdown(section: Section, facts: RunFacts, config: TrainConfig, eval_dir: Path,
                     eval_seconds: float, pictures: list[str]) -> str:
    """The section's text, between its markers: how it was made, its claims, cross pairs, tables and figures."""
    summary = read_summary(eval_dir / "summary.csv")
    scores = SeedScores.read(eval_dir)
    planner = config.init_from == PLANNER_START
    own = {name: facts.own_overrides[name] for name in section.conditions if facts.own_overrides[name]}
    lines = [
        SECTION_START.format(section.name),
        f"## {section.title}",
        "",
        f"Written by `{facts.command}` on {facts.date} (protocol `{facts.protocol}`, code at `{facts.code}`). Every "
        "number in this section "
        "was measured by that run's evaluation, of teams it trained or, where the time line says so, reused.",
        "",
        budget(config, facts.teams),
        *([f"- **Conditions:** {len(section.conditions)} of the section's "
           f"{len(section.conditions) + len(section.left_out)}; not run here: {', '.join(section.left_out)}."]
          if section.left_out else []),
        f"- **Shared overrides:** `{' '.join(facts.overrides)}`.",
        *(f"- **{name}** adds `{' '.join(overrides)}`." for name, overrides in own.items()),
        *made_lines(section, facts, eval_seconds),
        "",
        "### Claims",
        "",
        CLAIMS_START,
        *CLAIMS_HEADER,
        *claims_table(section, scores, config.total_steps, planner),
        CLAIMS_END,
        "",
        *([
            "### Cross-play across learners and teachers",
            "",
            "Teams that imitated one teacher share its conventions, so their cross-play between seeds can overstate "
            "how well they play with strangers. Each pair the protocol adds: its cross-play, beside each side's "
            "cross-play between its own seeds.",
            "",
            "| team | partner | grids | XP of the pair | XP within the team | XP within the partner |",
            "|---|---|---|---:|---:|---:|",
            *cross_pairs(summary, section.cross),
            "",
        ] if section.cross else []),
        "### Self-play, cross-play and the scripted partner",
        "",
        (eval_dir / "eval.md").read_text().rstrip(),
        "",
        "### Figures",
        "",
        *pictures,
        SECTION_END.format(section.name),
    ]
    return "\n".join(lines)


def copy_figures(eval_dir: Path, results: Path, section: str) -> list[str]:
    """The evaluation's pictures copied beside RESULTS.md (docs/results/<section>/), as Markdown images."""
    figures = results.parent / "docs" / "results" / section
    figures.mkdir(parents=True, exist_ok=True)
    pictures = []
    for picture in sorted(eval_dir.glob("*.png")):
        shutil.copy(picture, figures / picture.name)
        pictures.append(f"![{picture.stem}](docs/results/{section}/{picture.name})")
    return pictures


def claims_table(section: Section, scores: SeedScores, budget: int, planner: bool) -> list[str]:
    """The section's claims rows: each family's claims (and, for a planner-guided family, whether it outplays its
    teacher), what a shared teacher adds to each cross pair of its IK condition, and the claims beside the
    strangers."""
    rows = []
    for family, (ik, sk, learner, paper) in section.families.items():
        found = family_claims(scores, family, ik, sk, budget, paper)
        found += [row for first, second in section.cross if first == ik for row in shared_teacher(scores, ik, second)]
        found += beyond_teacher(scores, ik) if planner else []
        rows += [(family, learner, row) for row in found]
    rows += stranger_claims(scores, section.families, section.compared or {})
    return [f"| {who} | {learner} | {claim} | {here} | {decided} |" for who, learner, (claim, here, decided) in rows]


def read_sections(text: str) -> dict[str, str]:
    """RESULTS.md's sections, name -> text between (and with) its markers, in the file's order."""
    pattern = re.compile(r"<!-- section: (\S+) -->.*?<!-- /section: \1 -->", re.S)
    return {match.group(1): match.group(0) for match in pattern.finditer(text)}


# How the top table marks the verdicts of a section written before claims were decided by intervals over seeds.
BY_MEANS = " (by means of seeds, no interval: re-run this section)"


def claims_rows(section: str) -> list[str]:
    """The rows of a section's claims table, without its header. A table under another header was written before
    verdicts came from intervals: its rows compared means, and their verdicts say so (`BY_MEANS`)."""
    start, end = section.find(CLAIMS_START), section.find(CLAIMS_END)
    if start < 0 or end < 0:
        return []
    header, _, *rows = [row for row in section[start + len(CLAIMS_START):end].strip().splitlines()
                        if row.startswith("|")]
    if header == CLAIMS_HEADER[0]:
        return rows
    return [row.removesuffix(" |") + BY_MEANS + " |" for row in rows]


def write_results(path: Path, written: dict[str, str], order: list[str]) -> None:
    """RESULTS.md with the sections `written` replacing their earlier text, every other section kept as it was
    written, in the protocol's `order` (others after), and the claims of them all gathered at the top."""
    sections = read_sections(path.read_text()) if path.exists() else {}
    sections.update(written)
    names = [*(name for name in order if name in sections), *(name for name in sections if name not in order)]
    lines = [
        TITLE,
        "",
        "Each section below was written by the command it names (`python scripts/reproduce.py PROTOCOL --sections "
        "NAME`), which rewrites its own section and keeps the others as they were written. Each section says its "
        "budget, machine, time and date; the claims table gathers every section's claims, and its family and learner "
        "columns say which teams each row measures. A verdict is read from a 95% interval over seeds "
        "(docs/evaluation.md); one that a section written before such intervals decided by comparing means says so: "
        f"{BY_MEANS.strip()}.",
        "",
        "## The paper's claims, here",
        "",
        *CLAIMS_HEADER,
        *(row for name in names for row in claims_rows(sections[name])),
        "",
        *(part for name in names for part in (sections[name], "")),
    ]
    path.write_text("\n".join(lines))


def reproduce_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("protocol", help="a protocol file (configs/protocols/reduced.yaml or paper.yaml)")
    parser.add_argument("overrides", nargs="*", help="key=value overrides for every condition")
    parser.add_argument("--out", default="results/reduced", help="runs and evaluation go here")
    parser.add_argument("--results", default="RESULTS.md", help="the report to write")
    parser.add_argument("--teams", type=int, help="seeds per condition (default: the protocol's)")
    parser.add_argument("--rollouts", type=int, help="evaluation episodes per pair and grid (default: the protocol's)")
    parser.add_argument("--heldout", type=int, help="held-out levels in the evaluation (default: the protocol's)")
    parser.add_argument("--max-steps", type=int,
                        help="steps of an evaluation episode (default: the protocol's, else 256)")
    parser.add_argument("--collector", choices=EVAL_COLLECTORS,
                        help="how the evaluation plays, kitchen-eval's `collector` (default: the protocol's, else "
                             f"{EvalConfig().collector})")
    parser.add_argument("--sections", nargs="+", metavar="NAME",
                        help="train, evaluate and rewrite these of the protocol's sections only (default: all)")
    parser.add_argument("--conditions", nargs="+", metavar="NAME",
                        help="train and evaluate these of the protocol's conditions only (default: all)")
    parser.add_argument("--strangers", metavar="ZOO",
                        help="seat the held-out strangers of this zoo file (kitchen-zoo draw) in every section that "
                             "seats strangers, instead of the protocol's zoo; its best responses and learned strangers "
                             "are trained for them")
    parser.add_argument("--no-human-proxies", action="store_true",
                        help="evaluate without the human proxies even where the protocol seats them (fetching the "
                             "2019 games and fitting five proxies takes longer than a tiny run)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="conditions trained at a time, each in its own process (2 uses both cores of a 2-core "
                             "CPU; the results are the same)")
    return parser


def run_facts(args, argv, entries: dict, device: str, overrides: list[str], teams: int, started: float,
              seconds: dict, reused: list[str], evaluation: dict, proxies, out: Path, code: str) -> RunFacts:
    """What the report says of the run: its command, protocol, date, machine, budget and times."""
    machine = f"{machine_name()}, device {device}"
    if device.startswith("cuda") and torch.cuda.is_available():
        machine += f" ({torch.cuda.get_device_name()})"
    return RunFacts(
        command=" ".join(["python scripts/reproduce.py", *(argv if argv is not None else sys.argv[1:])]),
        protocol=args.protocol, code=code, date=datetime.date.today().isoformat(), machine=machine, teams=teams,
        overrides=overrides, own_overrides={name: own for name, (_, own) in entries.items()}, jobs=args.jobs,
        eval_workers=min(args.jobs, os.cpu_count() or 1) if device == "cpu" else 1,
        training_seconds=time.perf_counter() - started, condition_seconds=seconds, reused=reused, evaluation=evaluation,
        proxies=human_proxies(out / "humans", proxies) if proxies else None,
    )  # fmt: skip


def main(argv=None) -> int:
    parser = reproduce_parser()
    args = parser.parse_intermixed_args(argv)  # overrides may follow the options
    if args.jobs < 1:
        parser.error(f"--jobs must be at least 1, got {args.jobs}")
    try:
        full = with_instruments(with_strangers(yaml.safe_load(Path(args.protocol).read_text()), args.strangers))
        protocol, _ = select_conditions(full, named_conditions(full, args.sections, args.conditions))
        proxies = None if args.no_human_proxies else proxy_settings(protocol.get("evaluation", {}).get("human_proxies"))
    except OSError as error:
        parser.error(f"{args.protocol}: {error.strerror}")
    except ValueError as error:
        parser.error(str(error))
    out, results = Path(args.out), Path(args.results)
    overrides = [*protocol.get("overrides", []), *args.overrides]
    teams = args.teams or protocol["teams"]
    entries = {name: condition_entry(entry) for name, entry in protocol["conditions"].items()}
    # the shared overrides, the condition's own, then the command line's
    trained = {name: (path, [*protocol.get("overrides", []), *own, *args.overrides])
               for name, (path, own) in entries.items()}
    started, code = time.perf_counter(), code_version()
    try:
        reused = [name for name, (path, own) in trained.items() if trained_before(name, path, own, teams, out / "runs")]
        seconds = train_conditions(trained, teams, out / "runs", args.jobs)
    except RunStopped as error:
        print(f"reproduce: {error}; run the same command again to continue", file=sys.stderr)
        return error.exit_code
    except ConfigError as error:  # e.g. a condition's runs trained with other settings than the protocol's now
        print(f"reproduce: error: {error}", file=sys.stderr)
        return 2
    evaluation = {**protocol.get("evaluation", {}),
                  **{key: getattr(args, key) for key in ("rollouts", "heldout", "max_steps", "collector")
                     if getattr(args, key) is not None}}
    shared = load_config(next(iter(entries.values()))[0], overrides)  # its device and first seed: every condition's
    device = shared.runtime.device
    facts = run_facts(args, argv, entries, device, overrides, teams, started, seconds, reused, evaluation, proxies,
                      out, code)
    written = {}
    for section in sections_run(full, protocol, entries):
        if args.sections and section.name not in args.sections:
            continue  # a section of a condition another one compares with: it stays as it was written
        evaluated = time.perf_counter()
        try:
            eval_dir = evaluate_section(section, out, evaluation, device, facts.proxies, facts.eval_workers,
                                        shared.seed)
        except (ConfigError, CheckpointError) as error:  # e.g. a run the section reads that is missing
            print(f"reproduce: error: {error}", file=sys.stderr)
            return 2
        config = load_config(*trained[section.conditions[0]])
        written[section.name] = section_markdown(section, facts, config, eval_dir,
                                                 time.perf_counter() - evaluated,
                                                 copy_figures(eval_dir, results, section.name))
    write_results(results, written, list(protocol_sections(full)))
    print(f"wrote {results} (sections {', '.join(written)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
