"""One game of a person with a partner: the kitchen, the partner's policy, the record, and the replay.

A `Game` holds a one-kitchen `KitchenEnv` and a partner (a trained team, the scripted cook or a random agent)
acting on the seat the person does not play, through the same actor that evaluation seats. Each `step(action)`
is one tick: the partner samples its action from its own observation (its LSTM state and E3T context carried by
the env's transforms), the person's action fills the other seat, the kitchen steps, and one line is appended to
the game's JSON Lines record and flushed, so a killed server loses at most the step in flight.

Record (one file per game): a header line {"type": "header", "version", "layout": text grid, "layout_name", "seed",
"max_steps", "seat", "partner", "checkpoint", "checkpoint_sha256", "tick_ms", "mode", "started"}; then per step {"type":
"step", "t", "actions": [a0, a1], "reward", "deliveries", "score", "positions": [[x, y], [x, y]], "ms"}; then {"type":
"end", "reason", "score", "steps"}. `replay(path)` rebuilds the game through the JAX env from the header and the
recorded actions and checks every step's positions and score; `kitchen-humans import`
(`trainers.humans.command.games_from_records`) turns records into the human-games dataset for behaviour cloning.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections import defaultdict
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import jax
import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from jax_env import EAST, INTERACT, NORTH, NUM_ACTIONS, SOUTH, STAY, WEST, Layout
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.models import ActorCritic
from torch_kitchen.models.acting import sampling_actor
from torch_kitchen.partners.scripted_cook import scripted_actor_critic
from torch_kitchen.records import agent_cells, replayed_states
from trainers.evaluation import load_team

ACTIONS = {"up": NORTH, "down": SOUTH, "right": EAST, "left": WEST, "stay": STAY, "interact": INTERACT}
SCRIPTED, RANDOM = "scripted cook", "random agent"
RECORD_FORMAT = 1


def software_version() -> str:
    try:
        return version("infinite-kitchen")
    except PackageNotFoundError:
        return "unknown"


@dataclasses.dataclass
class Partner:
    """Who plays the other seat: a name, its actor-critic, its kitchen size (None: any) and where it came from."""

    name: str
    actor_critic: ActorCritic
    obs_shape: tuple[int, int, int] | None = None
    checkpoint: str | None = None
    sha256: str | None = None


def random_actor_critic() -> ActorCritic:
    """Uniform over the six actions for both seats."""
    logits = TensorDictModule(lambda obs: torch.zeros(*obs.shape[:-3], NUM_ACTIONS, device=obs.device),
                              in_keys=[("agents", "observation")], out_keys=[("agents", "logits")])
    return ActorCritic(actor=sampling_actor(logits), critic=logits, recurrent=False)


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_partner(name: str, device: str = "cpu") -> Partner:
    """The scripted cook, the random agent, or the trained team of a run directory or checkpoint (CheckpointError
    says why one cannot play)."""
    if name == SCRIPTED:
        return Partner(SCRIPTED, scripted_actor_critic())
    if name == RANDOM:
        return Partner(RANDOM, random_actor_critic())
    team = load_team(name, device)
    return Partner(team.name, team.actor_critic, team.obs_shape, team.checkpoint, file_sha256(Path(team.checkpoint)))


def check_fits(partner: Partner, layout: Layout) -> None:
    """ValueError unless the partner's networks were built for the kitchen's size."""
    if partner.obs_shape is not None and tuple(partner.obs_shape[:2]) != layout.shape:
        raise ValueError(f"{partner.name} was trained on {partner.obs_shape[0]}x{partner.obs_shape[1]} kitchens and "
                         f"cannot play a {layout.height}x{layout.width} one; pick a kitchen of its size")


class Recorder:
    """A game's JSON Lines record, each line flushed as it is written."""

    def __init__(self, path: Path, header: dict):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file = open(path, "w", encoding="utf-8")
        self.write({"type": "header", **header})

    def write(self, line: dict) -> None:
        self._file.write(json.dumps(line) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


class Game:
    """A person in seat `seat` with `partner` in the other, on `layout`, recorded to `record_path`."""

    def __init__(self, layout: Layout, partner: Partner, seat: int, record_path: Path, seed: int = 0,
                 max_steps: int = 400, tick_ms: int = 150, mode: str = "realtime", device: str = "cpu"):
        if seat not in (0, 1):
            raise ValueError(f"seat must be 0 or 1, got {seat}")
        check_fits(partner, layout)
        self.layout, self.partner, self.seat, self.max_steps = layout, partner, seat, max_steps
        self.kitchen = KitchenEnv(1, levels=layout, max_steps=max_steps, device=device, seed=seed)
        self.env = with_transforms(self.kitchen, partner.actor_critic.env_transforms())
        torch.manual_seed(seed)
        self.tensordict = self.env.reset()
        self.kitchen.precompile()  # here, not in the first tick
        self.t, self.score, self.over = 0, 0, False
        self.started = time.monotonic()
        self.recorder = Recorder(record_path, {
            "version": software_version(), "format": RECORD_FORMAT, "layout": layout.to_text(),
            "layout_name": layout.name, "seed": seed, "max_steps": max_steps, "seat": seat,
            "partner": partner.name, "checkpoint": partner.checkpoint, "checkpoint_sha256": partner.sha256,
            "tick_ms": tick_ms, "mode": mode, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        })  # fmt: skip

    def step(self, action: int) -> dict:
        """One tick with the person's `action` (an index into the six actions); returns the new `view()`."""
        [view] = step_games([self], [action])
        if isinstance(view, Exception):
            raise view
        return view

    def advance(self, acted: TensorDictBase, action: int) -> dict:
        """The tick after the partner acted (`acted`: this game's row of its forward pass): the person's `action`
        in the other seat, the kitchen's step, the record's line; returns the new `view()`."""
        actions = acted.get(("agents", "action")).clone()
        actions[0, self.seat] = action
        acted.set(("agents", "action"), actions)
        with torch.no_grad():
            stepped = self.env.step(acted)
        reward = float(stepped["next", "agents", "reward"][0, 0, 0])
        delivered = int(stepped["next", "deliveries"][0, 0])
        self.tensordict = step_mdp(stepped)
        self.t += 1
        self.score += delivered
        self.over = bool(stepped["next", "done"][0, 0])
        if self.recorder is None:  # ended while this step ran (the server stopping): the record is closed
            return self.view()
        self.recorder.write({
            "type": "step", "t": self.t, "actions": actions[0].tolist(), "reward": reward, "deliveries": delivered,
            "score": self.score, "positions": self.positions(),
            "ms": round((time.monotonic() - self.started) * 1000),
        })  # fmt: skip
        if self.over:
            self.end("finished")
        return self.view()

    def positions(self) -> list[list[int]]:
        return agent_cells(self.kitchen)

    def view(self) -> dict:
        """What the page draws: the cells, their contents, the cooks, the score and the time left."""
        # Through NumPy before indexing: indexing a JAX array dispatches an operation (80 us each).
        state = jax.tree_util.tree_map(lambda leaf: np.asarray(leaf)[0], self.kitchen.states)
        return {
            "type": "state", "width": self.layout.width, "height": self.layout.height,
            "kinds": state.grid.astype(int).tolist(), "contents": state.contents.astype(int).tolist(),
            "positions": self.positions(), "directions": state.agent_dir.astype(int).tolist(),
            "holding": state.agent_inv.astype(int).tolist(), "seat": self.seat, "score": self.score,
            "t": self.t, "time_left": self.max_steps - self.t, "over": self.over,
        }  # fmt: skip

    def end(self, reason: str) -> None:
        """Closes the record with its last line (at most once)."""
        if self.recorder is None:
            return
        self.over = True
        self.recorder.write({"type": "end", "reason": reason, "score": self.score, "steps": self.t})
        self.recorder.close()
        self.recorder = None


def step_games(games: Sequence[Game], actions: Sequence[int]) -> list[dict | Exception]:
    """One tick of each of `games`, the person's `actions[i]` in game i: the partner's forward passes for all the
    games that share it and a kitchen size (`acting_rows`; each row acts as it would alone), then each game's
    `advance`. Returns each game's new view, or the exception its tick raised (a game over, a record that cannot be
    written), so that one game's fault stays its own."""
    results: list[dict | Exception | None] = [None] * len(games)
    sharing: dict[tuple, list[int]] = defaultdict(list)
    for index, game in enumerate(games):
        if game.over:
            results[index] = RuntimeError("the game is over")
        else:
            sharing[id(game.partner.actor_critic), game.layout.shape].append(index)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for indices in sharing.values():
            rows = acting_rows([games[index] for index in indices])
            for index, row in zip(indices, rows):
                try:
                    results[index] = games[index].advance(row, actions[index])
                except Exception as error:  # noqa: BLE001 - handed to that game's caller
                    results[index] = error
    return results


ROUND_BATCH = 8  # games in one forward pass of their partner


def acting_rows(games: Sequence[Game]) -> list[TensorDictBase]:
    """Each game's tensordict with its partner's action (the partner and kitchen size of all of them): forward
    passes of `ROUND_BATCH` games each, the last padded with copies of its last game. A pass of one batch size, so
    that a jitted partner (the scripted cook) compiles once at the server's warm-up rather than for each number of
    games a round happens to hold (a second or more each, while every game waits)."""
    actor = games[0].partner.actor_critic.actor
    rows = []
    for first in range(0, len(games), ROUND_BATCH):
        chunk = games[first:first + ROUND_BATCH]
        # What the actor reads (a game's first tick holds fewer entries than its later ones).
        inputs = [game.tensordict.select(*actor.in_keys, strict=False) for game in chunk]
        acted = actor(torch.cat(inputs + inputs[-1:] * (ROUND_BATCH - len(chunk))))
        rows += [game.tensordict.update(acted[row:row + 1]) for row, game in enumerate(chunk)]
    return rows


# --------------------------------------------------------------------------------------------- records
def replay(path: str | Path, gif: str | Path | None = None) -> dict:
    """Replays a record through the JAX env (`replayed_states`): every step's positions and score must match.
    Returns a summary; raises ValueError at the first step that differs, and for a game that never ended.
    `gif`: also write the game as an animated GIF."""
    _, steps, end, states = replayed_states(path)
    if gif is not None:
        from jax_env.render import write_gif

        write_gif(states, str(gif))
    return {"steps": len(steps), "score": steps[-1]["score"] if steps else 0, "ended": end["reason"]}
