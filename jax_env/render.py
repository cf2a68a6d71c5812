"""Pictures and text of a kitchen: an RGB image per state, an animated GIF per episode, a contact sheet of
many levels, a terminal sketch.

Drawing uses numpy and Pillow only. Every function takes unbatched states (leaves without a batch axis),
as jax or numpy arrays; `write_gif` also takes one state whose leaves carry a leading time axis (T, ...),
and `render_contact_sheet` one whose leaves carry a leading batch axis (N, ...).
"""

from __future__ import annotations

import math
import os
from typing import Sequence

import jax
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from jax_env.layouts import COUNTER, FLOOR, GOAL, KIND_TO_SYMBOL, ONION_PILE, PLATE_PILE, POT
from jax_env.state import DIR_VECTORS, DISH, EMPTY, ITEM_NAMES, ONION, PLATE, POT_EMPTY, POT_FULL, POT_READY, State

# Shapes are drawn this many times larger and box-filtered down, which anti-aliases every edge while
# leaving flat areas (agent bodies included) at their exact colours.
_SUPERSAMPLE = 4
MIN_TILE_SIZE = 8

AGENT_COLOURS = ((214, 48, 49), (38, 98, 214))  # agent 0 red, agent 1 blue
_AGENT_OUTLINES = ((120, 20, 20), (16, 48, 120))

_FLOOR = (236, 229, 214)
_FLOOR_LINE = (218, 209, 190)
_COUNTER_EDGE = (134, 96, 60)
_COUNTER_TOP = (184, 140, 94)
_CRATE = (112, 78, 46)
_POT_BODY = (72, 74, 82)
_POT_INSIDE = (40, 41, 46)
_BROTH = (150, 112, 52)
_SOUP = (236, 116, 40)
_SOUP_SHINE = (250, 170, 90)
_READY_RING = (64, 200, 90)
_BAR_BACK = (58, 50, 42)
_BAR_COOKING = (245, 186, 40)
_GOAL_MAT = (104, 176, 104)
_GOAL_EDGE = (56, 120, 62)
_GOAL_STRIPE = (140, 204, 140)
_ONION = (228, 180, 66)
_ONION_EDGE = (150, 104, 28)
_ONION_STEM = (92, 156, 56)
_PLATE = (248, 248, 246)
_PLATE_EDGE = (150, 150, 156)
_SHEET_BACKGROUND = (250, 247, 240)
_SHEET_LABEL = (64, 54, 44)

_DIR_LETTERS = "NSEW"


def _to_numpy(state: State) -> State:
    """The same state with numpy leaves, fetched from the device in one go."""
    return jax.tree_util.tree_map(np.asarray, jax.device_get(state))


class _Tile:
    """Draws in one tile with coordinates relative to the tile: (0, 0) top-left, (1, 1) bottom-right."""

    def __init__(self, draw: ImageDraw.ImageDraw, x: int, y: int, size: int):
        self.draw, self.left, self.top, self.size = draw, x * size, y * size, size

    def point(self, u: float, v: float) -> tuple[float, float]:
        return self.left + u * self.size, self.top + v * self.size

    def line_width(self, fraction: float) -> int:
        return max(1, round(fraction * self.size))

    def rect(self, u0, v0, u1, v1, fill, outline=None, width=0.0, radius=0.0):
        box = (*self.point(u0, v0), *self.point(u1, v1))
        outline_px = self.line_width(width) if outline is not None else 0
        if radius > 0:
            self.draw.rounded_rectangle(box, radius * self.size, fill=fill, outline=outline, width=outline_px)
        else:
            self.draw.rectangle(box, fill=fill, outline=outline, width=outline_px)

    def circle(self, u, v, r, fill, outline=None, width=0.0):
        self.ellipse(u, v, r, r, fill, outline, width)

    def ellipse(self, u, v, ru, rv, fill, outline=None, width=0.0):
        box = (*self.point(u - ru, v - rv), *self.point(u + ru, v + rv))
        outline_px = self.line_width(width) if outline is not None else 0
        self.draw.ellipse(box, fill=fill, outline=outline, width=outline_px)

    def polygon(self, points, fill, outline=None, width=0.0):
        outline_px = self.line_width(width) if outline is not None else 0
        self.draw.polygon([self.point(u, v) for u, v in points], fill=fill, outline=outline, width=outline_px)


def _draw_floor(tile: _Tile) -> None:
    tile.rect(0, 0, 1, 1, fill=_FLOOR_LINE)
    tile.rect(0.03, 0.03, 0.97, 0.97, fill=_FLOOR)


def _draw_counter(tile: _Tile) -> None:
    tile.rect(0, 0, 1, 1, fill=_COUNTER_EDGE)
    tile.rect(0.04, 0.04, 0.96, 0.96, fill=_COUNTER_TOP, radius=0.05)


def _draw_onion(tile: _Tile, u: float, v: float, r: float) -> None:
    tile.polygon([(u - 0.25 * r, v - 0.8 * r), (u, v - 1.45 * r), (u + 0.25 * r, v - 0.8 * r)], fill=_ONION_STEM)
    tile.circle(u, v, r, fill=_ONION, outline=_ONION_EDGE, width=max(0.02, 0.12 * r))


def _draw_plate(tile: _Tile, u: float, v: float, r: float, with_soup: bool = False) -> None:
    tile.circle(u, v, r, fill=_PLATE, outline=_PLATE_EDGE, width=max(0.02, 0.1 * r))
    if with_soup:
        tile.circle(u, v, 0.66 * r, fill=_SOUP)
        tile.circle(u - 0.22 * r, v - 0.22 * r, 0.18 * r, fill=_SOUP_SHINE)
    else:
        tile.circle(u, v, 0.62 * r, fill=None, outline=_PLATE_EDGE, width=max(0.015, 0.05 * r))


def _draw_item(tile: _Tile, item: int, u: float, v: float, r: float) -> None:
    if item == ONION:
        _draw_onion(tile, u, v + 0.15 * r, 0.85 * r)
    elif item == PLATE:
        _draw_plate(tile, u, v, r)
    elif item == DISH:
        _draw_plate(tile, u, v, r, with_soup=True)


def _draw_onion_pile(tile: _Tile) -> None:
    _draw_counter(tile)
    tile.rect(0.14, 0.2, 0.86, 0.86, fill=_CRATE, radius=0.06)
    for u, v in ((0.34, 0.66), (0.66, 0.66), (0.5, 0.42)):
        _draw_onion(tile, u, v, 0.15)


def _draw_plate_pile(tile: _Tile) -> None:
    _draw_counter(tile)
    for v in (0.68, 0.56, 0.44):
        tile.ellipse(0.5, v, 0.32, 0.14, fill=_PLATE, outline=_PLATE_EDGE, width=0.03)


def _draw_goal(tile: _Tile) -> None:
    _draw_counter(tile)
    tile.rect(0.12, 0.12, 0.88, 0.88, fill=_GOAL_MAT, outline=_GOAL_EDGE, width=0.05, radius=0.06)
    # Chevrons pointing out of the kitchen: "serve here".
    for v in (0.3, 0.52):
        chevron = [(0.3, v + 0.18), (0.5, v), (0.7, v + 0.18), (0.7, v + 0.28), (0.5, v + 0.1), (0.3, v + 0.28)]
        tile.polygon(chevron, fill=_GOAL_STRIPE)


def _draw_pot(tile: _Tile, status: int) -> None:
    _draw_counter(tile)
    u, v = 0.5, 0.44
    tile.rect(0.08, v - 0.05, 0.92, v + 0.05, fill=_POT_BODY, radius=0.03)  # handles
    ready = status == POT_READY
    tile.circle(u, v, 0.34, fill=_POT_BODY, outline=_READY_RING if ready else None, width=0.06)
    if ready:
        tile.circle(u, v, 0.25, fill=_SOUP)
        tile.circle(u - 0.08, v - 0.08, 0.06, fill=_SOUP_SHINE)
    else:
        cooking = status <= POT_FULL
        tile.circle(u, v, 0.25, fill=_BROTH if cooking else _POT_INSIDE)
        onions = 3 if cooking else max(0, POT_EMPTY - status)
        spots = {1: ((0.5, 0.47),), 2: ((0.39, 0.47), (0.61, 0.47)), 3: ((0.39, 0.52), (0.61, 0.52), (0.5, 0.34))}
        for spot in spots.get(onions, ()):
            _draw_onion(tile, *spot, 0.095)
    if status <= POT_FULL:
        done = 1.0 - status / POT_FULL
        tile.rect(0.12, 0.84, 0.88, 0.94, fill=_BAR_BACK, radius=0.03)
        if done > 0:
            tile.rect(0.12, 0.84, 0.12 + 0.76 * done, 0.94, fill=_READY_RING if ready else _BAR_COOKING, radius=0.03)


def _draw_agent(tile: _Tile, agent: int, direction: int, held: int) -> None:
    dx, dy = DIR_VECTORS[direction]
    px, py = -dy, dx  # perpendicular to the facing
    tip = (0.5 + 0.4 * dx, 0.5 + 0.4 * dy)
    back = (0.5 - 0.3 * dx, 0.5 - 0.3 * dy)
    corners = [tip, (back[0] + 0.36 * px, back[1] + 0.36 * py), (back[0] - 0.36 * px, back[1] - 0.36 * py)]
    tile.polygon(corners, fill=AGENT_COLOURS[agent], outline=_AGENT_OUTLINES[agent], width=0.05)
    if held != EMPTY:
        # At the triangle's centroid, small enough to leave the agent's colour showing around it.
        _draw_item(tile, held, 0.5 - 0.067 * dx, 0.5 - 0.067 * dy, 0.16)


_STATIC_DRAWERS = {
    FLOOR: _draw_floor,
    COUNTER: _draw_counter,
    ONION_PILE: _draw_onion_pile,
    PLATE_PILE: _draw_plate_pile,
    GOAL: _draw_goal,
}


def render_state(state: State, tile_size: int = 32) -> np.ndarray:
    """Draw one unbatched state: uint8 (H * tile_size, W * tile_size, 3) RGB.

    Agents are triangles pointing where they face (agent 0 red, agent 1 blue) with what they hold drawn
    on them; pots show their onions, a progress bar while cooking, and a green ring around ready soup.
    """
    if int(tile_size) < MIN_TILE_SIZE:
        raise ValueError(f"tile_size must be at least {MIN_TILE_SIZE} pixels, got {tile_size}")
    state = _to_numpy(state)
    if state.grid.ndim != 2:
        raise ValueError(
            f"render_state draws one unbatched state, got a grid of shape {state.grid.shape}; "
            "index the batch first, or use write_gif for a time axis"
        )
    height, width = state.grid.shape
    size = int(tile_size) * _SUPERSAMPLE
    image = Image.new("RGB", (width * size, height * size), _FLOOR)
    draw = ImageDraw.Draw(image)

    for y in range(height):
        for x in range(width):
            kind, value = int(state.grid[y, x]), int(state.contents[y, x])
            tile = _Tile(draw, x, y, size)
            if kind == POT:
                _draw_pot(tile, value)
                continue
            _STATIC_DRAWERS.get(kind, _draw_floor)(tile)
            if kind == COUNTER and value != EMPTY:
                _draw_item(tile, value, 0.5, 0.5, 0.26)

    for agent in range(2):
        y, x = divmod(int(state.agent_pos[agent]), width)
        _draw_agent(_Tile(draw, x, y, size), agent, int(state.agent_dir[agent]), int(state.agent_inv[agent]))

    return np.asarray(image.reduce(_SUPERSAMPLE), dtype=np.uint8)


def _split_frames(states: State | Sequence[State], caller: str = "write_gif") -> list[State]:
    """Unbatched numpy states from a list of states or from one state with a leading (time or batch) axis."""
    if isinstance(states, State):
        stacked = _to_numpy(states)
        if stacked.step.ndim == 0:
            return [stacked]
        if stacked.step.ndim != 1:
            raise ValueError(
                f"{caller} takes states with at most one leading axis, got step of shape {stacked.step.shape}"
            )
        return [jax.tree_util.tree_map(lambda leaf, t=t: leaf[t], stacked) for t in range(stacked.step.shape[0])]
    frames = list(states)
    if not frames:
        raise ValueError(f"{caller} needs at least one state")
    return frames


def write_gif(
    states: State | Sequence[State], path: str | os.PathLike, tile_size: int = 32, fps: float = 10.0
) -> str:
    """Write an animated GIF of an episode, one frame per state, looping forever; returns the path.

    `states` is a list of unbatched states or one state whose leaves have a leading time axis (T, ...).
    Identical consecutive frames are stored once with their durations added, so the clip keeps its length.
    """
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    frames = [Image.fromarray(render_state(state, tile_size)) for state in _split_frames(states)]
    # One palette for the whole clip keeps still parts of the kitchen from flickering between frames.
    sample = frames[:: max(1, len(frames) // 32)]
    montage = Image.new("RGB", (frames[0].width, frames[0].height * len(sample)))
    for i, frame in enumerate(sample):
        montage.paste(frame, (0, i * frames[0].height))
    palette = montage.quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    indexed = [frame.quantize(palette=palette, dither=Image.Dither.NONE) for frame in frames]

    path = os.fspath(path)
    directory = os.path.dirname(path)
    if directory:
        os.makedirs(directory, exist_ok=True)
    indexed[0].save(
        path, save_all=True, append_images=indexed[1:], duration=round(1000 / fps), loop=0, disposal=1
    )
    return path


def render_contact_sheet(
    states: State | Sequence[State],
    columns: int | None = None,
    tile_size: int = 24,
    labels: Sequence[str] | None = None,
) -> np.ndarray:
    """Draw N levels on one sheet, row by row: uint8 (rows * (cell + label) + gaps, columns * cell + gaps, 3) RGB.

    `states` is a list of unbatched states or one state whose leaves have a leading batch axis (N, ...).
    Every level gets a cell the size of the largest one, centred in it; `columns` defaults to ceil(sqrt(N)).
    `labels`, one short string per level (e.g. "3 solo"), is written under each cell and cut to its width.
    """
    levels = _split_frames(states, "render_contact_sheet")
    if labels is not None and len(labels) != len(levels):
        raise ValueError(f"render_contact_sheet got {len(labels)} labels for {len(levels)} levels")
    if columns is not None and columns < 1:
        raise ValueError(f"columns must be positive, got {columns}")
    images = [render_state(level, tile_size) for level in levels]
    columns = min(columns or math.ceil(math.sqrt(len(images))), len(images))
    rows = math.ceil(len(images) / columns)
    cell_height = max(image.shape[0] for image in images)
    cell_width = max(image.shape[1] for image in images)
    gap = max(4, int(tile_size) // 3)

    font = ImageFont.load_default(size=max(10, round(int(tile_size) / 2)))
    label_height = 0 if labels is None else gap // 2 + font.getbbox("Agy|")[3]
    pitch_x, pitch_y = cell_width + gap, cell_height + label_height + gap
    sheet = Image.new("RGB", (gap + columns * pitch_x, gap + rows * pitch_y), _SHEET_BACKGROUND)
    draw = ImageDraw.Draw(sheet)

    for index, image in enumerate(images):
        row, column = divmod(index, columns)
        left, top = gap + column * pitch_x, gap + row * pitch_y
        offset = ((cell_width - image.shape[1]) // 2, (cell_height - image.shape[0]) // 2)
        sheet.paste(Image.fromarray(image), (left + offset[0], top + offset[1]))
        if labels is not None:
            text = str(labels[index])
            while len(text) > 1 and draw.textlength(text, font=font) > cell_width:
                text = text[:-2] + "…"
            x = left + (cell_width - draw.textlength(text, font=font)) / 2
            draw.text((x, top + cell_height + gap // 2), text, fill=_SHEET_LABEL, font=font)

    return np.asarray(sheet, dtype=np.uint8)


def _item_name(item: int) -> str:
    if item == EMPTY:
        return "nothing"
    return ITEM_NAMES[item] if 0 <= item < len(ITEM_NAMES) else f"item {item}?"


def _pot_phase(status: int) -> str:
    if status == POT_READY:
        return "ready"
    if status <= POT_FULL:
        return f"cooking, {status} left"
    if status <= POT_EMPTY:
        onions = POT_EMPTY - status
        return "empty" if onions == 0 else f"{onions} onion" + ("s" if onions > 1 else "")
    return f"status {status}?"


def state_to_text(state: State) -> str:
    """A compact text sketch of one unbatched state, for terminals, logs and error messages.

    The grid uses the layout symbols (W counter, O onion pile, B plate pile, P pot, X goal, space floor);
    agents are the digits 0 and 1, items on counters are o (onion), p (plate) and d (dish). Below the grid:
    the step, each agent's cell (x, y), facing (N/S/E/W) and held item, and each pot's status.
    """
    state = _to_numpy(state)
    height, width = state.grid.shape
    item_letters = {ONION: "o", PLATE: "p", DISH: "d"}
    rows = []
    for y in range(height):
        row = []
        for x in range(width):
            kind, value = int(state.grid[y, x]), int(state.contents[y, x])
            symbol = KIND_TO_SYMBOL.get(kind, "?")
            if kind == COUNTER and value != EMPTY:
                symbol = item_letters.get(value, "?")
            row.append(symbol)
        rows.append(row)

    lines = [f"step {int(state.step)}"]
    for agent in range(2):
        y, x = divmod(int(state.agent_pos[agent]), width)
        rows[y][x] = str(agent)
        direction, held = int(state.agent_dir[agent]), int(state.agent_inv[agent])
        facing = _DIR_LETTERS[direction] if 0 <= direction < 4 else "?"
        lines.append(f"agent {agent} at ({x},{y}) facing {facing}, holding {_item_name(held)}")

    pots = [
        f"pot ({x},{y}): {_pot_phase(int(state.contents[y, x]))}"
        for y, x in zip(*np.nonzero(state.grid == POT))
    ]
    lines.append("; ".join(pots))
    return "\n".join(["".join(row) for row in rows] + lines)
