"""`kitchen-zoo`: scripted cooks with conventions of their own, and the held-out strangers among them.

    kitchen-zoo draw --seed 0 --out configs/zoo          # draw, play, keep a diverse set, split, write
    kitchen-zoo draw --candidates 8 --keep 4 --strangers 2 --levels 8 --table-heldout 4 --out /tmp/zoo   # tiny
    kitchen-zoo show configs/zoo/zoo.yaml                # its conventions, one a line
    kitchen-zoo save cook_0_210 --run-dir runs/zoo       # a cook as a run kitchen-eval and kitchen-play read
    kitchen-zoo clash configs/zoo/zoo.yaml --heldout 20  # convention x convention cross-play: do they clash?

`draw` draws `candidates` conventions from `seed` (`torch_kitchen.partners.conventions.draw_convention`), plays each
with itself on `levels` generated *training* levels of the zoo's seed (never a held-out one), and drops those that do
not cook: two of a convention must deliver in at least `min_cooked` of the levels (ZSC-Eval drops its partners of low
return). Each cook's event counts per episode (`torch_kitchen.events`) make its profile; of the cooks, `keep` are chosen
whose profiles lie apart, greedily by the determinant of their similarity (an RBF kernel over the profiles standardised
per event, as ZSC-Eval keeps its partners by the determinant of their event-count similarity), `strangers` of them
held-out *strangers* and the rest conventions to train with. Which conventions may be strangers is decided by content:
one in four of all conventions, by their fingerprint (`stranger_by_content`), can only ever be a stranger, so a second
draw, with any seed or `--strangers`, never trains with a stranger of the first. No shipped config trains with a
stranger (`tests/trainers/test_zoo.py`), a training config that names one is refused, and `kitchen-eval` refuses to seat
a team beside a convention it met. `clash` (and `draw`, on `--clash-heldout` levels) plays every convention beside every
other, both seats, and says whether they clash: whether a convention delivers less beside the others than beside itself,
with an interval over the conventions. The zoo file (`zoo.yaml`) holds the conventions, their split and their
measurements, and the generator and kitchen size the levels came from; its table (`zoo.md`) shows each convention's
self-play on the 5 expanded layouts and the held-out levels, its events and its role, and the clash table, written by
the same command.
"""

from __future__ import annotations

import argparse
import dataclasses
import random
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np

from jax_env import EXPANDED_LAYOUTS, GeneratorConfig, layout_from_state
from jax_env.generator import SIZES as GENERATOR_SIZES
from jax_env.layouts import padded_layouts
from torch_kitchen.events import EVENTS
from torch_kitchen.models import model_identity
from torch_kitchen.partners.conventions import (
    ROLES,
    STRANGER,
    TRAIN,
    ZOO_FILE,
    Convention,
    ConventionError,
    Zoo,
    ZooMember,
    draw_convention,
    fingerprints,
    generator_settings,
    load_zoo,
    save_zoo,
)
from torch_kitchen.partners.scripted_cook import SCRIPTED_COOK
from trainers.checkpoint import LATEST, save_checkpoint
from trainers.config import ConfigError, TrainConfig
from trainers.config.compose import save_config
from trainers.evaluation.figures import draw_clash_heatmap
from trainers.evaluation.intervals import interval, mean, verdict
from trainers.evaluation.pairs import SP, XP, Matchup, evaluation_grids, is_heldout, play
from trainers.evaluation.tables import grid_groups, write_csv
from trainers.evaluation.teams import convention_team
from trainers.levels import sample_batch


# ---------------------------------------------------------------------------------------------- diversity
def event_profiles(events: np.ndarray) -> np.ndarray:
    """[n, E] mean events per episode -> the same standardised per event over the n (an event none differ in
    counts for nothing)."""
    spread = events.std(0)
    return (events - events.mean(0)) / np.where(spread > 0, spread, 1.0)


def similarity(profiles: np.ndarray) -> np.ndarray:
    """[n, n]: exp(-|a - b|^2 / 2E), 1 for equal profiles and smaller the further apart they lie."""
    distances = ((profiles[:, None] - profiles[None]) ** 2).sum(-1)
    return np.exp(-distances / (2 * profiles.shape[1]))


def select_diverse(profiles: np.ndarray, keep: int, pools: np.ndarray | None = None,
                   quotas: dict[int, int] | None = None) -> list[int]:
    """Indices of `keep` profiles in the order chosen: first the one furthest from the mean, then each time the one
    that makes the determinant of the chosen ones' similarity largest (a greedy volume of their spread). With
    `pools` (an int per profile) and `quotas` (pool -> how many), at most that many of each pool."""
    pools = np.zeros(len(profiles), dtype=int) if pools is None else np.asarray(pools)
    quotas = quotas or {0: keep}
    open_ = [i for i in range(len(profiles)) if quotas.get(int(pools[i]), 0) > 0]
    if not open_:
        return []
    kernel = similarity(profiles)
    spread = ((profiles - profiles.mean(0)) ** 2).sum(1)
    chosen = [max(open_, key=lambda i: spread[i])]
    while len(chosen) < min(keep, len(profiles)):
        taken = Counter(int(pools[i]) for i in chosen)
        best, best_logdet = None, -np.inf
        for candidate in range(len(profiles)):
            if candidate in chosen or taken[int(pools[candidate])] >= quotas.get(int(pools[candidate]), 0):
                continue
            rows = [*chosen, candidate]
            sign, logdet = np.linalg.slogdet(kernel[np.ix_(rows, rows)])
            logdet = logdet if sign > 0 else -np.inf
            if best is None or logdet > best_logdet:
                best, best_logdet = candidate, logdet
        if best is None:
            break  # every pool's quota met, or no candidate left in an open one
        chosen.append(best)
    return chosen


def stranger_by_content(convention: Convention) -> bool:
    """Whether a convention can only ever be a held-out stranger: a quarter of all conventions, by their fingerprint
    (how they play, not their name or the draw that found them), so that no zoo file, however drawn, trains with a
    convention another one holds out."""
    return int(convention.fingerprint, 16) % STRANGER_SHARE == 0


def mean_similarity(profiles: np.ndarray) -> float:
    """The mean similarity of distinct pairs of profiles (lower: further apart)."""
    kernel = similarity(profiles)
    n = len(profiles)
    return float((kernel.sum() - n) / max(n * (n - 1), 1))


STRANGER_SHARE = 4  # one convention in four, by content, is a stranger (`stranger_by_content`)


# ------------------------------------------------------------------------------------------------- drawing
def zoo_levels(seed: int, count: int, kitchen_size: int) -> list:
    """`count` generated training levels of the zoo's seed (the generator rejects every held-out grid)."""
    levels = sample_batch(seed, count, training=True, config=GeneratorConfig(size=kitchen_size))
    return [layout_from_state(jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], levels), name=f"zoo_{i:03d}")
            for i in range(count)]


def self_play(conventions: Sequence[Convention], grids: list, rollouts: int, seed: int, max_envs: int,
              workers: int, progress: bool, max_steps: int = 256):
    """Each convention with itself on every grid: (deliveries [n, G, R], events per episode and seat [n, G, E])."""
    obs_shape = (*grids[0].shape, 26)
    teams = [convention_team(convention, obs_shape) for convention in conventions]
    matchups = [Matchup(i, i, SP) for i in range(len(teams))]
    outcomes = play(teams, matchups, grids, rollouts, max_steps, max_envs, seed, progress=progress, workers=workers)
    return outcomes.deliveries, outcomes.events.sum(2) / (2 * rollouts)


# The roles the shipped zoo's conventions draw: a split of the work by seat, strict or not. Conventions that split it so
# clash (a cook delivers less beside another convention than beside its own kind); drawn from every role, or with no
# split, they do not (docs/evaluation.md).
ZOO_ROLES = ("seat0_loads", "seat0_serves")


def draw_zoo(seed: int = 0, candidates: int = 96, keep: int = 32, strangers: int = 8, levels: int = 64,
             kitchen_size: int = 7, min_cooked: float = 0.6, max_envs: int = 4096, workers: int = 1,
             progress: bool = True, max_steps: int = 256, roles: Sequence[str] = ZOO_ROLES) -> Zoo:
    """Draws (each convention's role among `roles`), plays (`max_steps`-step episodes), filters and selects a zoo
    (see the module docstring). Deterministic for its arguments."""
    rng = random.Random(seed)
    drawn = [draw_convention(rng, f"cook_{seed}_{i:03d}", roles) for i in range(candidates)]
    deliveries, events = self_play(drawn, zoo_levels(seed, levels, kitchen_size), 1, seed, max_envs, workers,
                                   progress, max_steps)
    cooked = (deliveries > 0).mean((1, 2))
    cooks = [i for i in range(candidates) if cooked[i] >= min_cooked]
    if len(cooks) < keep:
        raise ConfigError(f"{len(cooks)} of {candidates} conventions drawn cook (two of them deliver on at least "
                          f"{min_cooked:.0%} of {levels} levels), fewer than keep={keep}: draw more candidates")
    mean_events = events.mean(1)  # [n, E]
    profiles = event_profiles(mean_events[cooks])
    pools = np.array([stranger_by_content(drawn[i]) for i in cooks], dtype=int)  # 1: a stranger's pool
    if (pools == 0).sum() < keep - strangers or (pools == 1).sum() < strangers:
        raise ConfigError(f"of the {len(cooks)} conventions that cook, {(pools == 0).sum()} may train and "
                          f"{(pools == 1).sum()} are strangers by content, for keep={keep} with strangers={strangers}: "
                          "draw more candidates")
    order = select_diverse(profiles, keep, pools, {0: keep - strangers, 1: strangers})
    random_pick = np.random.default_rng(seed)
    random_similarity = np.mean([mean_similarity(profiles[random_pick.choice(len(cooks), keep, replace=False)])
                                 for _ in range(100)])
    members = []
    for chosen in order:
        i = cooks[chosen]
        split = STRANGER if pools[chosen] else TRAIN
        members.append(ZooMember(drawn[i], split, float(deliveries[i].mean()), float(cooked[i]),
                                 dict(zip(EVENTS, map(float, mean_events[i])))))
    return Zoo(seed, kitchen_size, generator_settings(kitchen_size), members, drawn=candidates, levels=levels,
               similarity={"kept": round(mean_similarity(profiles[order]), 4),
                           "random": round(float(random_similarity), 4), "cooks": len(cooks)})


# ------------------------------------------------------------------------------------------------- clashes
def cross_play(conventions: Sequence[Convention], grids: list, rollouts: int, seed: int, max_envs: int,
               workers: int, progress: bool, max_steps: int = 256) -> tuple[np.ndarray, list[str]]:
    """(deliveries [n, n, groups], the groups' names): convention i in seat 0 beside convention j in seat 1, mean
    deliveries per episode on each grid group (each classic layout, then the held-out levels together)."""
    obs_shape = (*grids[0].shape, 26)
    teams = [convention_team(convention, obs_shape) for convention in conventions]
    n = len(teams)
    matchups = [Matchup(i, j, SP if i == j else XP) for i in range(n) for j in range(n)]
    outcomes = play(teams, matchups, grids, rollouts, max_steps, max_envs, seed, progress=progress, workers=workers)
    groups = grid_groups(outcomes)
    per_grid = outcomes.deliveries.mean(-1)  # [n * n, G]
    by_group = [per_grid[:, [g for g, grid in enumerate(grids) if grid.name in names]].mean(1) for _, names in groups]
    return np.stack(by_group, axis=1).reshape(n, n, len(groups)), [name for name, _ in groups]


def same_minus_cross(deliveries: np.ndarray) -> np.ndarray:
    """float [n]: each convention with itself minus its mean with the others (either seat), from deliveries [n, n]."""
    n = len(deliveries)
    off = ~np.eye(n, dtype=bool)
    cross = ((deliveries * off).sum(1) + (deliveries * off).sum(0)) / (2 * (n - 1))
    return np.diag(deliveries) - cross


def clash_rows(deliveries: np.ndarray, groups: list[str]) -> list[dict]:
    """Per grid group: same-convention and cross-convention mean deliveries and the difference over conventions
    (each convention's own, `same_minus_cross`), with its 95% bootstrap interval over the conventions, and whether
    the conventions clash there (cross below same: the interval above 0)."""
    rows = []
    for g, group in enumerate(groups):
        matrix = deliveries[..., g]
        gap = interval(same_minus_cross(matrix)[:, None], mean)
        off = ~np.eye(len(matrix), dtype=bool)
        rows.append({"grids": group, "same": float(np.diag(matrix).mean()), "cross": float(matrix[off].mean()),
                     "difference": gap.value, "low": gap.low, "high": gap.high, "clash": verdict(gap)})
    return rows


def clash_table(rows: list[dict], conventions: int) -> str:
    lines = [
        f"Cross-play between the {conventions} conventions (each in seat 0 beside each in seat 1): with itself "
        "(same) against with the others (cross), mean deliveries per episode; the difference is each convention's "
        "own (with itself minus with the others), averaged, [95% bootstrap interval over the conventions]. The "
        "conventions clash where cross lies below same: the interval above 0.",
        "",
        "| grids | same convention | cross convention | same - cross | cross below same |",
        "|---|---:|---:|---:|---|",
    ]
    lines += [f"| {row['grids']} | {row['same']:.2f} | {row['cross']:.2f} | {row['difference']:+.2f} "
              f"[{row['low']:+.2f}, {row['high']:+.2f}] | {row['clash']} |" for row in rows]
    return "\n".join(lines) + "\n"


def clash(zoo: Zoo, out: Path, heldout: int, rollouts: int, seed: int, workers: int, progress: bool,
          max_steps: int = 256) -> str:
    """The zoo's convention x convention cross-play on the classic layouts and `heldout` held-out levels: writes
    clash.csv (every pair and grid group) and heatmap_clash.png (the held-out levels, or the last group), returns
    the table."""
    size = zoo.kitchen_size
    layouts = list(EXPANDED_LAYOUTS) if size == 7 else list(padded_layouts(size))
    conventions = [member.convention for member in zoo.members]
    deliveries, groups = cross_play(conventions, evaluation_grids(layouts, heldout, size), rollouts, seed, 4096,
                                    workers, progress, max_steps)
    names = [f"{m.name}*" if m.split == STRANGER else m.name for m in zoo.members]
    out.mkdir(parents=True, exist_ok=True)
    write_csv([{"seat0": zoo.members[i].name, "seat1": zoo.members[j].name, "grids": group,
                "deliveries": round(float(deliveries[i, j, g]), 4)}
               for i in range(len(names)) for j in range(len(names)) for g, group in enumerate(groups)],
              out / "clash.csv")
    draw_clash_heatmap(names, deliveries[..., -1], groups[-1], out / "heatmap_clash.png")
    return clash_table(clash_rows(deliveries, groups), len(names))


# -------------------------------------------------------------------------------------------------- table
def zoo_table(zoo: Zoo, heldout: int, rollouts: int, seed: int, max_envs: int, workers: int,
              progress: bool, max_steps: int = 256) -> str:
    """Markdown: each convention's split, role and description, its self-play (`max_steps`-step episodes) on each
    classic layout and on the held-out levels, and its events per episode and seat on the zoo's levels."""
    size = zoo.kitchen_size
    layouts = list(EXPANDED_LAYOUTS) if size == 7 else list(padded_layouts(size))
    grids = evaluation_grids(layouts, heldout, size)
    conventions = [member.convention for member in zoo.members]
    deliveries, _ = self_play(conventions, grids, rollouts, seed, max_envs, workers, progress, max_steps)
    classic = [g for g, grid in enumerate(grids) if not is_heldout(grid.name)]
    held = [g for g, grid in enumerate(grids) if is_heldout(grid.name)]
    short = [name.removesuffix("_7x7") for name in layouts]
    lines = [
        f"Self-play of each convention (two of it; mean deliveries per episode, {rollouts} rollouts per grid) on the "
        f"expanded classic layouts and {len(held)} held-out levels, and its events per episode and seat on the zoo's "
        f"{zoo.levels} training levels. Drawn {zoo.drawn} from seed {zoo.seed}, {zoo.similarity.get('cooks', '?')} "
        f"cooked, {len(zoo.members)} kept; mean similarity of the kept profiles "
        f"{zoo.similarity.get('kept', float('nan')):.3f} against {zoo.similarity.get('random', float('nan')):.3f} "
        "for as many cooks drawn at random (lower: further apart).",
        "",
        f"| convention | split | role | {' | '.join(short)} | held-out | {' | '.join(EVENTS)} | convention |",
        "|---|---|---|" + "---:|" * (len(short) + 1 + len(EVENTS)) + "---|",
    ]
    for m, member in enumerate(zoo.members):
        per_layout = " | ".join(f"{deliveries[m, g].mean():.2f}" for g in classic)
        events = " | ".join(f"{member.events[event]:.1f}" for event in EVENTS)
        heldout_mean = f"{deliveries[m, held].mean():.2f}" if held else ""
        lines.append(f"| {member.name} | {member.split} | {member.convention.role} | {per_layout} | {heldout_mean} | "
                     f"{events} | {member.convention.describe()} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------- saving
def save_cook(convention: Convention, run_dir: str | Path, kitchen_size: int = 7) -> Path:
    """The scripted cook of `convention` as a run of its own, RUN_DIR/<name>/seed0, with a checkpoint that
    `kitchen-eval`, `kitchen-play` and `load_team` read as any trained team's (no weights: its model header holds
    the convention)."""
    config = TrainConfig(name=convention.name, run_dir=str(run_dir), architecture=SCRIPTED_COOK,
                         kitchen_size=kitchen_size, eval_episodes=0)
    run = config.run_path
    identity = model_identity(SCRIPTED_COOK, (kitchen_size, kitchen_size, 26), config.hidden, config.share_params)
    save_checkpoint(run / "checkpoints" / LATEST, {
        "config": config.to_dict(), "model": {**identity, "options": {"convention": convention.as_dict()}},
        "actor": {}, "critic": {}, "update": 0, "env_steps": config.planned_steps,
        "met": fingerprints([convention]),
    })  # fmt: skip
    save_config(config, run / "config.yaml")
    return run


# ------------------------------------------------------------------------------------------- command line
def zoo_parser() -> argparse.ArgumentParser:
    """kitchen-zoo's command line: draw, clash, show, save."""
    parser = argparse.ArgumentParser(prog="kitchen-zoo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    verbs = parser.add_subparsers(dest="verb", required=True)
    drawing = verbs.add_parser("draw", help="draw conventions, keep a diverse set that cooks, split off strangers")
    drawing.add_argument("--seed", type=int, default=0)
    drawing.add_argument("--candidates", type=int, default=96, help="conventions drawn")
    drawing.add_argument("--keep", type=int, default=32, help="conventions kept, the strangers among them")
    drawing.add_argument("--strangers", type=int, default=8, help="held-out strangers among the kept")
    drawing.add_argument("--levels", type=int, default=64, help="generated training levels each plays on")
    drawing.add_argument("--min-cooked", type=float, default=0.6, help="share of levels two of it must deliver on")
    drawing.add_argument("--kitchen-size", type=int, default=7, choices=GENERATOR_SIZES)
    drawing.add_argument("--table-heldout", type=int, default=100, help="held-out levels in the table")
    drawing.add_argument("--table-rollouts", type=int, default=2, help="episodes per grid in the table")
    drawing.add_argument("--clash-heldout", type=int, default=20,
                      help="held-out levels of the convention x convention cross-play (0: the classic layouts only)")
    drawing.add_argument("--workers", type=int, default=1, help="processes that play at once")
    drawing.add_argument("--max-steps", type=int, default=256,
                      help="steps of an episode, in the draw, the table and the clash alike")
    drawing.add_argument("--roles", nargs="+", choices=ROLES, default=list(ZOO_ROLES),
                         help="the roles a convention may draw (default: the split by seat, the shipped zoo's; both "
                              "loader server: no split)")
    drawing.add_argument("--out", default=str(Path(ZOO_FILE).parent), help="folder of zoo.yaml and zoo.md")
    clashes = verbs.add_parser("clash", help="convention x convention cross-play of a zoo: clash.md, .csv and heat map")
    clashes.add_argument("zoo", nargs="?", default=ZOO_FILE)
    clashes.add_argument("--heldout", type=int, default=20, help="held-out levels beside the classic layouts")
    clashes.add_argument("--rollouts", type=int, default=1, help="episodes per pair and grid")
    clashes.add_argument("--max-steps", type=int, default=256, help="steps of an episode")
    clashes.add_argument("--seed", type=int, default=0)
    clashes.add_argument("--workers", type=int, default=1, help="processes that play at once")
    clashes.add_argument("--out", default="results/clash", help="folder of clash.md, clash.csv, heatmap_clash.png")
    clashes.add_argument("--conventions", nargs="+", metavar="NAME",
                         help="these conventions of the zoo only, in this order (default: every one)")
    showing = verbs.add_parser("show", help="print a zoo file's conventions")
    showing.add_argument("zoo", nargs="?", default=ZOO_FILE)
    saving = verbs.add_parser("save", help="save cooks of a zoo as runs that kitchen-eval and kitchen-play read")
    saving.add_argument("names", nargs="+", help="conventions of the zoo")
    saving.add_argument("--zoo", default=ZOO_FILE)
    saving.add_argument("--run-dir", default="runs/zoo", help="the runs go to RUN_DIR/<name>/seed0")
    return parser


def show(args: argparse.Namespace) -> None:
    zoo = load_zoo(args.zoo)
    for member in zoo.members:
        print(f"{member.name:14s} {member.split:8s} self-play {member.self_play:5.2f}  {member.convention.describe()}")


def save(args: argparse.Namespace) -> None:
    zoo = load_zoo(args.zoo)
    for name in args.names:
        print(f"wrote {save_cook(zoo.convention(name), args.run_dir, zoo.kitchen_size)}")


def clash_command(args: argparse.Namespace) -> None:
    out, zoo = Path(args.out), load_zoo(args.zoo)
    if args.conventions:
        members = {member.name: member for member in zoo.members}
        unknown = [name for name in args.conventions if name not in members]
        if unknown or len(set(args.conventions)) < 2:
            wanted = f"no {', '.join(unknown)} in" if unknown else "two or more of"
            raise ConventionError(f"--conventions: {wanted} {args.zoo}; its conventions: {', '.join(members)}")
        zoo = dataclasses.replace(zoo, members=[members[name] for name in dict.fromkeys(args.conventions)])
    table = clash(zoo, out, args.heldout, args.rollouts, args.seed, args.workers, True, args.max_steps)
    (out / "clash.md").write_text(f"# Convention x convention: {args.zoo}\n\n" + table
                                  + "\n![convention x convention](heatmap_clash.png)\n")
    print(table)
    print(f"wrote {out / 'clash.md'}, {out / 'clash.csv'}, {out / 'heatmap_clash.png'}")


def draw(args: argparse.Namespace) -> None:
    """Draws the zoo, writes zoo.yaml and its table with the clash (zoo.md, headed by the command that made it)."""
    if not 0 <= args.strangers <= args.keep <= args.candidates:
        raise ConfigError(f"need 0 <= strangers <= keep <= candidates, got {args.strangers}, {args.keep}, "
                          f"{args.candidates}")
    zoo = draw_zoo(args.seed, args.candidates, args.keep, args.strangers, args.levels, args.kitchen_size,
                   args.min_cooked, workers=args.workers, max_steps=args.max_steps, roles=args.roles)
    table = zoo_table(zoo, args.table_heldout, args.table_rollouts, args.seed, 4096, args.workers, True,
                      args.max_steps)
    out = Path(args.out)
    table += ("\n## Do the conventions clash?\n\n"
              + clash(zoo, out, args.clash_heldout, 1, args.seed, args.workers, True, args.max_steps)
              + "\n![convention x convention](heatmap_clash.png)\n")
    print(f"wrote {save_zoo(zoo, out / 'zoo.yaml')}")
    (out / "zoo.md").write_text(f"# The zoo\n\n`kitchen-zoo draw --seed {args.seed} --candidates "
                                f"{args.candidates} --keep {args.keep} --strangers {args.strangers} --levels "
                                f"{args.levels} --clash-heldout {args.clash_heldout}"
                                + (f" --max-steps {args.max_steps}" if args.max_steps != 256 else "")
                                + f" --roles {' '.join(args.roles)}"
                                + "`\n\n" + table)
    print(table)
    print(f"wrote {out / 'zoo.md'}")


VERBS = {"draw": draw, "clash": clash_command, "show": show, "save": save}


def main(argv: Sequence[str] | None = None) -> int:
    args = zoo_parser().parse_args(argv)
    try:
        VERBS[args.verb](args)
    except (ConfigError, ConventionError) as error:
        print(f"kitchen-zoo: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
