"""Exact number of distinct initial states the Infinite Kitchen generator (`jax_env.generator`) can produce.

An initial state is (grid, loose items, agent cells, agent facings); pots start empty and hands empty, so they
add nothing. The count is a sum over the distinct interior wall maps (different predicates can give the same
map: the empty interior is also a fully reopened middle block, and a column-3 or row-3 wall reopened at both
ends is also a middle block keeping only its middle column or row):

    for each wall map m with w interior walls (all of them questionable cells, so q = 8 + w questionable walls,
    counting the 4 corners and the 4 T-junctions, and 24 + w wall cells in all):
        required items: 16 * 15 * 14 * 13 ordered placements on the 16 safe cells (the kinds are distinct)
        extras: for each set T of kinds given a second copy, q! / (q - |T|)! ordered distinct cells
        loose items: for each set S of loose kinds, c! / (c - |S|)! ordered distinct plain counters, where
                     c = 24 + w - 4 - |T| counters hold no pile, pot or goal
        agents: 2 quadrant pairs x 3 x 3 cells x 2 assignments = 36, facings 4 x 4 = 16

The grid determines the wall map (walls are its non-floor cells), and required items (safe cells) and extras
(questionable cells) live on disjoint cells, so different terms are different states.

Relation to the paper's 4.60e28: the paper gives no computation. The walls + items (5.3e11) and + agents &
facings (3.1e14) figures agree with a count of the authors' released generator; with loose items this
generator reaches 3.1e18 distinct initial states, about 1.5e10 times fewer than the paper's figure, which no
part of the generator as specified (pots and hands start empty) can make up.

    python scripts/count_initial_states.py                 # the exact count and its breakdown
    python scripts/count_initial_states.py --cross-check   # also compare reduced counts with JAX samples

Pure Python; only the cross-check imports jax (through jax_env).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from pathlib import Path
from typing import Mapping

import numpy as np

SIZE = 7
COUNTER = 1  # jax_env.layouts.COUNTER: a plain counter cell
BORDER = frozenset((r, c) for r in range(SIZE) for c in range(SIZE) if r in (0, SIZE - 1) or c in (0, SIZE - 1))
CORNERS = frozenset({(0, 0), (0, 6), (6, 0), (6, 6)})
T_JUNCTIONS = frozenset({(0, 3), (3, 0), (3, 6), (6, 3)})
SAFE = tuple(sorted(BORDER - CORNERS - T_JUNCTIONS))
BLOCK = tuple((r, c) for r in range(2, 5) for c in range(2, 5))
VERTICAL = tuple((r, 3) for r in range(1, 6))
HORIZONTAL = tuple((3, c) for c in range(1, 6))
CROSS = frozenset({(3, c) for c in range(SIZE)} | {(r, 3) for r in range(SIZE)})
QUESTIONABLE = frozenset(CROSS | set(BLOCK) | CORNERS)

NUM_REQUIRED = 4  # onion pile, plate pile, pot, goal
NUM_AGENT_CELLS = 2 * 3 * 3 * 2  # quadrant pair, a cell in each quadrant, which agent goes where
NUM_FACINGS = 4 * 4
PAPER_CLAIM = 4.60e28

# The paper's probabilities, named as the fields of jax_env.generator.GeneratorConfig.
PAPER_PROBS = {
    "p_empty": 0.1,
    "p_middle": 0.3,
    "p_vertical": 0.3,
    "p_horizontal": 0.3,
    "p_block_reopen": 0.5,
    "p_wall_intact": 0.25,
    "p_extra_item": 0.75,
    "p_loose_onion": 0.5,
    "p_loose_plate": 0.5,
    "p_loose_dish": 0.5,
}
LOOSE_FIELDS = ("p_loose_onion", "p_loose_plate", "p_loose_dish")


def falling(n: int, k: int) -> int:
    """n * (n - 1) * ... * (n - k + 1): ordered choices of k distinct cells among n."""
    return math.perm(n, k) if 0 <= k <= n else 0


def outcomes(p: float) -> tuple[bool, ...]:
    """The outcomes a coin with P(True) = p can show."""
    return ((False,) if p < 1 else ()) + ((True,) if p > 0 else ())


def wall_maps_by_predicate(probs: Mapping[str, float]) -> dict[str, set[frozenset]]:
    """Interior wall maps (sets of (row, col) walls) each predicate can produce, for predicates of positive
    probability."""
    maps: dict[str, set[frozenset]] = {}
    if probs["p_empty"] > 0:
        maps["empty"] = {frozenset()}
    if probs["p_middle"] > 0:
        kept = outcomes(1 - probs["p_block_reopen"])
        maps["middle"] = {
            frozenset(cell for cell, keep in zip(BLOCK, choice) if keep)
            for choice in itertools.product(kept, repeat=len(BLOCK))
        }
    for name, line in (("vertical", VERTICAL), ("horizontal", HORIZONTAL)):
        if probs[f"p_{name}"] > 0:
            maps[name] = set()
            if probs["p_wall_intact"] > 0:
                maps[name].add(frozenset(line))
            if probs["p_wall_intact"] < 1:
                maps[name] |= {frozenset(line) - set(opened) for opened in itertools.combinations(line, 2)}
    return maps


def wall_maps(probs: Mapping[str, float]) -> set[frozenset]:
    """The distinct interior wall maps of the generator."""
    return set().union(*wall_maps_by_predicate(probs).values())


def extras_and_loose(walls: frozenset, probs: Mapping[str, float]) -> tuple[int, int]:
    """(extra placements, extra and loose placements) on one wall map, required items fixed."""
    questionable_walls = len(QUESTIONABLE & (BORDER | walls))
    all_walls = len(BORDER) + len(walls)
    extra_counts = [sum(flags) for flags in itertools.product(outcomes(probs["p_extra_item"]), repeat=NUM_REQUIRED)]
    loose_counts = [sum(flags) for flags in itertools.product(*(outcomes(probs[f]) for f in LOOSE_FIELDS))]
    extras = sum(falling(questionable_walls, k) for k in extra_counts)
    with_loose = sum(
        falling(questionable_walls, k) * sum(falling(all_walls - NUM_REQUIRED - k, j) for j in loose_counts)
        for k in extra_counts
    )
    return extras, with_loose


def count_initial_states(probs: Mapping[str, float] = PAPER_PROBS) -> dict[str, int]:
    """Exact support sizes of the generator with these probabilities (only which are 0, 1 or between matters):
    wall maps, walls + items, + agents & facings, + loose items (the full initial state)."""
    maps = wall_maps(probs)
    required = falling(len(SAFE), NUM_REQUIRED)
    per_map = [extras_and_loose(m, probs) for m in maps]
    items = required * sum(extras for extras, _ in per_map)
    agents = NUM_AGENT_CELLS * NUM_FACINGS
    return {
        "wall maps": len(maps),
        "walls + items": items,
        "+ agents & facings": items * agents,
        "+ loose items": required * agents * sum(loose for _, loose in per_map),
    }


def reduced_count(probs: Mapping[str, float], with_agents: bool = False) -> int:
    """Support size of `reduced_keys`: levels up to where the required items stand (walls, extras, loose items),
    times the agent cells and facings if `with_agents`."""
    total = sum(loose for _, loose in (extras_and_loose(m, probs) for m in wall_maps(probs)))
    return total * (NUM_AGENT_CELLS * NUM_FACINGS if with_agents else 1)


def reduced_keys(grid: np.ndarray, contents: np.ndarray, agent_pos=None, agent_dir=None) -> np.ndarray:
    """uint8 (N, 78) or (N, 82): one row per level (grid, contents uint8 (N, 7, 7)) that forgets which safe
    cells the required items took: the 33 non-safe cells' kinds and contents, then the contents of the 12
    safe cells left free, in a fixed order. For a fixed placement of the required items this is one-to-one,
    and every placement leaves the same choices for the rest, so the distinct rows number `reduced_count`."""
    n = grid.shape[0]
    safe = np.array([r * SIZE + c for r, c in SAFE])
    other = np.setdiff1d(np.arange(SIZE * SIZE), safe)
    grid, contents = grid.reshape(n, -1), contents.reshape(n, -1)
    free_first = np.argsort(grid[:, safe] != COUNTER, axis=1, kind="stable")[:, : len(SAFE) - NUM_REQUIRED]
    parts = [grid[:, other], contents[:, other], np.take_along_axis(contents[:, safe], free_first, axis=1)]
    if agent_pos is not None:
        parts += [np.asarray(agent_pos).reshape(n, 2), np.asarray(agent_dir).reshape(n, 2)]
    return np.concatenate([np.asarray(p, dtype=np.uint8) for p in parts], axis=1)


def cross_check(
    probs: Mapping[str, float], num_samples: int = 200_000, seed: int = 0, with_agents: bool = False,
    batch_size: int = 25_000,
) -> tuple[int, int]:
    """(distinct sampled, analytic): the number of distinct `reduced_keys` among about `num_samples` levels
    (whole batches of equal size) from the JAX sampler with these probabilities, and `reduced_count`. Equal
    when sampling covers the support."""
    try:
        import jax
    except ImportError as error:
        raise SystemExit(f"the cross-check samples with jax_env, which needs jax: {error}") from error
    if str(Path(__file__).resolve().parents[1]) not in sys.path:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from jax_env.generator import GeneratorConfig, sample_levels

    config = GeneratorConfig(**probs)
    num_batches = -(-num_samples // batch_size)
    seen = set()
    for i in range(num_batches):
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), i), -(-num_samples // num_batches))
        levels = jax.tree_util.tree_map(np.asarray, sample_levels(keys, config))
        agents = (levels.agent_pos, levels.agent_dir) if with_agents else (None, None)
        seen.update(row.tobytes() for row in reduced_keys(levels.grid, levels.contents, *agents))
    return len(seen), reduced_count(probs, with_agents)


# Reduced settings small enough for sampling to cover: each exercises one part of the count.
CROSS_CHECKS = {
    "walls (all predicates, overlapping maps)": dict(
        PAPER_PROBS, p_empty=0.2, p_middle=0.4, p_vertical=0.2, p_horizontal=0.2, p_wall_intact=0.5,
        p_extra_item=0.0, p_loose_onion=0.0, p_loose_plate=0.0, p_loose_dish=0.0,
    ),
    "continuous walls + a loose onion": dict(
        PAPER_PROBS, p_empty=0.0, p_middle=0.0, p_vertical=0.5, p_horizontal=0.5, p_wall_intact=0.5,
        p_extra_item=0.0, p_loose_onion=0.5, p_loose_plate=0.0, p_loose_dish=0.0,
    ),
    "extras of all 4 kinds, empty interior": dict(
        PAPER_PROBS, p_empty=1.0, p_middle=0.0, p_vertical=0.0, p_horizontal=0.0,
        p_extra_item=1.0, p_loose_onion=0.0, p_loose_plate=0.0, p_loose_dish=0.0,
    ),
    "agents & facings, empty interior": dict(
        PAPER_PROBS, p_empty=1.0, p_middle=0.0, p_vertical=0.0, p_horizontal=0.0,
        p_extra_item=0.0, p_loose_onion=0.0, p_loose_plate=0.0, p_loose_dish=0.0,
    ),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cross-check", action="store_true", help="compare reduced counts with JAX samples")
    parser.add_argument("--samples", type=int, default=200_000, help="levels sampled per cross-check")
    args = parser.parse_args()

    for name, maps in wall_maps_by_predicate(PAPER_PROBS).items():
        print(f"{name:>10} predicate: {len(maps):4d} wall maps")
    counts = count_initial_states(PAPER_PROBS)
    print(f"{'distinct':>10} wall maps: {counts['wall maps']:4d} (after removing maps shared by predicates)")
    print()
    for name, value in counts.items():
        print(f"{name:>20}: {value:.3e}  ({value})")
    total = counts["+ loose items"]
    print()
    print(f"exact number of distinct initial states: {total} = {total:.3e}")
    print(f"paper's claim: {PAPER_CLAIM:.2e} = {PAPER_CLAIM / total:.3g} x this count (the paper shows no computation;")
    print("  walls + items and + agents & facings match counts of the released generator, 5.3e11 and 3.1e14)")

    if args.cross_check:
        print()
        for name, probs in CROSS_CHECKS.items():
            with_agents = name.startswith("agents")
            sampled, analytic = cross_check(probs, args.samples, with_agents=with_agents)
            verdict = "ok" if sampled == analytic else "MISMATCH"
            print(f"cross-check {name}: {sampled} distinct in {args.samples} samples, analytic {analytic}: {verdict}")


if __name__ == "__main__":
    main()
