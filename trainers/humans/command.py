"""`kitchen-humans`: the 2019 human-human games as a dataset of this project's states and actions.

    kitchen-humans fetch                      # -> data/humans/{train,test}_<layout>.npz, every step checked
    kitchen-humans train                      # -> runs/bc_<layout>/seed0 (train split) and a table of how they play
    kitchen-humans train --fit-on test        # -> runs/human_proxy_<layout>/seed0: the evaluations' human proxies
    kitchen-humans import games/*.jsonl --out data/study --split train   # a study's own kitchen-play games

`fetch` downloads the `overcooked-ai` 1.1.0 source distribution through pip into a cache folder (once), reads the
two trials pickles from it (pandas: `pip install .[humans]`), converts every game (`jax_env.human_games`), checks
that each recorded step replays exactly through the JAX env (a mismatch stops with the game and step named), and
writes one compact file per split and layout: the states before each step and both players' actions. The games of
the layouts that fit a 7x7 kitchen are also written drawn inside one (`<layout>_in_7x7`), checked the same way.

`import` turns `kitchen-play` records into the same dataset (each replayed and checked; only the person's seat
is a human label), so that `train --data` fits proxies of a study's own participants.

`train` fits a proxy per layout on one split (`trainers.humans.behaviour_cloning`; `--candidates` fits, the one kept
whose two copies deliver closest to that split's humans; where they deliver under half the humans' soups, it is
fine-tuned by anchored IPPO into `<team>/anchored/`, and the closest kept), saves it as a trained team that
`kitchen-eval` and `kitchen-play` seat, and writes a table of the proxies measured on the other split: accuracy
against always-STAY, accuracy on the humans' moves and interactions against their most frequent one, and the soups
two proxies deliver together in games of the humans' length against the humans' own. As in Carroll et al. (2019),
the proxies fitted on the train split (`bc_<layout>`) are partners a method may train with, and those fitted on the
test split (`human_proxy_<layout>`) are the human proxies of evaluations (`kitchen-eval human_proxies=runs`), so
that no team is tuned to the partner it is measured with.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tarfile
from pathlib import Path
from typing import Sequence

from jax_env.human_games import (
    LAYOUTS,
    SOURCE,
    TRIALS,
    HumanGame,
    human_games,
    load_dataset,
    padded_game,
    read_trials,
    write_dataset,
)
from jax_env.layouts import CLASSIC_LAYOUTS, PADDED_LAYOUTS, PADDED_SIZES, padded_layouts, padded_name
from trainers.humans.behaviour_cloning import (
    ProxySettings,
    accuracy,
    choose_proxy,
    deliveries_together,
    fine_tuned,
    human_batch,
    save_proxy,
)

DATA = Path("data/humans")
CACHE = Path.home() / ".cache" / "infinite-kitchen"


def download_source(cache: Path) -> Path:
    """The source distribution of `SOURCE` in `cache` (downloaded by pip the first time)."""
    name, version = SOURCE.split("==")
    found = sorted(cache.glob(f"{name.replace('-', '_')}-{version}.tar.gz"))
    if found:
        return found[0]
    cache.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:", SOURCE, "-d", str(cache)]
    result = subprocess.run(command, capture_output=True, text=True)
    found = sorted(cache.glob(f"{name.replace('-', '_')}-{version}.tar.gz"))
    if result.returncode or not found:
        last = (result.stderr.strip().splitlines() or ["no archive"])[-1]
        raise RuntimeError(f"pip could not download {SOURCE}'s source distribution: {last}")
    return found[0]


def trials_in(archive: Path) -> dict[str, object]:
    """{split: its DataFrame} read from the source distribution without unpacking it."""
    frames = {}
    with tarfile.open(archive) as tar:
        for split, member in TRIALS.items():
            path = next((m for m in tar.getnames() if m.endswith(member)), None)
            if path is None:
                raise RuntimeError(f"{archive.name} holds no {member}")
            frames[split] = read_trials(tar.extractfile(path))
    return frames


def convert(frames: dict[str, object], progress: bool = True) -> list[HumanGame]:
    """Every game of every split, checked step by step, and again drawn inside each generated kitchen size (7x7,
    9x9) where it fits, checked again."""
    from tqdm import tqdm

    games = []
    for split, frame in frames.items():
        for game in tqdm(human_games(frame, split), desc=f"{split} games", disable=not progress, leave=False):
            games.append(game)
            for size in PADDED_SIZES:
                if padded_name(game.layout, size) in padded_layouts(size):
                    games.append(padded_game(game, size))
    return games


def fetch(out: Path, cache: Path, progress: bool = True) -> list[HumanGame]:
    games = convert(trials_in(download_source(cache)), progress)
    written = write_dataset(games, out)
    recorded = [g for g in games if g.layout in CLASSIC_LAYOUTS]
    steps = sum(len(g) for g in recorded)
    padded = {size: sum(len(g) for g in games if g.layout in padded_layouts(size)) for size in PADDED_SIZES}
    inside = " and ".join(f"{count:,} steps inside {size}x{size} kitchens" for size, count in padded.items())
    print(f"{len(recorded)} games, {steps:,} of {steps:,} recorded steps replayed exactly (and, their games drawn "
          f"inside the generated kitchens' sizes, {inside}); written to {out}/:")
    for (split, layout), count in sorted(written.items()):
        file = f"{split}_{layout}.npz"
        print(f"  {file:<34} {count:>6,} steps, "
              f"{sum(1 for g in games if (g.split, g.layout) == (split, layout))} games")
    return games


def games_from_records(paths: Sequence[str | Path], split: str) -> list[HumanGame]:
    """`kitchen-play` records -> `HumanGame`s of `split`: each record replayed once and checked (`replayed_states`),
    the state before every step kept; the person's seat is the human one. Games on unregistered kitchens (held-out
    or generated levels, level files) are refused: a proxy is fitted per layout."""
    import numpy as np

    from jax_env import layout_names
    from torch_kitchen.records import replayed_states

    games = []
    for path in paths:
        header, steps, _, states = replayed_states(path)  # every step as recorded, or a ValueError naming it
        if header["layout_name"] not in layout_names():
            raise ValueError(f"{path} was played on {header['layout_name']!r}, not a registered layout: proxies are "
                             "fitted per layout (the classic, expanded or drawn-inside-7x7 ones)")
        before = states[:-1]
        games.append(HumanGame(
            name=Path(path).stem, split=split, layout=header["layout_name"],
            contents=np.stack([s.contents for s in before]), agent_pos=np.stack([s.agent_pos for s in before]),
            agent_dir=np.stack([s.agent_dir for s in before]), agent_inv=np.stack([s.agent_inv for s in before]),
            actions=np.asarray([line["actions"] for line in steps], np.int64),
            delivered=np.asarray([line["deliveries"] for line in steps], np.int32),
            human_seats=(header["seat"] == 0, header["seat"] == 1),
        ))  # fmt: skip
    return games


RUN_NAMES = {"train": "bc_{layout}", "test": "human_proxy_{layout}"}  # by the split a proxy is fitted on


def what_humans_did(games: Sequence[HumanGame], game_steps: int = 0) -> tuple[float, int]:
    """The soups the humans of `games` delivered on average, and the steps of the games two proxies play to compare
    with them: `game_steps`, or as long as those games on average."""
    import numpy as np

    soups = float(np.mean([game.deliveries for game in games]))
    return soups, game_steps or int(round(np.mean([len(game) for game in games])))


def train(data: Path, runs: Path, layouts: Sequence[str], settings: ProxySettings, episodes: int,
          report: Path | None, game_steps: int = 0, fit_on: str = "train") -> str:
    """A proxy per layout, saved under `runs`; returns (and writes to `report`) the table of how they play. Two
    proxies play `episodes` games of `game_steps` steps together (0: as long as the humans' games of the split it
    is measured on). `fit_on`: the split fitted on ("train" or "test"); it is measured on the other."""
    import numpy as np
    import torch

    torch.set_num_threads(settings.threads)
    rows, ratios = [], []
    for layout in layouts:
        measure_on = "test" if fit_on == "train" else "train"
        train_games, test_games = load_dataset(data, fit_on, layout), load_dataset(data, measure_on, layout)
        train_batch, test_batch = human_batch(train_games), human_batch(test_games)
        fitted_humans, fitted_steps = what_humans_did(train_games, game_steps)
        run = runs / RUN_NAMES[fit_on].format(layout=layout) / f"seed{settings.seed}"
        chosen = choose_proxy(train_batch, layout, settings, fitted_steps, fitted_humans, episodes)
        chosen = fine_tuned(chosen, layout, settings, fitted_steps, fitted_humans, episodes, run)
        proxy = chosen.actor_critic
        save_proxy(proxy, dataclasses.replace(settings, seed=chosen.seed), layout, run)
        scores = accuracy(proxy, test_batch, train_batch)
        humans, steps = what_humans_did(test_games, game_steps)
        together = deliveries_together(proxy, layout, steps, episodes, settings.seed)
        ratios += [together / humans] if humans else []
        candidates = " ".join(f"{chosen.soups[seed]:.1f}" for seed in sorted(chosen.soups))
        candidates += "".join(f"; KL {coef:g}: {soups:.1f}" for coef, soups in chosen.tuned.items())
        kept = "-" if chosen.anchor_coef is None else f"KL {chosen.anchor_coef:g}"
        rows.append(f"| {layout} | {len(train_batch):,} / {len(test_batch):,} | {scores['accuracy']:.3f} | "
                    f"{scores['always_stay']:.3f} | {scores['moving_accuracy']:.3f} | "
                    f"{scores['moving_majority']:.3f} | {steps} | {together:.2f} | {humans:.2f} | "
                    + (f"{together / humans:.2f} |" if humans else "- |")
                    + f" {chosen.seed} | {kept} | {candidates} / {fitted_humans:.2f} |")
        print(rows[-1], flush=True)
    table = "\n".join([
        f"Proxies fitted on the {fit_on} split, measured on the {measure_on} split: {settings.architecture} hidden "
        f"{settings.hidden}, {settings.epochs} epochs, lr {settings.lr:g}, STAY weight {settings.stay_weight:g}; "
        f"per layout {settings.candidates} fits (seeds {settings.seed} to {settings.seed + settings.candidates - 1}), "
        f"the one kept whose two copies deliver closest to the {fit_on} split's humans ({episodes} games of their "
        f"length; \"candidates\": each fit's soups / the humans'); where the kept fit's two copies deliver under "
        f"{settings.fine_tune_below:g} x the humans' soups, it is also fine-tuned by anchored IPPO, "
        f"{settings.fine_tune_steps:,} steps at rate {settings.fine_tune_lr:g}, with KL weight "
        f"{settings.anchor_coef:g} first and then weights searched for, at most {settings.fine_tunes} (\"KL w\": "
        "that fine-tune's soups), and the closest of them and the fit is kept (\"fine-tuned\"); two proxies together: "
        f"{episodes} other games per layout (actions sampled), "
        + (f"{game_steps} steps each." if game_steps else f"as long as the humans' {measure_on} games."),
        "",
        f"| layout | steps {fit_on} / {measure_on} | accuracy | always STAY | accuracy on moves | their majority "
        "| game steps "
        f"| BC+BC soups | humans' soups | ratio | seed kept | fine-tuned | candidates on the {fit_on} split |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
        *rows,
        "",
        f"Two proxies together deliver {np.mean(ratios) if ratios else float('nan'):.2f} of what the humans did, "
        f"on average over the {len(ratios)} layouts.",
    ]) + "\n"  # fmt: skip
    if report is not None:
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(table)
    return table


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="kitchen-humans", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    fetching = commands.add_parser("fetch", help="download, convert and check the games; write the dataset")
    fetching.add_argument("--out", type=Path, default=DATA, help=f"dataset folder (default {DATA})")
    fetching.add_argument("--cache", type=Path, default=CACHE, help=f"download folder (default {CACHE})")
    importing = commands.add_parser("import", help="kitchen-play records into the dataset format")
    importing.add_argument("records", nargs="+", type=Path, help="kitchen-play game records (.jsonl)")
    importing.add_argument("--out", type=Path, required=True, help="dataset folder to write")
    importing.add_argument("--split", default="train", help="the split they form (train or test; default train)")
    training = commands.add_parser("train", help="fit a human proxy per layout; write a table of how they play")
    defaults = ProxySettings()
    training.add_argument("--data", type=Path, default=DATA, help=f"the fetched dataset (default {DATA})")
    training.add_argument("--runs", type=Path, default=Path("runs"), help="where the proxies go (default runs)")
    training.add_argument("--layouts", nargs="+", default=[*LAYOUTS.values(), *PADDED_LAYOUTS],
                          help="layouts to fit (default: the 5 classic ones and those drawn inside a 7x7 kitchen; the "
                               "<layout>_in_9x9 ones by name)")
    training.add_argument("--report", type=Path, help="also write the table here")
    training.add_argument("--fit-on", choices=sorted(RUN_NAMES), default="train",
                          help="the split to fit (train: runs/bc_<layout>, partners to train with; test: "
                               "runs/human_proxy_<layout>, the evaluations' human proxies); measured on the other")
    training.add_argument("--episodes", type=int, default=32, help="games of two proxies per layout")
    training.add_argument("--game-steps", type=int, default=0,
                          help="steps of those games (default: as long as the humans' test games)")
    for field in dataclasses.fields(ProxySettings):
        training.add_argument(f"--{field.name.replace('_', '-')}", type=type(getattr(defaults, field.name)),
                              default=getattr(defaults, field.name), help=f"default {getattr(defaults, field.name)}")
    args = parser.parse_args(argv)
    try:
        if args.command == "fetch":
            fetch(args.out, args.cache)
        elif args.command == "import":
            written = write_dataset(games_from_records(args.records, args.split), args.out)
            for (split, layout), count in sorted(written.items()):
                print(f"{args.out / f'{split}_{layout}.npz'}: {count:,} steps")
        else:
            names = [field.name for field in dataclasses.fields(ProxySettings)]
            settings = ProxySettings(**{name: getattr(args, name) for name in names})
            print(train(args.data, args.runs, args.layouts, settings, args.episodes, args.report, args.game_steps,
                        args.fit_on))
    except (RuntimeError, ValueError, ImportError, FileNotFoundError) as error:
        print(f"kitchen-humans: error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
