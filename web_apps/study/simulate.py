"""`kitchen-study simulate CONFIG --participants N`: a pilot by proxies. N simulated participants go through the
study's own server, from its link to its completion code, into a study folder that `kitchen-study analyse` and
`kitchen-study power` read like any other.

The server is `kitchen-study run` of a copy of the config (STUDY_DIR/study.yaml: its `out_dir` the simulation's
folder and, unless `--keep-pace`, its pace `turns`, so that the kitchen steps as soon as a participant's key arrives,
the fastest the server allows), in a subprocess on a free port held from before its start (`--fd`), its log in
STUDY_DIR/server.log. Each participant (`ProxyParticipant`, on a thread of its own, `--parallel` at once) speaks the
pages' protocol (`web_apps.study.client.Participant`: HTTP for the stages, a WebSocket for the games).

Its keys. Each state the server sends (the cells' kinds and contents, the cooks' cells, facings and hands, the step
and the steps left) is rebuilt as the kitchen's `State` and read through the env's own observation function
(`observation_of`), and a partner-like policy samples the participant's key from its seat's view:

    a human proxy   on a kitchen where `--proxy` (default runs/bc_{kitchen}/seed0, `kitchen-humans train`'s
                    behaviour-cloned proxies; `{kitchen}`: the kitchen's name) names a run that exists, the kitchen
                    told by the state's grid;
    a stand-in      elsewhere: the scripted cook of a convention of the shipped zoo (configs/zoo/zoo.yaml), one of its
                    training conventions drawn per participant (`--stand-in NAME`: that one for every participant).

A participant's skill is its noise, drawn once from U(0, MAX_NOISE): the probability of a key drawn uniformly instead
of the policy's (a stand-in's convention plays with this noise in place of its own). At the config's real-time pace
(`--keep-pace`) a planner thread picks the keys, off the server's clock: every state is answered at once with the
last key planned, so a tick never waits for a plan and a plan slower than a tick leaves its key in place.

Its answers, the response model. For a Likert scale of K points, with half-range h = (K - 1) / 2:

    each item       round((K + 1) / 2 + h * (SLOPE * (d - r) + leaning + e)), clipped to 1..K: d the deliveries
                    of the game just played; r what the participant's earlier games (its practice included)
                    delivered per step, times this game's steps (r = d for a first game without practice);
                    leaning ~ N(0, LEANING_SD), the participant's own, drawn once; e ~ N(0, ANSWER_SD) per answer
    forced choice   the one of the last two games that delivered more, with probability CHOICE_P, else the other;
                    on a tie either, half and half

SLOPE = 0.15, LEANING_SD = 0.25 and ANSWER_SD = 0.35 (in half-ranges), CHOICE_P = 0.8, MAX_NOISE = 0.3: on a 5-point
scale 0.3 points per soup above what the participant is used to, a leaning of sd 0.5 points and a noise of sd 0.7
points per answer. A participant's draws (noise, leaning, stand-in, keys, answers) come from `--seed` and its index;
the row of the design it takes is its order of arrival at the server, and the partners' actions are the server's.
Beside the database and the records: study.yaml, server.log and proxies.json (each participant's
id, noise, leaning, the policy of each kitchen it played, its deliveries and the answers it posted).

Proxies are not people: a pilot by proxies tries the study's machinery end to end and gives the power analysis a first
guess; the real pilot's games replace it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random
import secrets
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import torch
import yaml
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from jax_env import NUM_ACTIONS, State
from jax_env.observation import get_obs
from torch_kitchen.keys import LOGITS, OBSERVATION
from torch_kitchen.models import ActorCritic
from torch_kitchen.partners.conventions import STRANGER, TRAIN, ZOO_FILE, Convention, ConventionError, load_zoo
from torch_kitchen.partners.scripted_cook import scripted_actor_critic
from trainers.checkpoint import CheckpointError
from web_apps.play.game import ACTIONS, Partner, check_fits, load_partner
from web_apps.study.assignment import GAME, PLAYED, PRACTICE
from web_apps.study.client import (
    Participant,
    ProtocolError,
    ServerTransport,
    Socket,
    base_url,
    loopback_listener,
    start_server,
    wait_until_serving,
)
from web_apps.study.config import (
    FORCED_CHOICE,
    SCRIPTED_COOK,
    StudyConfig,
    StudyError,
    kitchen_of,
    load_study,
    partner_key,
)
from web_apps.study.database import DATABASE

PROXY = "runs/bc_{kitchen}/seed0"  # kitchen-humans train's proxies, fitted on the train split
MAX_NOISE = 0.3  # a participant's noise is drawn from U(0, MAX_NOISE)
SLOPE = 0.15  # half-ranges of the Likert scale per soup above what the participant is used to
LEANING_SD = 0.25  # half-ranges: how differently participants use the scale
ANSWER_SD = 0.35  # half-ranges: each answer's own noise
CHOICE_P = 0.8  # the forced choice picks the game that delivered more with this probability
SIMULATED_CONFIG, SERVER_LOG, PROXIES = "study.yaml", "server.log", "proxies.json"
KEYS = {index: name for name, index in ACTIONS.items()}  # an action's index -> the key the pages send for it


class SimulationError(RuntimeError):
    """The simulation could not run its server to the end; the message says why in one line."""


# ------------------------------------------------------------------------------------------- observations
_OBSERVE = jax.jit(get_obs)


def observation_of(view: dict) -> torch.Tensor:
    """uint8 [1, 2, H, W, 26]: both seats' observations of a state message (`web_apps.play.game.Game.view`), as the
    env makes them: the message's kitchen rebuilt as a `State` and read through the env's observation function."""
    width = view["width"]
    state = State(grid=jnp.asarray(view["kinds"], jnp.uint8), contents=jnp.asarray(view["contents"], jnp.uint8),
                  agent_pos=jnp.asarray([y * width + x for x, y in view["positions"]], jnp.int32),
                  agent_dir=jnp.asarray(view["directions"], jnp.int32),
                  agent_inv=jnp.asarray(view["holding"], jnp.int32), step=jnp.asarray(view["t"], jnp.int32))
    return torch.from_numpy(np.array(_OBSERVE(state, view["t"] + view["time_left"])))[None]


def grid_key(kinds) -> tuple:
    """What tells a kitchen from another in a state message: its cells' kinds."""
    grid = np.asarray(kinds, dtype=np.uint8)
    return grid.shape, grid.tobytes()


# ----------------------------------------------------------------------------------------- response model
def likert_answer(delivered: int, reference: float, leaning: float, points: int, rng: random.Random) -> int:
    """One Likert answer, 1..`points`, after a game that delivered `delivered` where the participant is used to
    `reference` (the module docstring's response model)."""
    half = (points - 1) / 2
    latent = (points + 1) / 2 + half * (SLOPE * (delivered - reference) + leaning + rng.gauss(0, ANSWER_SD))
    return min(points, max(1, math.floor(latent + 0.5)))


def forced_choice_answer(previous: int, current: int, positions: list[int], rng: random.Random) -> int:
    """The chosen one of `positions` (the last two games', in order) after they delivered `previous` and `current`:
    the one that delivered more with probability CHOICE_P; on a tie either."""
    if previous == current:
        return rng.choice(positions)
    better, worse = (positions[0], positions[1]) if previous > current else (positions[1], positions[0])
    return better if rng.random() < CHOICE_P else worse


def reference_of(earlier: list[tuple[int, int]], delivered: int, steps: int) -> float:
    """What the participant is used to in a game of `steps` steps: its `earlier` games' (deliveries, steps)
    deliveries per step times `steps`; `delivered` itself where it has played none."""
    played = sum(length for _, length in earlier)
    return sum(soups for soups, _ in earlier) / played * steps if played else float(delivered)


# ---------------------------------------------------------------------------------------- who plays
class Proxy(NamedTuple):
    path: str
    actor_critic: ActorCritic


class Kitchens:
    """The study's kitchens as a state message shows them (by their grid), each with its human proxy where `proxy`
    (a run's path, `{kitchen}` its name; None: `PROXY` where it exists) names one; a StudyError where one is there
    but cannot play, or where an explicit `proxy` names none."""

    def __init__(self, config: StudyConfig, proxy: str | None = None):
        names = list(dict.fromkeys([*([config.practice_kitchen] if config.practice_games else []), *config.kitchens]))
        layouts = {name: kitchen_of(name, config.seed) for name in names}
        self.names = {}
        for name, layout in layouts.items():
            self.names.setdefault(grid_key(layout.grid), name)
        self.proxies: dict[str, Proxy] = {}
        loaded: dict[str, Partner] = {}  # one load per run, where `proxy` names one for every kitchen
        for name, layout in layouts.items():
            path = partner_key(proxy or PROXY, name)
            if not Path(path).exists():
                continue
            try:
                if path not in loaded:
                    loaded[path] = load_partner(path, config.device)
                check_fits(loaded[path], layout)
            except (CheckpointError, ValueError) as error:
                raise StudyError(f"the human proxy {path}: {error}") from None
            if loaded[path].actor_critic.env_transforms():
                raise StudyError(f"the human proxy {path} carries a state from step to step (an LSTM's or a partner "
                                 "context), which a simulated participant does not keep: give a feed-forward one")
            self.proxies[name] = Proxy(path, loaded[path].actor_critic)
        if proxy is not None and not self.proxies:
            raise StudyError(f"--proxy {proxy}: no run there for any of the study's kitchens ({', '.join(names)})")
        self.without_proxy = [name for name in names if name not in self.proxies]

    def name_of(self, view: dict) -> str | None:
        """The study's kitchen a state message is in (None: one of none of its grids, e.g. a generated one)."""
        return self.names.get(grid_key(view["kinds"]))


def stand_in_conventions(name: str | None) -> list[Convention]:
    """The conventions the stand-ins are drawn from: the zoo's training ones, or the one `name`d (a convention of the
    zoo, strangers included, or `scripted_cook`: the default convention)."""
    if name == SCRIPTED_COOK:
        return [Convention()]
    try:
        zoo = load_zoo(ZOO_FILE)
        return [zoo.convention(name, splits=(TRAIN, STRANGER))] if name else zoo.training
    except (ConventionError, OSError) as error:
        raise StudyError(f"--stand-in: {error}" if name else f"the stand-ins' conventions: {error}") from None


@dataclasses.dataclass(frozen=True)
class Draw:
    """A simulated participant as drawn from the seed: its noise (its skill), its leaning on the Likert scale, its
    stand-in's convention, and the seed of its keys and answers."""

    index: int
    noise: float
    leaning: float
    stand_in: Convention
    seed: int

    @property
    def external_id(self) -> str:
        return f"proxy-{self.index:04d}"


def draw_participant(index: int, seed: int, conventions: list[Convention]) -> Draw:
    """Participant `index`'s draw, the same for the same `seed` whatever else is simulated."""
    rng = random.Random(f"{seed}:proxy:{index}")
    return Draw(index, round(rng.uniform(0, MAX_NOISE), 3), round(rng.gauss(0, LEANING_SD), 3), rng.choice(conventions),
                rng.randrange(2**32))


# ------------------------------------------------------------------------------------------------ playing
def state_of(message: dict) -> dict:
    """A game's state message; a ProtocolError for anything else (the game ended early, a refused message)."""
    if message.get("type") != "state":
        raise ProtocolError(f"the game sent {message.get('type')!r} instead of its state: {message.get('reason')}")
    return message


def action_message(key: str) -> str:
    return json.dumps({"type": "action", "action": key})


def play_in_turns(socket: Socket, view: dict, plan: Callable[[dict], str]) -> dict:
    """A turns-paced game to its end, each state answered with the key planned on it (the kitchen waits for it);
    returns the last state."""
    while not view["over"]:
        socket.send(action_message(plan(view)))
        view = state_of(socket.receive())
    return view


def play_in_time(socket: Socket, view: dict, plan: Callable[[dict], str]) -> dict:
    """A real-time game to its end, planned off the server's clock: every state is answered at once with the last
    key planned, and a planner thread, when free, plans on it and sends its key as soon as it has one (the server
    steps with the latest key of each tick). A tick thus never waits for a plan nor goes without a key."""
    sending, last = threading.Lock(), ["stay"]

    def send(key: str) -> None:
        with sending:  # the planner's thread and this one share the socket
            socket.send(action_message(key))

    def plan_and_send(state: dict) -> None:
        last[0] = plan(state)
        send(last[0])

    with ThreadPoolExecutor(1) as planner:
        planning = None
        while not view["over"]:
            send(last[0])
            if planning is None or planning.done():
                if planning is not None:
                    planning.result()  # a plan's error is the game's
                planning = planner.submit(plan_and_send, view)
            view = state_of(socket.receive())
    return view


class ProxyParticipant(Participant):
    """A simulated participant whose keys come from a partner-like policy (a human proxy, else its stand-in) with its
    drawn noise, and whose answers come from the response model (the module docstring)."""

    def __init__(self, transport, token: str, draw: Draw, kitchens: Kitchens, realtime: bool = False):
        super().__init__(transport, draw.external_id, token)
        self.draw, self.kitchens, self.realtime = draw, kitchens, realtime
        # The participant's noise replaces the convention's own: one noise, applied to every policy alike (`key_for`).
        self.stand_in = scripted_actor_critic(dataclasses.replace(draw.stand_in, noise=0.0))
        self.keys, self.answering = random.Random(f"{draw.seed}:keys"), random.Random(f"{draw.seed}:answers")
        self.played: list[tuple[str, int, int]] = []  # (kind, deliveries, steps) of each game, in order
        self.policies: dict[str, str] = {}  # kitchen -> the policy that played there
        self.last_view: dict | None = None

    def policy_for(self, view: dict) -> ActorCritic:
        kitchen = self.kitchens.name_of(view)
        proxy = self.kitchens.proxies.get(kitchen)
        self.policies[kitchen or "another kitchen"] = (f"proxy {proxy.path}" if proxy
                                                       else f"stand-in {self.draw.stand_in.name}")
        return proxy.actor_critic if proxy else self.stand_in

    def key_for(self, view: dict, actor_critic: ActorCritic) -> str:
        """The key of the participant's seat: the policy's action on its observation, or with probability its noise
        one drawn uniformly."""
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            acted = actor_critic.actor(TensorDict({OBSERVATION: observation_of(view)}, batch_size=[1]))
        probabilities = torch.softmax(acted[LOGITS][0, view["seat"]].float(), -1)
        probabilities = (1 - self.draw.noise) * probabilities + self.draw.noise / NUM_ACTIONS
        return KEYS[self.keys.choices(range(NUM_ACTIONS), weights=probabilities.tolist())[0]]

    def play(self, stage: int, steps: int | None = None) -> dict:
        """Plays the game of `stage` to its end (`steps` is not taken: a proxy leaves no game open); returns its
        last state."""
        self.socket, view = self.open_game(stage)
        try:
            view = state_of(view)
            actor_critic = self.policy_for(view)
            play = play_in_time if self.realtime else play_in_turns
            self.last_view = play(self.socket, view, lambda state: self.key_for(state, actor_critic))
        finally:
            self.socket.close()
        return self.last_view

    def take_stage(self, conditions: list[str] | None = None) -> str:
        kind = super().take_stage(conditions)
        if kind in PLAYED:
            self.played.append((kind, self.last_view["score"], self.last_view["t"]))
        return kind

    def answers(self, where: dict, conditions: list[str] | None = None) -> dict[str, int]:
        """The response model's answers to a questions stage (`where`: its position and what it asks)."""
        position, asks = where["position"], where["asks"]
        practice = sum(kind == PRACTICE for kind, _, _ in self.played)
        games = [(soups, steps) for kind, soups, steps in self.played if kind == GAME]
        delivered, steps = games[position]
        reference = reference_of([(soups, length) for _, soups, length in self.played[:practice + position]],
                                 delivered, steps)
        answers = {item: allowed[likert_answer(delivered, reference, self.draw.leaning, len(allowed),
                                               self.answering) - 1]
                   for item, allowed in asks.items() if item != FORCED_CHOICE}
        if FORCED_CHOICE in asks:
            answers[FORCED_CHOICE] = forced_choice_answer(games[position - 1][0], delivered, asks[FORCED_CHOICE],
                                                          self.answering)
        return answers

    def summary(self) -> dict:
        """Who the participant was, what it delivered and what it answered (a row of proxies.json)."""
        return {"participant": self.external_id, "noise": self.draw.noise, "leaning": self.draw.leaning,
                "policies": self.policies,
                "practice_deliveries": [soups for kind, soups, _ in self.played if kind == PRACTICE],
                "deliveries": [soups for kind, soups, _ in self.played if kind == GAME],
                "answers": {str(stage): answers for stage, answers in self.answered.items()}}


# ------------------------------------------------------------------------------------------------ the pilot
def simulation_folder(config: StudyConfig, out: str | None) -> Path:
    """The simulated study's folder: `out`, or the study's own folder's name with "-simulated"; a StudyError where it
    is the study's own folder or already holds a study."""
    folder = Path(out) if out else config.folder.with_name(f"{config.folder.name}-simulated")
    if folder.resolve() == config.folder.resolve():
        raise StudyError(f"{folder} is the study's own folder: a simulation writes into another (--out)")
    if (folder / DATABASE).exists():
        raise StudyError(f"{folder} already holds a study: give another --out, or remove it")
    return folder


def write_simulated_config(config: StudyConfig, folder: Path, keep_pace: bool, max_steps: int | None = None
                           ) -> tuple[StudyConfig, Path]:
    """The config the simulation's server runs (the study's, in `folder`, paced by turns unless `keep_pace`, its
    games and practice games at most `max_steps` steps where given), and where it is written."""
    served = dataclasses.replace(config, out_dir=str(folder.resolve()), pace=config.pace if keep_pace else "turns")
    if max_steps is not None:
        served = dataclasses.replace(served, max_steps=min(config.max_steps, max_steps),
                                     practice_steps=min(config.practice_steps, max_steps))
    path = folder / SIMULATED_CONFIG
    path.write_text(yaml.safe_dump(served.to_dict(), sort_keys=False), encoding="utf-8")
    return served, path


@contextmanager
def study_server(config_path: Path, folder: Path) -> Iterator[tuple[str, str]]:
    """`kitchen-study run` of `config_path` in a subprocess started here (where the config's relative paths start),
    its log in `folder`, stopped on the way out: yields its base URL and its participants' token."""
    token, listener, log = secrets.token_urlsafe(16), loopback_listener(), folder / SERVER_LOG
    base = base_url(listener)
    server = start_server(config_path.resolve(), listener, token, log, cwd=Path.cwd())
    try:
        try:
            wait_until_serving(server, ServerTransport(base), token, log, timeout_s=300)
        except ProtocolError as error:
            raise SimulationError(f"{str(error).splitlines()[0]} (its log: {log})") from None
        yield base, token
    finally:
        server.terminate()
        server.wait(timeout=60)


def visit(base: str, token: str, draw: Draw, kitchens: Kitchens, config: StudyConfig
          ) -> tuple[ProxyParticipant, str | None, float]:
    """One participant's whole visit: (the participant, why it did not finish or None, its seconds)."""
    start = time.monotonic()
    transport = ServerTransport(base)
    person = ProxyParticipant(transport, token, draw, kitchens, realtime=config.pace == "realtime")
    failure = None
    try:
        person.enter(config.participant_param)
        while person.take_stage() != "complete":
            pass
    except Exception as error:  # noqa: BLE001 - reported with the others', not raised on a thread
        failure = f"{type(error).__name__}: {error}"
    finally:
        transport.http.close()
    return person, failure, time.monotonic() - start


def visit_all(base: str, token: str, draws: list[Draw], kitchens: Kitchens, config: StudyConfig, parallel: int
              ) -> list[tuple[ProxyParticipant, str | None]]:
    """Every participant's visit, `parallel` at once, a line printed as each ends."""
    printing, ended = threading.Lock(), [0]

    def one(draw: Draw) -> tuple[ProxyParticipant, str | None]:
        person, failure, seconds = visit(base, token, draw, kitchens, config)
        with printing:
            ended[0] += 1
            print(f"  [{ended[0]}/{len(draws)}] {visit_line(person, failure, seconds)}", flush=True)
        return person, failure

    with ThreadPoolExecutor(parallel) as pool:
        return list(pool.map(one, draws))


def visit_line(person: ProxyParticipant, failure: str | None, seconds: float) -> str:
    if failure is not None:
        return f"{person.external_id} did not finish ({seconds:.0f} s): {failure[:300]}"
    summary = person.summary()
    likert = [np.mean([value for item, value in answers.items() if item != FORCED_CHOICE])
              for answers in person.answered.values()]
    return (f"{person.external_id} finished in {seconds:.0f} s: noise {person.draw.noise:.2f}, leaning "
            f"{person.draw.leaning:+.2f}, keys from {', '.join(sorted(set(person.policies.values())))}; delivered "
            f"{' '.join(map(str, summary['practice_deliveries'])) or '-'} in practice, "
            f"{' '.join(map(str, summary['deliveries']))} in its games; mean Likert answer after each "
            f"{' '.join(f'{mean:.1f}' for mean in likert)}")


def plan_lines(config: StudyConfig, served: StudyConfig, folder: Path, participants: int, seed: int,
               kitchens: Kitchens, stand_in: str | None) -> list[str]:
    """What the simulation will do, before it starts: its folder, pace, keys and answers."""
    if served.pace == "realtime":
        pace = f"the config's real time, a step every {config.tick_ms} ms (--keep-pace)"
    elif config.pace == "turns":
        pace = "turns, the config's own: a step as soon as a key arrives"
    else:
        pace = (f"turns, a step as soon as a key arrives: the config's real-time {config.tick_ms}-ms tick is "
                "overridden for the simulation (--keep-pace keeps it)")
    proxied: dict[str, list[str]] = {}  # a proxy's path -> the kitchens it plays
    for kitchen, proxy in kitchens.proxies.items():
        proxied.setdefault(proxy.path, []).append(kitchen)
    keys = [f"on {', '.join(names)} the human proxy {path}" for path, names in proxied.items()]
    if kitchens.without_proxy:
        convention = (f"convention {stand_in}" if stand_in
                      else f"a training convention of {ZOO_FILE}, drawn per participant")
        keys.append(f"on {', '.join(kitchens.without_proxy)} a stand-in, the scripted cook of {convention}")
    lines = [f"kitchen-study: simulating {participants} participants of study {config.name} into {folder}/ "
             f"(seed {seed})", f"  pace: {pace}",
             f"  keys: {'; '.join(keys)}; each participant's noise (its skill: the probability of a key drawn "
             f"uniformly) from U(0, {MAX_NOISE:g})",
             "  answers: the response model of web_apps/study/simulate.py (docs/study.md, \"A pilot by proxies\")"]
    if participants % config.block_size:
        lines.append(f"  {participants} participants fill no whole number of the design's blocks of "
                     f"{config.block_size}: its counts will be unequal")
    return lines


def run_pilot(config_path: str | Path, participants: int, out: str | None = None, seed: int = 0,
              proxy: str | None = None, stand_in: str | None = None, parallel: int = 4,
              keep_pace: bool = False, max_steps: int | None = None) -> int:
    """`kitchen-study simulate`: `participants` simulated participants through the study of `config_path`'s server
    into a study folder (the module docstring); returns 0. A StudyError for bad input, a SimulationError where the
    server would not serve or a participant did not finish (its folder then holds the others)."""
    config = load_study(config_path)
    folder = simulation_folder(config, out)
    kitchens = Kitchens(config, proxy)
    conventions = stand_in_conventions(stand_in) if stand_in or kitchens.without_proxy else [Convention()]
    draws = [draw_participant(index, seed, conventions) for index in range(participants)]
    folder.mkdir(parents=True, exist_ok=True)
    served, served_path = write_simulated_config(config, folder, keep_pace, max_steps)
    print("\n".join(plan_lines(config, served, folder, participants, seed, kitchens, stand_in)), flush=True)
    start = time.monotonic()
    with study_server(served_path, folder) as (base, token):
        visits = visit_all(base, token, draws, kitchens, served, parallel)
    rows = [{**person.summary(), **({"failure": failure} if failure else {})} for person, failure in visits]
    (folder / PROXIES).write_text(json.dumps(rows, indent=1), encoding="utf-8")
    failed = sum(failure is not None for _, failure in visits)
    print(f"kitchen-study: {participants - failed} of {participants} simulated participants finished in "
          f"{time.monotonic() - start:.0f} s, into {folder}/ ({SIMULATED_CONFIG}: the config its server ran; "
          f"{PROXIES}: each participant's draw, deliveries and answers; {SERVER_LOG})\n"
          "Proxies are not people: their study tries the machinery and gives the power analysis a first guess, "
          "which the real pilot's games replace. Next:\n"
          f"  kitchen-study analyse {folder}    # the report: {folder / 'analysis' / 'report.md'}\n"
          f"  kitchen-study power {folder}      # participants needed, from these games", flush=True)
    if failed:
        raise SimulationError(f"{failed} of {participants} simulated participants did not finish (above; the "
                              f"server's log: {folder / SERVER_LOG})")
    return 0
