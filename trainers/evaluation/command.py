"""The whole evaluation job (`evaluate`), the report of a finished training run, and the command line
`kitchen-eval`."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from jax_env import EXPANDED_LAYOUTS, load_layout
from jax_env.generator import SIZES as GENERATOR_SIZES
from jax_env.layouts import padded_layouts
from torch_kitchen.partners.conventions import ConventionError, load_zoo
from trainers.checkpoint import CheckpointError
from trainers.config import ConfigError, DeviceConfig, EvalConfig
from trainers.config.compose import config_help, load_config, save_config
from trainers.evaluation.figures import draw_figures, draw_heatmap, draw_learning_curve, draw_stranger_heatmap
from trainers.evaluation.gifs import parse_gif_request, record_gif
from trainers.evaluation.pairs import Outcomes, evaluation_grids, make_matchups, play
from trainers.evaluation.strangers import (
    StrangerOutcomes,
    load_human_proxies,
    markdown_strangers,
    play_with_strangers,
    stranger_pair_rows,
    stranger_rows,
    with_human_proxies,
)
from trainers.evaluation.tables import (
    markdown_summary,
    pair_rows,
    seed_rows,
    summary_rows,
    visit_shares,
    write_csv,
)
from trainers.evaluation.teams import (
    STRANGERS_CONDITION,
    Team,
    convention_team,
    load_learned_strangers,
    load_population,
    load_team,
    scripted_cook_team,
)
from trainers.plugins import PluginError, add_plugin_option, import_plugins


def load_best_responses(runs: dict[str, str], strangers: list[str], evaluated: list, device: str) -> dict:
    """{stranger index: its best response} of `best_responses` (trained with `best_response_to` that stranger); a
    best response among the evaluated teams, or one of another stranger, is a ConfigError in one line."""
    for team in evaluated:
        target = team.config.algorithm_config.get("best_response_to")
        if target:
            raise ConfigError(f"{team.name} is a best response to the stranger {target!r}, an evaluation instrument "
                              "rather than a team: give it under best_responses")
    if runs and not strangers:
        raise ConfigError("best_responses scores teams over the strangers' best responses: give strangers=ZOO too")
    found = {}
    for name, run in runs.items():
        if name not in strangers:
            raise ConfigError(f"best_responses names {name!r}, which is not a stranger of the zoo: "
                              f"{', '.join(strangers)}")
        team = load_team(run, device)
        if team.config.algorithm_config.get("best_response_to") != name:
            raise ConfigError(f"best_responses: {run} was not trained as the best response to {name!r} "
                              "(algorithm=zoo_ippo algorithm_config.best_response_to=NAME)")
        found[strangers.index(name)] = team
    return found


def refuse_met_strangers(teams: list[Team], strangers: list[Team], where: str) -> None:
    """A team that trained or distilled with a convention (by content: its fingerprint, whatever zoo file it came
    from or name it had) is never scored beside a stranger that is, or learned from, that convention: a ConfigError
    in one line. Nor is a learned stranger ever a team to evaluate."""
    for team in teams:
        if team.config.learned_stranger:
            raise ConfigError(f"{team.name} is a learned stranger (learned_stranger=true), an evaluation partner "
                              "rather than a team: give it under learned_strangers")
        for stranger in strangers:
            shared = sorted(stranger.met.keys() & team.met.keys())
            if shared:
                raise ConfigError(f"{team.name} trained with the convention {team.met[shared[0]]!r}, which the "
                                  f"stranger {stranger.name!r} of {where} is or learned from (fingerprint "
                                  f"{shared[0]}): a stranger is a partner no evaluated team met")


def evaluate(config: EvalConfig) -> Path:
    """Loads the population, plays every matchup, writes tables, figures and GIFs to `config.out_dir`."""
    device = config.runtime.device
    torch.set_num_threads(config.runtime.threads)
    if not config.conditions:
        raise ConfigError("no conditions to evaluate: give conditions: {name: run_dir_or_glob, ...}")
    population = load_population(config.conditions, device)
    evaluated = [team for members in population.values() for team in members]
    grids = evaluation_grids(config.layouts, config.heldout, config.kitchen_size)
    partner = scripted_cook_team((*grids[0].shape, 26), device) if config.partner else None
    teams, matchups = make_matchups(population, config.cross, partner)
    proxies = load_human_proxies(config.human_proxies, grids, device) if config.human_proxies else {}
    zoo = load_zoo(config.strangers, config.kitchen_size) if config.strangers else None
    strangers = [convention_team(convention, (*grids[0].shape, 26), device, condition=STRANGERS_CONDITION)
                 for convention in (zoo.strangers if zoo else [])]
    refuse_met_strangers(evaluated, strangers, config.strangers)
    learned = load_learned_strangers(config.learned_strangers, device)
    refuse_met_strangers(evaluated, learned, "learned_strangers")
    best_responses = load_best_responses(config.best_responses, [s.name for s in strangers], evaluated, device)
    by_name = {grid.name: grid for grid in grids}
    for heatmap in config.heatmaps:
        if heatmap not in by_name:
            raise ConfigError(f"heatmaps names {heatmap!r}, which is not a test grid: {', '.join(by_name)}")
    gifs = [parse_gif_request(request, teams, by_name) for request in config.gifs]
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_config(config, out / "eval_config.yaml")
    print(f"{len(teams)} teams, {len(matchups)} pairs, {len(grids)} grids, {config.rollouts} rollouts: "
          f"{len(matchups) * len(grids) * config.rollouts:,} episodes"
          + (f"; {(2 * len(evaluated) + 1) * len(strangers)} pairs with {len(strangers)} strangers" if zoo else ""))

    outcomes = play(teams, matchups, grids, config.rollouts, config.max_steps, config.max_envs, config.seed,
                    device, config.progress, config.workers, config.collector)
    if proxies:
        outcomes = with_human_proxies(outcomes, proxies, config.rollouts, config.max_steps, config.max_envs,
                                      config.seed, device, config.collector)
    write_csv(pair_rows(outcomes), out / "pairs.csv")
    summary = summary_rows(outcomes)
    write_csv(summary, out / "summary.csv")
    write_csv(seed_rows(outcomes), out / "seeds.csv")
    table = markdown_summary(summary, config.rollouts)
    written = draw_figures(outcomes, summary, out)
    if strangers:
        text, met = report_strangers(evaluated, strangers, grids, config, out, "strangers", best_responses)
        table += "\n" + text
        group, _ = met.groups[-1]  # the held-out levels, where there are any
        written.append(draw_stranger_heatmap([team.name for team in met.teams], [s.name for s in met.strangers],
                                             np.nanmean(met.normalised[..., -1], axis=2), group,
                                             out / "heatmap_strangers.png"))
    if learned:
        table += "\n" + report_strangers(evaluated, learned, grids, config, out, "learned_strangers")[0]
    (out / "eval.md").write_text(table)
    print(table)
    written += draw_heatmaps_and_gifs(outcomes, config, by_name, gifs, out)
    for path in written:
        print(f"wrote {path}")
    return out


def report_strangers(evaluated: list[Team], strangers: list[Team], grids: list, config: EvalConfig, out: Path,
                     name: str, best_responses: dict | None = None) -> tuple[str, StrangerOutcomes]:
    """Every evaluated team beside each stranger, both seats (scored over its best response where it has one):
    `name`_pairs.csv and `name`.csv written; returns the table and the outcomes."""
    met = play_with_strangers(evaluated, strangers, grids, config.rollouts, config.max_steps, config.max_envs,
                              config.seed, config.runtime.device, config.progress, config.workers, best_responses,
                              config.collector)
    write_csv(stranger_pair_rows(met), out / f"{name}_pairs.csv")
    rows = stranger_rows(met, config.seed)
    write_csv(rows, out / f"{name}.csv")
    kind = "held-out strangers" if name == "strangers" else "learned strangers"
    return markdown_strangers(rows, [stranger.name for stranger in strangers], config.rollouts, kind=kind), met


def draw_heatmaps_and_gifs(outcomes: Outcomes, config: EvalConfig, by_name: dict, gifs: list, out: Path
                           ) -> list[Path]:
    """The visit heat maps of `config.heatmaps` and the GIFs asked for; returns the files written."""
    written = []
    for grid_name in config.heatmaps:
        panels = visit_shares(outcomes, grid_name)
        if panels:
            written.append(draw_heatmap(by_name[grid_name], panels, out / f"heatmap_{grid_name}.png"))
    for first, second, grid in gifs:
        name = f"{first.name}+{second.name}@{grid.name}".replace("/", "-")
        written.append(record_gif(first, second, grid, out / f"{name}.gif", config.max_steps, config.seed))
    return written


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
    args = parser.parse_intermixed_args(argv)  # overrides may follow --import MODULE
    try:
        import_plugins(args.plugins)
        evaluate(load_config(args.config, args.overrides, schema=EvalConfig))
    except (ConfigError, CheckpointError, ConventionError, ValueError, PluginError) as error:
        print(f"kitchen-eval: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
