"""The paper's experiment as one command: train every condition of a protocol, evaluate the whole grid, write
RESULTS.md with the numbers beside the paper's claims.

    python scripts/reproduce.py configs/protocols/reduced.yaml      # about 75 min of training on a 2-core CPU
    python scripts/reproduce.py configs/protocols/paper.yaml        # the paper's budget, on a GPU
    python scripts/reproduce.py configs/protocols/reduced.yaml --out results/reduced --results RESULTS.md

A protocol file names the conditions (a trainer config each, or a config and the condition's own overrides,
applied after the shared ones), the overrides they share, the seeds trained together per condition (`teams`),
the families compared (an IK condition and the SK conditions of the same architecture and learner, which it
cross-plays; `learner` says how they learn, `paper` whose of the paper's figures apply), further pairs to
cross-play (`cross`), and the evaluation's sizes; `evaluation: {human_proxies: true}` also seats a human proxy
(behaviour-cloned from the 2019 human games' test split, `kitchen-humans`) beside every team on the classic
layouts drawn inside a 7x7 kitchen, which join the test grids.
Training writes `<out>/runs/<condition>/seed<k>`; a condition already trained is skipped and one that stopped
part-way is resumed, so an interrupted reproduction continues where it stopped. Extra `key=value` arguments
override every condition (e.g. `total_steps=1e5` for a smoke run); `--conditions` runs part of a protocol (the
families and cross pairs of the conditions named; RESULTS.md lists those left out). The evaluation (`kitchen-eval`'s
code) goes to `<out>/eval`; RESULTS.md gets its tables, the claims compared, the budget, machine, wall times and the
command.
"""

from __future__ import annotations

import argparse
import csv
import math
import shutil
import sys
import time
from pathlib import Path

import torch
import yaml

from jax_env import EXPANDED_LAYOUTS, PADDED_LAYOUTS
from trainers.composer import load_config
from trainers.config import DeviceConfig, EvalConfig
from trainers.evaluate import HUMAN_PROXY_RUN, SCRIPTED_CONDITION, cross_condition, evaluate
from trainers.humans import CACHE, fetch
from trainers.humans import train as train_proxies
from trainers.machine import machine_name
from trainers.resume import RunStopped
from trainers.train_command import train_or_resume
from trainers.training_run import team_configs

HELDOUT = "held-out"
PAPER_STEPS = 2e9  # env steps per team in the paper
# Deliveries in cross-play on held-out levels the paper reports for IK teams at 2e9 steps (Fig. 7), per family.
PAPER_HELDOUT_XP = {"MLP": 9, "GNN": 10}


SCRATCH = "IPPO from scratch"  # the paper's learner, a family's unless it names another


def condition_entry(entry: str | dict) -> tuple[str, list[str]]:
    """A protocol's condition -> (its trainer config, its own overrides): a path, or {config:, overrides:}, where
    overrides may hold lists (a YAML alias to another condition's) that count as their items."""
    if isinstance(entry, str):
        return entry, []
    overrides = []
    for item in entry.get("overrides", []):
        overrides += item if isinstance(item, list) else [item]
    return entry["config"], overrides


def select_conditions(protocol: dict, names: list[str] | None) -> tuple[dict, list[str]]:
    """The protocol cut to the conditions `names` (None: all of them): a family keeps its named SK conditions and
    stays while its IK condition is named, a cross pair while both sides are; and the conditions left out."""
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


def train_condition(name: str, path: str, overrides: list[str], teams: int, runs: Path) -> None:
    """Trains (or resumes, or skips) one condition's teams together."""
    config = load_config(path, [*overrides, f"name={name}", f"runtime.teams={teams}", f"run_dir={runs}"])
    train_or_resume(team_configs(config))


def logged_training_seconds(condition: Path) -> float:
    """Seconds a condition's teams spent training, from their own logs (so a resumed or skipped condition counts
    too): each batch's steps, all teams', over the steps per second logged for it, which time the whole batch
    (collection and every team's update) in the log of the condition's last team."""
    seeds = sorted(condition.glob("seed*"), key=lambda seed: int(seed.name.removeprefix("seed")))
    rates = seeds[-1] / "csv" / "scalars" / "charts" / "steps_per_second.csv"
    seconds, previous = 0.0, 0.0
    for line in rates.read_text().splitlines():
        if line.strip():
            steps, rate = map(float, line.split(",")[:2])
            seconds += len(seeds) * (steps - previous) / rate
            previous = steps
    return seconds


def read_summary(path: Path) -> dict[tuple[str, str], dict]:
    with open(path) as handle:
        return {(row["condition"], row["grids"]): row for row in csv.DictReader(handle)}


def value(summary: dict, condition: str, grids: str, key: str) -> float:
    row = summary.get((condition, grids))
    return float(row[key]) if row is not None and row[key] != "" else math.nan


def claims(summary: dict, family: str, ik: str, sk: dict[str, str], budget: int, learner: str = SCRATCH,
           paper: str | None = None) -> list[str]:
    """Markdown rows: each of the paper's claims for one family (an IK condition, layout -> its SK condition) and
    the learner it was tested under, what came out here, and whether it holds at this budget (env steps per team).
    A family without SK conditions has only its held-out claim; `paper`: the paper's family whose held-out figure
    applies (default: this one's name)."""
    heldout = next((grids for _, grids in summary if grids.startswith(HELDOUT)), None)
    rows = []
    if sk:
        ik_xp = {layout: value(summary, ik, layout, "xp") for layout in sk}
        sk_xp = {layout: value(summary, condition, layout, "xp") for layout, condition in sk.items()}
        wins = sum(ik_xp[layout] > sk_xp[layout] for layout in sk)
        pairs = ", ".join(f"{layout.removesuffix('_7x7')} {ik_xp[layout]:.2f} vs {sk_xp[layout]:.2f}" for layout in sk)
        rows.append(("IK beats SK in cross-play on the 5 layouts (Fig. 3a)", pairs, f"{wins} of {len(sk)} layouts"))
        if heldout:
            sk_sp = [value(summary, condition, heldout, "sp") for condition in sk.values()]
            rows.append(("SK scores 0 on generated levels, even in self-play (Fig. 7)",
                         f"SK self-play on {heldout}: {min(sk_sp):.2f} to {max(sk_sp):.2f}",
                         "holds" if max(sk_sp) < 0.5 else "does not hold"))
    if heldout and (paper or family) in PAPER_HELDOUT_XP:
        paper, ik_heldout = PAPER_HELDOUT_XP[paper or family], value(summary, ik, heldout, "xp")
        at_paper_budget = ("holds" if ik_heldout >= paper - 1 else "does not hold") if budget >= PAPER_STEPS else (
            f"{budget:.1e} steps, not 2e9: not comparable")
        rows.append((f"IK reaches about {paper} deliveries in cross-play on held-out levels at 2e9 steps (Fig. 7)",
                     f"IK cross-play on {heldout}: {ik_heldout:.2f}", at_paper_budget))
    if sk:
        ik_gap = [value(summary, ik, layout, "gap") for layout in sk]
        sk_gap = [value(summary, condition, layout, "gap") for layout, condition in sk.items()]
        smaller = sum(a < b for a, b in zip(ik_gap, sk_gap))
        rows.append(("The SP - XP gap is smaller for IK (Fig. 3b)",
                     f"mean gap IK {sum(ik_gap) / len(ik_gap):.2f}, SK {sum(sk_gap) / len(sk_gap):.2f}",
                     f"smaller on {smaller} of {len(sk)} layouts"))
    return [f"| {family} | {learner} | {claim} | {ours} | {verdict} |" for claim, ours, verdict in rows]


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


def human_proxies(out: Path) -> Path:
    """The test split's human proxy of every classic layout drawn inside a 7x7 kitchen, in `out`/runs (fetched and
    fitted the first time: `kitchen-humans fetch`, then `kitchen-humans train --fit-on test`)."""
    from trainers.behaviour_cloning import ProxySettings

    runs = out / "runs"
    missing = [g for g in PADDED_LAYOUTS if not (runs / HUMAN_PROXY_RUN.format(grid=g) / "checkpoints").is_dir()]
    if missing:
        if not (out / "data").is_dir():
            fetch(out / "data", CACHE, progress=False)
        train_proxies(out / "data", runs, missing, ProxySettings(), 32, out / "proxies.md", fit_on="test")
    return runs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("protocol", help="a protocol file (configs/protocols/reduced.yaml or paper.yaml)")
    parser.add_argument("overrides", nargs="*", help="key=value overrides for every condition")
    parser.add_argument("--out", default="results/reduced", help="runs and evaluation go here")
    parser.add_argument("--results", default="RESULTS.md", help="the report to write")
    parser.add_argument("--teams", type=int, help="seeds per condition (default: the protocol's)")
    parser.add_argument("--rollouts", type=int, help="evaluation episodes per pair and grid (default: the protocol's)")
    parser.add_argument("--heldout", type=int, help="held-out levels in the evaluation (default: the protocol's)")
    parser.add_argument("--conditions", nargs="+", metavar="NAME",
                        help="train and evaluate these of the protocol's conditions only (default: all)")
    args = parser.parse_args(argv)
    try:
        protocol, left_out = select_conditions(yaml.safe_load(Path(args.protocol).read_text()), args.conditions)
    except OSError as error:
        parser.error(f"{args.protocol}: {error.strerror}")
    except ValueError as error:
        parser.error(str(error))
    out = Path(args.out)
    overrides = [*protocol.get("overrides", []), *args.overrides]
    teams, conditions = args.teams or protocol["teams"], protocol["conditions"]
    entries = {name: condition_entry(entry) for name, entry in conditions.items()}
    families = {  # family -> (its IK condition, layout -> its SK condition, its learner, the paper's family)
        family: (members["ik"],
                 {load_config(entries[name][0], entries[name][1]).levels: name for name in members["sk"]},
                 members.get("learner", SCRATCH), members.get("paper"))
        for family, members in protocol["families"].items()
    }

    seconds = {}
    for name, (path, own) in entries.items():
        print(f"== {name}: {teams} teams, {path} {' '.join([*overrides, *own])}", flush=True)
        try:
            train_condition(name, path, [*overrides, *own], teams, out / "runs")
        except RunStopped as error:
            print(f"reproduce: {name}: {error}; run the same command again to continue", file=sys.stderr)
            return error.exit_code
        seconds[name] = logged_training_seconds(out / "runs" / name)
    evaluation = {**protocol.get("evaluation", {}),
                  **{key: getattr(args, key) for key in ("rollouts", "heldout") if getattr(args, key) is not None}}
    shared = load_config(entries[next(iter(conditions))][0], overrides)  # what every condition shares: budget, device
    device = shared.runtime.device
    proxies = human_proxies(out / "humans") if evaluation.get("human_proxies") else None
    eval_config = EvalConfig(
        conditions={name: str(out / "runs" / name / "seed*") for name in conditions},
        cross=[*([ik, name] for ik, sk, _, _ in families.values() for name in sk.values()),
               *protocol.get("cross", [])],
        layouts=[*EXPANDED_LAYOUTS, *(PADDED_LAYOUTS if proxies else [])], heldout=evaluation["heldout"],
        human_proxies=str(proxies or ""),
        rollouts=evaluation["rollouts"], max_steps=evaluation.get("max_steps", 256),
        heatmaps=evaluation.get("heatmaps", []), runtime=DeviceConfig(device=device),
        out_dir=str(out / "eval"), progress=False,
    ).check()  # fmt: skip
    evaluated = time.perf_counter()
    evaluate(eval_config)
    seconds["evaluation"] = time.perf_counter() - evaluated

    summary = read_summary(out / "eval" / "summary.csv")
    figures = Path(args.results).parent / "docs" / "results"
    figures.mkdir(parents=True, exist_ok=True)
    pictures = []
    for picture in sorted((out / "eval").glob("*.png")):
        shutil.copy(picture, figures / picture.name)
        pictures.append(f"![{picture.stem}](docs/results/{picture.name})")
    machine = f"{machine_name()}, device {device}"
    if device.startswith("cuda") and torch.cuda.is_available():
        machine += f" ({torch.cuda.get_device_name()})"
    command = " ".join(["python scripts/reproduce.py", *(argv if argv is not None else sys.argv[1:])])
    lines = [
        "# Results: the paper's experiment at a reduced budget",
        "",
        f"Written by `{command}` (protocol `{args.protocol}`). Every number below was measured by that run.",
        "",
        f"- **Budget:** {shared.total_steps:,} env steps per team ({shared.num_updates} updates of "
        f"{shared.num_envs} kitchens x {shared.rollout_steps} steps), {teams} teams (seeds "
        f"{shared.seed}..{shared.seed + teams - 1}) per condition; the paper trains {PAPER_STEPS:.0e} steps per team "
        f"(this is 1/{PAPER_STEPS / shared.total_steps:,.0f} of it), 6 seeds. Where a claim does not hold here, the "
        "budget comes first: read the training curves of the runs (`tensorboard --logdir "
        f"{out / 'runs'}`) before the claim.",
        *([f"- **Conditions:** {len(conditions)} of the protocol's {len(conditions) + len(left_out)}; not run here: "
           f"{', '.join(left_out)}."] if left_out else []),
        f"- **Shared overrides:** `{' '.join(overrides)}`.",
        *(f"- **{name}** adds `{' '.join(own)}`." for name, (_, own) in entries.items() if own),
        f"- **Machine:** {machine}. **Time:** {sum(seconds.values()) / 60:.0f} min in all; "
        + ", ".join(f"{name} {s / 60:.1f} min" for name, s in seconds.items())
        + " (training from the runs' logs: collection and updates; evaluation: its wall time).",
        f"- **Evaluation:** the 5 expanded layouts and {evaluation['heldout']} held-out levels, "
        f"{evaluation['rollouts']} rollouts per pair and grid; the scripted cook "
        f"(`torch_kitchen/scripted.py`) beside every team; \"{SCRIPTED_CONDITION}\" is its own self-play."
        + (f" The classic layouts that fit a 7x7 kitchen, drawn inside one ({', '.join(PADDED_LAYOUTS)}), with "
           "each one's human proxy beside every team (behaviour-cloned from the 2019 human games' test split, so no "
           "team is tuned to it; how the proxies play: "
           f"`{out / 'humans' / 'proxies.md'}`); \"human_proxy_<layout>\" is two proxies together."
           if proxies else ""),
        "",
        "## The paper's claims, here",
        "",
        "| family | learner | claim | here | at this budget |",
        "|---|---|---|---|---|",
        *(row for family, (ik, sk, learner, paper) in families.items()
          for row in claims(summary, family, ik, sk, shared.total_steps, learner, paper)),
        "",
        *([
            "## Cross-play across learners and teachers",
            "",
            "Teams that imitated one teacher share its conventions, so their cross-play between seeds can overstate "
            "how well they play with strangers. Each pair the protocol adds: its cross-play, beside each side's "
            "cross-play between its own seeds.",
            "",
            "| team | partner | grids | XP of the pair | XP within the team | XP within the partner |",
            "|---|---|---|---:|---:|---:|",
            *cross_pairs(summary, protocol["cross"]),
            "",
        ] if protocol.get("cross") else []),
        "## Self-play, cross-play and the scripted partner",
        "",
        (out / "eval" / "eval.md").read_text(),
        "## Figures",
        "",
        *pictures,
        "",
    ]
    Path(args.results).write_text("\n".join(lines))
    print(f"wrote {args.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
