"""A game played in a `KitchenEnv` and recorded step by step (`kitchen-play`'s and `kitchen-study`'s records, one
JSON line per step after a header), read back and replayed through the same env: every step's positions and score
checked, the states before each step rebuilt (`replayed_states`), for a replay, a GIF, or human games to clone."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import step_mdp

from jax_env import NUM_ACTIONS, State, parse_layout
from torch_kitchen.env import KitchenEnv

HEADER_FIELDS = ("layout", "layout_name", "seed", "max_steps", "seat")  # what a replay needs


def read_record(path: str | Path) -> tuple[dict, list[dict], dict | None]:
    """(header, step lines, end line or None) of a game record; ValueError for a file that is not one (a line
    that is not JSON, no header, a header without what a replay needs, a step without two legal actions)."""
    lines = []
    for number, text in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if text.strip():
            try:
                lines.append(json.loads(text))
            except json.JSONDecodeError:
                raise ValueError(f"{path}: line {number} is not JSON (a record cut short?)") from None
    if not lines or not isinstance(lines[0], dict) or lines[0].get("type") != "header":
        raise ValueError(f"{path} is not a game record (no header line)")
    if missing := [field for field in HEADER_FIELDS if field not in lines[0]]:
        raise ValueError(f"{path}: the header lacks {', '.join(missing)}")
    steps = [line for line in lines if isinstance(line, dict) and line.get("type") == "step"]
    for line in steps:
        actions = line.get("actions")
        if not (isinstance(actions, list) and len(actions) == 2
                and all(isinstance(a, int) and 0 <= a < NUM_ACTIONS for a in actions)):
            raise ValueError(f"{path}: step {line.get('t')} has actions {actions!r}, not two of 0..{NUM_ACTIONS - 1}")
    ends = [line for line in lines if isinstance(line, dict) and line.get("type") == "end"]
    return lines[0], steps, (ends[0] if ends else None)


def agent_cells(kitchen: KitchenEnv) -> list[list[int]]:
    """[[x, y] of agent 0, [x, y] of agent 1] in the first kitchen of `kitchen`."""
    width = kitchen.jax_env.width
    return [[int(p % width), int(p // width)] for p in np.asarray(kitchen.states.agent_pos)[0]]


def recorded_kitchen(header: dict) -> tuple[KitchenEnv, TensorDictBase]:
    """The kitchen a record's game was played in, reset as the game started (its layout, seed and length)."""
    layout = parse_layout(header["layout"], name=header["layout_name"])
    kitchen = KitchenEnv(1, levels=layout, max_steps=header["max_steps"], seed=header["seed"])
    return kitchen, kitchen.reset()


def take_actions(kitchen: KitchenEnv, tensordict: TensorDictBase, actions: list[int]) -> TensorDictBase:
    """One recorded step: both agents' `actions` from `tensordict`; returns the tensordict of the next step."""
    tensordict.set(("agents", "action"), torch.tensor([actions]))
    return step_mdp(kitchen.step(tensordict))


def replayed_states(path: str | Path) -> tuple[dict, list[dict], dict, list[State]]:
    """(header, step lines, end line, states): a record's game rebuilt through the JAX env, every step's positions
    and score checked (a ValueError at the first step that differs, or for a game that never ended: no end line, the
    record was cut or its server killed). `states` holds the state before each step and the last one after it,
    unbatched, as NumPy arrays."""
    header, steps, end = read_record(path)
    if end is None:
        raise ValueError(f"{path}: the game never ended (no end line after {len(steps)} steps): the record is cut")
    kitchen, td = recorded_kitchen(header)

    def current() -> State:
        return jax.tree_util.tree_map(lambda leaf: np.asarray(leaf)[0], kitchen.states)

    states, score = [current()], 0
    for line in steps:
        td = take_actions(kitchen, td, line["actions"])
        score += int(td["deliveries"][0, 0])
        if agent_cells(kitchen) != line["positions"] or score != line["score"]:
            raise ValueError(f"{path}: step {line['t']} differs: recorded positions {line['positions']} score "
                             f"{line['score']}, replayed {agent_cells(kitchen)} score {score}")
        states.append(current())
    return header, steps, end, states
