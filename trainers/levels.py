"""`kitchen-levels`: look at Infinite Kitchen levels as text, as a contact sheet, or as text files to edit.

    kitchen-levels sample --n 16 --seed 0 --print --sheet outputs/levels.png
    kitchen-levels sample --n 1000 --training --export outputs/levels/
    kitchen-levels sample --n 4000 --training --kitchen-size 9 --smaller-kitchens 0.75 --intact-walls 0.5
    kitchen-levels heldout --sheet outputs/heldout.png
    kitchen-levels show outputs/levels/level_0003.txt cramped_room_7x7 --sheet outputs/show.png
    python -m trainers.levels sample --n 4 --print

`sample` draws level i from key i of `jax.random.split(jax.random.PRNGKey(seed), n)` (see `level_keys`), all
in one jitted, vmapped call; `--training` rejects the held-out grids as training does. `heldout` shows the 105
held-out evaluation levels. `show` checks registered layouts or hand-edited text files: their text, solvability
class and the reason for it. Exported files are named `level_0000.txt`, ... and read back by `load_layout`.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Mapping, Sequence

import jax
import numpy as np
from PIL import Image
from tqdm import tqdm

from jax_env.generator import SIZES as GENERATOR_SIZES
from jax_env.generator import GeneratorConfig, heldout_grids, heldout_set, sample_levels, sample_training_levels
from jax_env.layouts import EXPANDED_LAYOUTS, Layout, load_layout, save_layout
from jax_env.render import MIN_TILE_SIZE, render_contact_sheet
from jax_env.solvability import CLASS_NAMES, analyse_layout, classify_levels
from jax_env.state import State, layout_from_state, make_state

PROG = "kitchen-levels"
# Labels under the pictures must fit a 7-tile cell.
SHORT_CLASS_NAMES = {"unsolvable": "unsolvable", "solo": "solo", "forced_coordination": "forced"}
# Writing more files than this shows a progress bar.
PROGRESS_MIN_FILES = 100

def level_keys(seed: int, n: int) -> jax.Array:
    """The keys of `sample`: uint32 (n, 2), `jax.random.split(jax.random.PRNGKey(seed), n)`; level i uses key i."""
    return jax.random.split(jax.random.PRNGKey(seed), n)


def sample_batch(seed: int, n: int, training: bool = False, config: GeneratorConfig = GeneratorConfig()) -> State:
    """n start states batched (n, ...) in one jitted call: `sample_levels`, or with `training` the vmapped
    `sample_training_levels`, which never return a held-out grid."""
    keys = level_keys(seed, n)
    if training:
        return sample_training_levels(keys, config, heldout_grids(config))
    return sample_levels(keys, config)


def level_classes(levels: State) -> list[str]:
    """The `CLASS_NAMES` entry of each level of a batch (n, ...)."""
    codes = classify_levels(np.asarray(levels.grid), np.asarray(levels.agent_xy()))
    return [CLASS_NAMES[int(code)] for code in codes]


def unbatch(levels: State) -> list[State]:
    """The levels of a batch (n, ...) as a list of unbatched numpy states."""
    levels = jax.tree_util.tree_map(np.asarray, jax.device_get(levels))
    return [jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], levels) for i in range(levels.step.shape[0])]


def class_summary(classes: Sequence[str]) -> str:
    """One line counting the levels of each class."""
    counts = ", ".join(f"{classes.count(name)} {name}" for name in CLASS_NAMES if name in classes)
    return f"{len(classes)} levels: {counts}"


def write_sheet(path: str, states: Sequence[State], labels: Sequence[str], columns: int | None, tile_size: int) -> str:
    """Save a labelled contact sheet as PNG; returns a line saying where and how big."""
    image = render_contact_sheet(states, columns=columns, tile_size=tile_size, labels=labels)
    directory = os.path.dirname(path)
    if directory:
        os.makedirs(directory, exist_ok=True)
    Image.fromarray(image).save(path, format="PNG")
    return f"sheet: {path} ({len(states)} levels, {image.shape[1]}x{image.shape[0]} px)"


def export_levels(directory: str, layouts: Sequence[Layout]) -> str:
    """Write `level_0000.txt`, ... into `directory` with `save_layout`; returns a line saying where."""
    os.makedirs(directory, exist_ok=True)
    many = len(layouts) > PROGRESS_MIN_FILES
    for index, layout in enumerate(tqdm(layouts, desc="writing levels", unit="file", disable=not many)):
        save_layout(layout, os.path.join(directory, f"level_{index:04d}.txt"))
    return f"levels: {len(layouts)} files in {directory}"


def emit_batch(args: argparse.Namespace, levels: State, names: Mapping[int, str] | None = None) -> None:
    """Print, draw and export a batch of start states (n, ...) as the flags ask; `names` maps some indices to a
    name for their printed header."""
    states = unbatch(levels)
    classes = level_classes(levels)
    layouts = [layout_from_state(state, name=f"level_{i:04d}") for i, state in enumerate(states)]
    if args.print:
        for index, (layout, level_class) in enumerate(zip(layouts, classes)):
            name = f": {names[index]}" if names and index in names else ""
            print(f"# level {index} ({level_class}){name}\n{layout.to_text()}\n")
    print(class_summary(classes))
    if args.sheet:
        labels = [f"{index} {SHORT_CLASS_NAMES[level_class]}" for index, level_class in enumerate(classes)]
        print(write_sheet(args.sheet, states, labels, args.columns, args.tile_size))
    if args.export:
        print(export_levels(args.export, layouts))


def run_sample(args: argparse.Namespace) -> None:
    config = GeneratorConfig(size=args.kitchen_size, p_smaller=args.smaller_kitchens, p_wall_intact=args.intact_walls)
    emit_batch(args, sample_batch(args.seed, args.n, training=args.training, config=config))


def run_heldout(args: argparse.Namespace) -> None:
    levels = heldout_set(GeneratorConfig(size=args.kitchen_size))
    # The last levels of the set are the expanded classic layouts, in EXPANDED_LAYOUTS order.
    generated = int(levels.step.shape[0]) - len(EXPANDED_LAYOUTS)
    emit_batch(args, levels, names={generated + i: name for i, name in enumerate(EXPANDED_LAYOUTS)})


def run_show(args: argparse.Namespace) -> None:
    # Load everything first, so that a bad file is reported before anything is printed.
    layouts = [load_layout(item) for item in args.layouts]
    states = [make_state(layout) for layout in layouts]
    reports = [analyse_layout(layout) for layout in layouts]
    for item, layout, report in zip(args.layouts, layouts, reports):
        print(f"# {item}\n{layout.to_text()}\nclass: {report.level_class}\n{report.explain()}\n")
    if args.sheet:
        labels = [f"{layout.name} {SHORT_CLASS_NAMES[report.level_class]}" for layout, report in zip(layouts, reports)]
        print(write_sheet(args.sheet, states, labels, args.columns, args.tile_size))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True, metavar="{sample,heldout,show}")

    def add_sheet_options(command: argparse.ArgumentParser) -> None:
        command.add_argument("--sheet", metavar="PATH.png", help="write a labelled contact sheet of the levels")
        command.add_argument("--columns", type=int, default=None, help="levels per sheet row (default: square)")
        command.add_argument("--tile-size", type=int, default=24, help="pixels per grid cell on the sheet")

    def add_batch_options(command: argparse.ArgumentParser) -> None:
        command.add_argument("--kitchen-size", type=int, default=GENERATOR_SIZES[0], choices=GENERATOR_SIZES,
                             help="the generated kitchens' side (training's kitchen_size)")
        command.add_argument("--print", action="store_true", help="print each level's text grid under a header")
        add_sheet_options(command)
        command.add_argument("--export", metavar="DIR", help="write one text file per level, level_0000.txt, ...")

    sample = commands.add_parser("sample", help="draw random levels from the generator")
    sample.add_argument("--n", type=int, default=16, help="number of levels")
    sample.add_argument("--seed", type=int, default=0, help="level i uses key i of split(PRNGKey(seed), n)")
    sample.add_argument("--training", action="store_true", help="sample as training does: no held-out grid")
    sample.add_argument("--smaller-kitchens", type=float, default=0.0,
                        help="at --kitchen-size 9: the share of 7x7 kitchens drawn inside (smaller_kitchens)")
    sample.add_argument("--intact-walls", type=float, default=GeneratorConfig.p_wall_intact,
                        help="the probability that a continuous wall stays whole (training's intact_walls)")
    add_batch_options(sample)
    sample.set_defaults(run=run_sample)

    heldout = commands.add_parser("heldout", help="the held-out evaluation levels (105 at 7x7, 100 at 9x9)")
    add_batch_options(heldout)
    heldout.set_defaults(run=run_heldout)

    show = commands.add_parser("show", help="check registered layouts or text-grid files")
    show.add_argument("layouts", nargs="+", metavar="FILE_OR_NAME", help="registered layout name or text-grid file")
    add_sheet_options(show)
    show.set_defaults(run=run_show)
    return parser


def check_args(args: argparse.Namespace) -> None:
    """Refuse bad numbers and paths before any work, with a `ValueError`."""
    if getattr(args, "n", 1) < 1:
        raise ValueError(f"--n must be at least 1, got {args.n}")
    if args.tile_size < MIN_TILE_SIZE:
        raise ValueError(f"--tile-size must be at least {MIN_TILE_SIZE}, got {args.tile_size}")
    if args.columns is not None and args.columns < 1:
        raise ValueError(f"--columns must be at least 1, got {args.columns}")
    for flag in ("smaller_kitchens", "intact_walls"):
        if not 0.0 <= getattr(args, flag, 0.0) <= 1.0:
            raise ValueError(f"--{flag.replace('_', '-')} must be in [0, 1], got {getattr(args, flag)}")
    if getattr(args, "smaller_kitchens", 0.0) and args.kitchen_size == GENERATOR_SIZES[0]:
        raise ValueError(f"--smaller-kitchens draws smaller kitchens inside larger ones: set --kitchen-size "
                         f"{GENERATOR_SIZES[-1]}")
    if args.sheet and not args.sheet.lower().endswith(".png"):
        raise ValueError(f"--sheet must name a .png file, got {args.sheet!r}")
    export = getattr(args, "export", None)
    if export and os.path.exists(export) and not os.path.isdir(export):
        raise ValueError(f"--export {export!r} is a file, not a directory")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        check_args(args)
        args.run(args)
    except (ValueError, OSError) as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
