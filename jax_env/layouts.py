"""Kitchen layouts: the text grid format, its parser, and the registry of named kitchens.

A layout is the static part of a kitchen: which cell is floor, counter, pile, pot or goal, and where the
two agents start. Grids are written one row per line with these symbols:

    W counter   O onion pile   B plate pile   P pot   X delivery goal   A agent start   (space) floor
    o p d       a counter holding an onion, a plate or a dish (plated soup) at the start
    0 1         agent 0 / agent 1 start, for a level whose agent 0 is not the first 'A' in row-major order

Piles, pots and goals are counters too: agents never stand on them, they face them.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Sequence

import numpy as np

# Cell kinds, as stored in `Layout.grid` and `State.grid` (uint8).
FLOOR, COUNTER, ONION_PILE, PLATE_PILE, POT, GOAL = range(6)
NUM_CELL_KINDS = 6

SYMBOL_TO_KIND = {
    " ": FLOOR, "A": FLOOR, "W": COUNTER, "O": ONION_PILE, "B": PLATE_PILE, "P": POT, "X": GOAL,
    "o": COUNTER, "p": COUNTER, "d": COUNTER, "0": FLOOR, "1": FLOOR,
}  # fmt: skip
KIND_TO_SYMBOL = {FLOOR: " ", COUNTER: "W", ONION_PILE: "O", PLATE_PILE: "B", POT: "P", GOAL: "X"}
ITEM_SYMBOLS = {"o": 1, "p": 2, "d": 3}  # the item codes of jax_env.state: ONION, PLATE, DISH
_REQUIRED = {ONION_PILE: "onion pile (O)", PLATE_PILE: "plate pile (B)", POT: "pot (P)", GOAL: "goal (X)"}


@dataclasses.dataclass(frozen=True, eq=False)
class Layout:
    """A kitchen's static map and the agents' start cells.

    grid: uint8 (H, W) of cell kinds (FLOOR, COUNTER, ONION_PILE, PLATE_PILE, POT, GOAL).
    agent_start: the two agents' start cells as (x, y), agent 0 first.
    start_items: items lying on counters at the start, as ((x, y), item code) pairs.
    """

    name: str
    grid: np.ndarray
    agent_start: tuple[tuple[int, int], tuple[int, int]]
    start_items: tuple[tuple[tuple[int, int], int], ...] = ()

    @property
    def height(self) -> int:
        return int(self.grid.shape[0])

    @property
    def width(self) -> int:
        return int(self.grid.shape[1])

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def to_text(self) -> str:
        """The layout in the text grid format (inverse of `parse_layout` up to agent order)."""
        rows = [[KIND_TO_SYMBOL[int(k)] for k in row] for row in self.grid]
        row_major = sorted(self.agent_start, key=lambda cell: (cell[1], cell[0])) == list(self.agent_start)
        for agent, (x, y) in enumerate(self.agent_start):
            rows[y][x] = "A" if row_major else str(agent)
        symbol_of_item = {item: symbol for symbol, item in ITEM_SYMBOLS.items()}
        for (x, y), item in self.start_items:
            rows[y][x] = symbol_of_item[item]
        return "\n".join("".join(row) for row in rows)

    def same_map(self, other: "Layout") -> bool:
        """True when both layouts have the same cells (agent starts ignored)."""
        return self.grid.shape == other.grid.shape and bool(np.array_equal(self.grid, other.grid))

    def __repr__(self) -> str:
        return f"Layout({self.name!r}, {self.height}x{self.width})"


def parse_layout(text: str, name: str = "custom", agent_order: Sequence[int] = (0, 1)) -> Layout:
    """Parse a text grid into a `Layout`, refusing malformed kitchens with a `ValueError`.

    The first `A` in row-major order is agent 0 unless `agent_order` says otherwise (JaxMARL's
    forced_coord puts the row-major second `A` first: `agent_order=(1, 0)`); a grid may instead name its
    agents `0` and `1`. Leading and trailing blank
    lines are ignored; trailing spaces inside the grid are floor, so rows must all have the same length.
    """
    lines = _grid_lines(text, name)
    grid, agents, items, numbered = _read_symbols(lines, name)
    if numbered[0] or numbered[1]:
        if agents or len(numbered[0]) != 1 or len(numbered[1]) != 1:
            raise ValueError(
                f"layout {name!r}: name the agents either with two 'A' or with one '0' and one '1', "
                f"found {len(agents)} 'A', {len(numbered[0])} '0', {len(numbered[1])} '1'"
            )
        agents, agent_order = numbered[0] + numbered[1], (0, 1)
    if len(agents) != 2:
        where = ", ".join(f"(row {y}, column {x})" for x, y in agents) or "none"
        raise ValueError(f"layout {name!r}: needs exactly 2 agents 'A', found {len(agents)}: {where}")
    for kind, what in _REQUIRED.items():
        if not np.any(grid == kind):
            raise ValueError(f"layout {name!r}: has no {what}; every kitchen needs at least one")
    _check_border(grid, agents, name)
    if sorted(agent_order) != [0, 1]:
        raise ValueError(f"layout {name!r}: agent_order must be a permutation of (0, 1), got {agent_order!r}")
    ordered = (agents[agent_order[0]], agents[agent_order[1]])
    return Layout(name=name, grid=grid, agent_start=ordered, start_items=tuple(items))


def _grid_lines(text: str, name: str) -> list[str]:
    """The grid's rows, blank lines around it dropped; refused if empty or ragged."""
    lines = text.split("\n")
    while lines and not lines[0].strip():
        lines.pop(0)
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise ValueError(f"layout {name!r}: the grid is empty")
    width = len(lines[0])
    for y, line in enumerate(lines):
        if len(line) != width:
            raise ValueError(
                f"layout {name!r}: row {y} has {len(line)} cells but row 0 has {width}; "
                "every row must have the same length (pad with 'W' or spaces)"
            )
    return lines


def _read_symbols(lines: list[str], name: str) -> tuple[np.ndarray, list, list, dict[int, list]]:
    """(grid of kinds, cells of `A`, items on counters, cells of `0` and `1`), refusing unknown symbols."""
    grid = np.zeros((len(lines), len(lines[0])), dtype=np.uint8)
    agents: list[tuple[int, int]] = []
    items: list[tuple[tuple[int, int], int]] = []
    numbered: dict[int, list[tuple[int, int]]] = {0: [], 1: []}
    for y, line in enumerate(lines):
        for x, symbol in enumerate(line):
            if symbol not in SYMBOL_TO_KIND:
                known = ", ".join(repr(s) for s in SYMBOL_TO_KIND)
                raise ValueError(
                    f"layout {name!r}: unknown symbol {symbol!r} at row {y}, column {x}; known symbols: {known}"
                )
            grid[y, x] = SYMBOL_TO_KIND[symbol]
            if symbol == "A":
                agents.append((x, y))
            elif symbol in "01":
                numbered[int(symbol)].append((x, y))
            elif symbol in ITEM_SYMBOLS:
                items.append(((x, y), ITEM_SYMBOLS[symbol]))
    return grid, agents, items, numbered


def _check_border(grid: np.ndarray, agents: list[tuple[int, int]], name: str) -> None:
    """Refuses floor (or an agent) on the outer border: a kitchen is closed."""
    height, width = grid.shape
    for y in range(height):
        for x in range(width):
            on_border = y in (0, height - 1) or x in (0, width - 1)
            if on_border and grid[y, x] == FLOOR:
                what = "an agent" if (x, y) in agents else "floor"
                raise ValueError(
                    f"layout {name!r}: {what} on the outer border at row {y}, column {x}; "
                    "the border must be counters, piles, pots or goals"
                )


# The classic kitchens at their native sizes, with JaxMARL's agent order.
_CLASSIC = {
    "cramped_room": ("WWPWW\nOA AO\nW   W\nWBWXW", (0, 1)),
    "asymm_advantages": ("WWWWWWWWW\nO WXWOW X\nW   P   W\nW A PA  W\nWWWBWBWWW", (0, 1)),
    "coord_ring": ("WWWPW\nW A P\nBAW W\nO   W\nWOXWW", (0, 1)),
    "forced_coord": ("WWWPW\nO WAP\nOAW W\nB W W\nWWWXW", (1, 0)),
    "counter_circuit": ("WWWPPWWW\nW A    W\nB WWWW X\nW     AW\nWWWOOWWW", (0, 1)),
}

# The classic kitchens redrawn on the 7x7 Infinite Kitchen template (held out of training).
_EXPANDED = {
    "cramped_room_7x7": "WWWPWWP\nOA    O\nW     W\nW     W\nW     W\nW    AW\nBBWWWXX",
    "asymm_advantages_7x7": "WXWWWWW\nW   A W\nB     O\nWWWPWPW\nB     X\nW A   W\nWOWWWWW",
    "coord_ring_7x7": "BWWWWPW\nWA A  P\nW WWW W\nB WWW W\nW WWW W\nO     W\nWOWXWWX",
    "forced_coord_7x7": "WWWWWWW\nOA W  P\nO  W  P\nW  W  W\nB  W AW\nB  W  W\nWWWWXXW",
    "counter_circuit_7x7": "XWWPWWP\nW  A  W\nW     W\nB WWW X\nW     W\nW  A  W\nBWWOWWO",
}

CLASSIC_LAYOUTS: tuple[str, ...] = tuple(_CLASSIC)
EXPANDED_LAYOUTS: tuple[str, ...] = tuple(_EXPANDED)
PADDED_SIZE = 7  # the Infinite Kitchen's size
PADDED_SIZES = (7, 9)  # the generator's kitchen sizes (`jax_env.generator.SIZES`)


def padded_text(text: str, size: int = PADDED_SIZE) -> str:
    """A grid drawn in the middle of a `size` x `size` kitchen of counters. The classic layouts are walled in, so
    the added cells are out of reach and the kitchen steps exactly as the classic one does (its cells shifted)."""
    rows = text.split("\n")
    top, left = (size - len(rows)) // 2, (size - len(rows[0])) // 2
    middle = ["W" * left + row + "W" * (size - len(row) - left) for row in rows]
    return "\n".join(["W" * size] * top + middle + ["W" * size] * (size - len(rows) - top))


def _fits(name: str, size: int) -> bool:
    rows = _CLASSIC[name][0].split("\n")
    return max(len(rows), len(rows[0])) <= size


# The classic layouts drawn inside a generated kitchen's size, "<layout>_in_7x7" or "_in_9x9": where teams of that
# size meet partners that know only the classic kitchen (the human proxies). asymm_advantages (9 wide) and
# counter_circuit (8 wide) fit 9x9 only.
_PADDED = {
    f"{name}_in_{size}x{size}": (name, size) for size in PADDED_SIZES for name in _CLASSIC if _fits(name, size)
}  # fmt: skip


def padded_layouts(size: int = PADDED_SIZE) -> tuple[str, ...]:
    """The names of the classic layouts drawn inside `size` x `size` kitchens."""
    return tuple(name for name, (_, padded_size) in _PADDED.items() if padded_size == size)


def padded_name(layout: str, size: int = PADDED_SIZE) -> str:
    """The name of classic `layout` drawn inside a `size` x `size` kitchen (registered where it fits)."""
    return f"{layout}_in_{size}x{size}"


PADDED_LAYOUTS: tuple[str, ...] = padded_layouts(PADDED_SIZE)  # the 7x7 ones
PADDED_LAYOUTS_9X9: tuple[str, ...] = padded_layouts(9)


def layout_names() -> tuple[str, ...]:
    """Every registered layout name."""
    return CLASSIC_LAYOUTS + EXPANDED_LAYOUTS + tuple(_PADDED)


def padded_offset(name: str, size: int = PADDED_SIZE) -> tuple[int, int]:
    """(dx, dy): where cell (0, 0) of classic layout `name` lies in its `size` x `size` drawing."""
    text = _CLASSIC[name][0].split("\n")
    return (size - len(text[0])) // 2, (size - len(text)) // 2


def get_layout(name: str) -> Layout:
    """Look a layout up by name (`cramped_room`, `cramped_room_7x7`, ...)."""
    if name in _CLASSIC:
        text, order = _CLASSIC[name]
        return parse_layout(text, name=name, agent_order=order)
    if name in _EXPANDED:
        return parse_layout(_EXPANDED[name], name=name)
    if name in _PADDED:
        classic, size = _PADDED[name]
        text, order = _CLASSIC[classic]
        return parse_layout(padded_text(text, size), name=name, agent_order=order)
    raise ValueError(f"unknown layout {name!r}; registered layouts: {', '.join(layout_names())}")


def save_layout(layout: Layout, path: str) -> str:
    """Write a layout as a text-grid file that `load_layout` reads back; returns the path."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as grid_file:
        grid_file.write(layout.to_text() + "\n")
    return path


def layout_name(name_or_path: str) -> str:
    """The name `load_layout` gives a layout: a registered name as it is, a file's name without its extension."""
    if name_or_path in layout_names():
        return name_or_path
    return os.path.splitext(os.path.basename(name_or_path))[0]


def load_layout(name_or_path: str) -> Layout:
    """A registered layout by name, else a text-grid file; `ValueError` with a one-line message otherwise."""
    if name_or_path in layout_names():
        return get_layout(name_or_path)
    if os.path.isfile(name_or_path):
        with open(name_or_path, encoding="utf-8") as grid_file:
            text = grid_file.read()
        return parse_layout(text, name=layout_name(name_or_path))
    if os.sep in name_or_path or name_or_path.endswith(".txt"):
        raise ValueError(f"layout file {name_or_path!r} does not exist")
    return get_layout(name_or_path)
