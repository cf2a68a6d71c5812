"""`kitchen-humans`: the 2019 human-human games as a dataset of this project's states and actions.

    kitchen-humans fetch                      # -> data/humans/{train,test}_<layout>.npz, every step checked

`fetch` downloads the `overcooked-ai` 1.1.0 source distribution through pip into a cache folder (once), reads the
two trials pickles from it (pandas: `pip install .[humans]`), converts every game (`jax_env.human_games`), checks
that each recorded step replays exactly through the JAX env (a mismatch stops with the game and step named), and
writes one compact file per split and layout: the states before each step and both players' actions. The games of
the layouts that fit a 7x7 kitchen are also written drawn inside one (`<layout>_in_7x7`), checked the same way.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tarfile
from pathlib import Path
from typing import Sequence

from jax_env.human_games import SOURCE, TRIALS, HumanGame, human_games, padded_game, read_trials, write_dataset
from jax_env.layouts import PADDED_LAYOUTS, PADDED_SIZE

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
    """Every game of every split, checked step by step, and again drawn inside a 7x7 kitchen where it fits."""
    from tqdm import tqdm

    games = []
    for split, frame in frames.items():
        for game in tqdm(human_games(frame, split), desc=f"{split} games", disable=not progress, leave=False):
            games.append(game)
            if f"{game.layout}_in_{PADDED_SIZE}x{PADDED_SIZE}" in PADDED_LAYOUTS:
                games.append(padded_game(game))
    return games


def fetch(out: Path, cache: Path, progress: bool = True) -> list[HumanGame]:
    games = convert(trials_in(download_source(cache)), progress)
    written = write_dataset(games, out)
    recorded = [g for g in games if g.layout not in PADDED_LAYOUTS]
    steps = sum(len(g) for g in recorded)
    padded = sum(len(g) for g in games) - steps
    print(f"{len(recorded)} games, {steps:,} of {steps:,} recorded steps replayed exactly (and {padded:,} steps of "
          f"their games drawn inside a {PADDED_SIZE}x{PADDED_SIZE} kitchen); written to {out}/:")
    for (split, layout), count in sorted(written.items()):
        file = f"{split}_{layout}.npz"
        print(f"  {file:<34} {count:>6,} steps, "
              f"{sum(1 for g in games if (g.split, g.layout) == (split, layout))} games")
    return games


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="kitchen-humans", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    fetching = commands.add_parser("fetch", help="download, convert and check the games; write the dataset")
    fetching.add_argument("--out", type=Path, default=DATA, help=f"dataset folder (default {DATA})")
    fetching.add_argument("--cache", type=Path, default=CACHE, help=f"download folder (default {CACHE})")
    args = parser.parse_args(argv)
    try:
        fetch(args.out, args.cache)
    except (RuntimeError, ValueError, ImportError) as error:
        print(f"kitchen-humans: error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
