"""The 2019 human-human Overcooked games (Carroll et al.) as this project's states and actions, checked step by step.

The games ship inside the `overcooked-ai` 1.1.0 source distribution on PyPI as two pickled pandas DataFrames
(train and test trials): one row per time step of a game, with the state before and after it as Python literals
and both players' actions. The five layouts are the classic ones (`random0` is forced_coord, `random3`
counter_circuit) and their terrain is JaxMARL's, so every transition replays through `Overcooked.step_env` once
two encodings are mapped: a pot's recorded cook time t is status max(20 - t, 0) (the game's client kept counting
past 20), and a plated soup, held or on a counter, is a dish. The study paid 5 points per soup (JaxMARL: 20), so
deliveries are compared, not rewards.

    frame = read_trials(path)                       # needs pandas
    for game in human_games(frame, "train"):        # HumanGame: arrays per step, checked on construction
        padded_game(game)                           # the same game in its layout drawn inside a 7x7 kitchen
    write_dataset(games, folder)                    # one .npz per split and layout
    load_dataset(folder, "test", "cramped_room")    # -> HumanGames of that split and layout
"""

from __future__ import annotations

import ast
import dataclasses
import functools
from pathlib import Path
from typing import Iterable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from jax_env.env import DELIVERY_REWARD, INTERACT, STAY, Overcooked
from jax_env.layouts import (
    COUNTER,
    FLOOR,
    GOAL,
    ONION_PILE,
    PADDED_SIZE,
    PLATE_PILE,
    POT,
    Layout,
    load_layout,
    padded_layouts,
    padded_name,
    padded_offset,
)
from jax_env.state import DIR_VECTORS, DISH, EMPTY, ONION, PLATE, POT_EMPTY, POT_FULL, State

RECORDED_REWARD = 5.0  # per soup delivered, in the study's game
SOURCE = "overcooked-ai==1.1.0"  # the PyPI release whose source distribution carries the games
TRIALS = {split: f"src/overcooked_ai_py/data/human_data/clean_{split}_trials.pickle" for split in ("train", "test")}
LAYOUTS = {  # the games' layout names -> this project's
    "cramped_room": "cramped_room",
    "asymmetric_advantages": "asymm_advantages",
    "coordination_ring": "coord_ring",
    "random0": "forced_coord",
    "random3": "counter_circuit",
}
TERRAIN = {"X": COUNTER, "O": ONION_PILE, "P": POT, "D": PLATE_PILE, "S": GOAL, " ": FLOOR, "1": FLOOR, "2": FLOOR}
ITEMS = {"onion": ONION, "dish": PLATE, "soup": DISH}  # a held or set-down object; "dish" is an empty plate there
FIELDS = ("contents", "agent_pos", "agent_dir", "agent_inv")  # what a step changes, compared field by field
STORED = (*FIELDS, "actions", "delivered")  # a game's arrays in the dataset


def action_index(action) -> int:
    """A recorded action ([dx, dy] or "INTERACT") -> this project's action index."""
    if isinstance(action, str):
        if action.upper() != "INTERACT":
            raise ValueError(f"unknown action {action!r}")
        return INTERACT
    move = tuple(int(v) for v in action)
    return STAY if move == (0, 0) else DIR_VECTORS.index(move)


def terrain(rows: Iterable[str]) -> np.ndarray:
    """The games' layout text (X counter, O onion, P pot, D dishes, S serving, 1/2 starts) -> cell kinds."""
    return np.asarray([[TERRAIN[symbol] for symbol in row] for row in rows], dtype=np.uint8)


def game_state(record: dict, layout: Layout, step: int) -> dict[str, np.ndarray]:
    """One recorded state (the games' dict) -> this project's `State` fields, as NumPy arrays."""
    grid = np.asarray(layout.grid)
    width = layout.width
    contents = np.where(grid == POT, POT_EMPTY, 0).astype(np.uint8)
    objects = record["objects"].values() if isinstance(record["objects"], dict) else record["objects"]
    for thing in objects:
        x, y = thing["position"]
        if grid[y, x] == POT:
            _, onions, cook_time = thing["state"]
            contents[y, x] = POT_EMPTY - onions if onions < 3 else max(POT_FULL - cook_time, 0)
        else:
            contents[y, x] = ITEMS[thing["name"]]
    players = record["players"]
    held = [player.get("held_object") for player in players]
    return {
        "contents": contents,
        "agent_pos": np.asarray([p["position"][1] * width + p["position"][0] for p in players], np.int32),
        "agent_dir": np.asarray([DIR_VECTORS.index(tuple(p["orientation"])) for p in players], np.int32),
        "agent_inv": np.asarray([EMPTY if h is None else ITEMS[h["name"]] for h in held], np.int32),
        "step": np.int32(step),
    }


@dataclasses.dataclass(frozen=True)
class HumanGame:
    """One recorded game on a registered layout: the state before each of its T steps, both players' actions from
    it, and the soups each step delivered; `human_seats` says which seats a person played (both in the 2019
    games; one in a `kitchen-play` game, whose other seat was the partner).

    contents uint8 [T, H, W]; agent_pos, agent_dir, agent_inv int32 [T, 2]; actions int64 [T, 2]; delivered int32
    [T]. The grid is the layout's (`jax_env.load_layout(layout)`)."""

    name: str
    split: str
    layout: str
    contents: np.ndarray
    agent_pos: np.ndarray
    agent_dir: np.ndarray
    agent_inv: np.ndarray
    actions: np.ndarray
    delivered: np.ndarray
    human_seats: tuple[bool, bool] = (True, True)

    def __len__(self) -> int:
        return len(self.actions)

    def states(self) -> State:
        """The states before each step, batched [T]."""
        grid = np.broadcast_to(np.asarray(load_layout(self.layout).grid), self.contents.shape)
        return State(grid=jnp.asarray(grid), contents=jnp.asarray(self.contents), agent_pos=jnp.asarray(self.agent_pos),
                     agent_dir=jnp.asarray(self.agent_dir), agent_inv=jnp.asarray(self.agent_inv),
                     step=jnp.arange(len(self), dtype=jnp.int32))

    @property
    def deliveries(self) -> int:
        return int(self.delivered.sum())


def read_trials(path) -> "pandas.DataFrame":  # noqa: F821
    """A trials pickle (a path or an open binary file) as its DataFrame."""
    try:
        import pandas
    except ImportError:
        raise ImportError("reading the human games needs pandas: pip install .[humans]") from None
    return pandas.read_pickle(path)


def _literal(value):
    return ast.literal_eval(value) if isinstance(value, str) else value


def human_games(frame, split: str) -> Iterator[HumanGame]:
    """Every game of a trials DataFrame, converted and checked: each recorded step replays exactly through the JAX
    step (`ValueError` naming the game and step otherwise), and each step starts where the one before it ended."""
    keys = ["layout_name", "workerid_num", "run", "round_num"]
    for (layout_name, worker, run, round_num), rows in frame.groupby(keys, sort=True):
        rows = rows.sort_values("cur_gameloop")
        name = f"{LAYOUTS[layout_name]}-worker{int(worker)}-{run}-round{int(round_num)}"
        layout = load_layout(LAYOUTS[layout_name])
        recorded = terrain(_literal(rows["layout"].iloc[0]))
        if not np.array_equal(recorded, np.asarray(layout.grid)):
            raise ValueError(f"{name}: the recorded terrain differs from {layout.name}'s")
        before = [game_state(_literal(s), layout, t) for t, s in enumerate(rows["state"])]
        after = [game_state(_literal(s), layout, t + 1) for t, s in enumerate(rows["next_state"])]
        actions = np.asarray([[action_index(a) for a in _literal(j)] for j in rows["joint_action"]], np.int64)
        game = HumanGame(
            name=name, split=split, layout=layout.name, actions=actions,
            delivered=np.rint(np.asarray(rows["reward"], np.float32) / RECORDED_REWARD).astype(np.int32),
            **{field: np.stack([state[field] for state in before]) for field in FIELDS},
        )  # fmt: skip
        check_replay(game, {field: np.stack([state[field] for state in after]) for field in FIELDS})
        yield game


CHUNK = 512  # steps replayed per call: one compilation per layout, whatever a game's length


@functools.cache
def _batched_step(layout: str):
    return jax.jit(jax.vmap(Overcooked(load_layout(layout)).step_env))


def replay_steps(game: HumanGame) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every step of `game` taken by the JAX env from its recorded state: (the states after, by field; the soups
    each step delivered)."""
    step = _batched_step(game.layout)
    states, actions = game.states(), jnp.asarray(game.actions, jnp.int32)
    pad = -len(game) % CHUNK  # repeats of the last step, dropped below
    states, actions = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, 0)]),
                                             (states, actions))
    afters, rewards = [], []
    for start in range(0, len(actions), CHUNK):
        chunk = jax.tree_util.tree_map(lambda x: x[start:start + CHUNK], (states, actions))
        after, reward, _, _ = step(*chunk)
        afters.append({field: np.asarray(getattr(after, field)) for field in FIELDS})
        rewards.append(np.rint(np.asarray(reward[:, 0]) / DELIVERY_REWARD).astype(np.int32))
    return ({field: np.concatenate([a[field] for a in afters])[: len(game)] for field in FIELDS},
            np.concatenate(rewards)[: len(game)])


def check_replay(game: HumanGame, recorded_after: dict[str, np.ndarray]) -> None:
    """`ValueError` at the first step whose replay differs from the recorded state after it (or its deliveries), or
    that does not start where the step before it ended. `recorded_after` may stop a step short (a game whose state
    after its last step is not known)."""
    replayed, delivered = replay_steps(game)
    known = len(recorded_after["contents"])

    def differs(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # bool [steps]: any element differs
        return (a != b).reshape(len(a), -1).any(axis=1)

    problems = []  # (step, message) of the first step each check fails at
    for field in FIELDS:
        after = recorded_after[field]
        if (bad := np.flatnonzero(differs(replayed[field][:known], after))).size:
            t = int(bad[0])
            problems.append((t, f"step {t} replays to {field} {replayed[field][t].tolist()}, the record has "
                                f"{after[t].tolist()}"))
        if (bad := np.flatnonzero(differs(getattr(game, field)[1:], after[: len(game) - 1]))).size:
            t = int(bad[0])
            problems.append((t + 1, f"step {t + 1} does not start where step {t} ended ({field})"))
    if (bad := np.flatnonzero(delivered[:known] != game.delivered[:known])).size:
        t = int(bad[0])
        problems.append((t, f"step {t} replays to {delivered[t]} soups delivered, the record has {game.delivered[t]}"))
    if problems:
        raise ValueError(f"{game.name}: {min(problems, key=lambda problem: problem[0])[1]}")


def padded_game(game: HumanGame, size: int = PADDED_SIZE) -> HumanGame:
    """`game` in its layout drawn inside a `size` x `size` kitchen (`jax_env.layouts.padded_layouts`), where teams
    of that size can meet a proxy of its players: the same steps, every cell shifted, every step's replay checked."""
    layout = padded_name(game.layout, size)
    if layout not in padded_layouts(size):
        raise ValueError(f"{game.layout} does not fit a {size}x{size} kitchen")
    (dx, dy), (height, width) = padded_offset(game.layout, size), game.contents.shape[1:]
    contents = np.zeros((len(game), size, size), np.uint8)
    contents[:, dy:dy + height, dx:dx + width] = game.contents
    x, y = game.agent_pos % width, game.agent_pos // width
    agent_pos = ((y + dy) * size + x + dx).astype(np.int32)
    padded = dataclasses.replace(game, layout=layout, contents=contents, agent_pos=agent_pos)
    check_replay(padded, {field: getattr(padded, field)[1:] for field in FIELDS})
    return padded


def write_dataset(games: Iterable[HumanGame], folder: str | Path) -> dict[tuple[str, str], int]:
    """One `<split>_<layout>.npz` per split and layout in `folder`, each game's steps one after the other with its
    index in `game` and its name in `names`. Returns the steps written per (split, layout)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    grouped: dict[tuple[str, str], list[HumanGame]] = {}
    for game in games:
        grouped.setdefault((game.split, game.layout), []).append(game)
    for (split, layout), group in grouped.items():
        arrays = {field: np.concatenate([getattr(g, field) for g in group]) for field in STORED}
        np.savez_compressed(folder / f"{split}_{layout}.npz", **arrays, names=np.asarray([g.name for g in group]),
                            game=np.concatenate([np.full(len(g), i, np.int32) for i, g in enumerate(group)]),
                            human_seats=np.asarray([g.human_seats for g in group], bool))
    return {key: sum(len(g) for g in group) for key, group in grouped.items()}


def load_dataset(folder: str | Path, split: str, layout: str) -> list[HumanGame]:
    """The games of one split and layout written by `write_dataset`."""
    path = Path(folder) / f"{split}_{layout}.npz"
    if not path.exists():
        raise FileNotFoundError(f"no human games at {path}: run `kitchen-humans fetch` first")
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    if missing := {*STORED, "names", "game", "human_seats"} - arrays.keys():
        raise ValueError(f"{path} lacks {', '.join(sorted(missing))}: written by another version; write it again")
    games = []
    for index, name in enumerate(arrays["names"]):
        rows = arrays["game"] == index
        games.append(HumanGame(name=str(name), split=split, layout=layout,
                               human_seats=tuple(bool(seat) for seat in arrays["human_seats"][index]),
                               **{field: arrays[field][rows] for field in STORED}))
    return games
