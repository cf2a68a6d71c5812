"""Conventions: how a scripted cook plays, as data. A convention is a named, typed config; the cook
(`torch_kitchen.partners.scripted_cook.ScriptedCook`) reads it, so cooks of different conventions are one class.

    preferences       event -> weight in [-1, 1]: goals that lead to the event are taken earlier (> 0) or later
                      (< 0); ZSC-Eval's evaluation partners are such weight vectors, with at most three non-zero
    role              "both"; "loader": takes plates and soups only where no onion can go in a pot; "server": takes
                      onions only where no plate or soup can be taken; "west_loads": the work split by side, the cook
                      west of its partner (north where they share a column) a loader and the other a server, so two
                      cooks of the convention always split it while beside "west_serves", the mirror, both take the
                      same part; "seat0_loads" and its mirror "seat0_serves": the split by seat, the cook in seat
                      0 a loader wherever the two stand (a split by side changes hands as the cooks pass each other)
    strict_role       False: a loader or server does the other part of the work while none of its own can be done;
                      True: it waits for its own instead
    handover          "when_needed": puts an item on a counter the partner can reach where it cannot carry it to its
                      goal itself; "prefer": also where the partner is nearer that goal; "avoid": never
    move_order        the move taken among equally short ones (a permutation of "NSEW")
    goal_temperature  0: the best goal it can reach; > 0: a goal drawn with probability ~ exp(score / temperature)
    move_temperature  0: a shortest way; > 0: a move drawn with probability ~ exp(-steps left after it / temperature)
    noise             the probability of an action drawn uniformly instead

The default convention is the scripted cook of every earlier run, action for action. `draw_convention` draws one
from a seed, as the zoo (`trainers.zoo`) does. A `Zoo` is a file of conventions split into those to train with and
the held-out strangers (`load_zoo`; the project ships `ZOO_FILE`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import random
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from jax_env import GeneratorConfig
from torch_kitchen.events import EVENTS

ROLES = ("both", "loader", "server", "west_loads", "west_serves", "seat0_loads", "seat0_serves")
# The roles a convention plays as the first cook of the two and as the second: the first by position (west, or north
# in one column) for a split by side, the cook in seat 0 for a split by seat.
SIDES = {"west_loads": ("loader", "server"), "west_serves": ("server", "loader")}
SEATS = {"seat0_loads": ("loader", "server"), "seat0_serves": ("server", "loader")}
SPLITS = {**SIDES, **SEATS}
HANDOVERS = ("when_needed", "prefer", "avoid")
MOVE_ORDER = "NSEW"  # the move a cook takes where several are equally short: the first of them in this order
MAX_PREFERENCES = 3  # ZSC-Eval's partners: at most three events with a non-zero weight


# The knobs added after the first zoos were drawn: a fingerprint counts them only where they differ from their default.
LATER_KNOBS = ("strict_role",)


class ConventionError(ValueError):
    """A convention that no cook can play; the message says what is allowed."""


@dataclass(frozen=True)
class Convention:
    """How a scripted cook plays (see the module docstring); `Convention()` is the scripted cook of earlier runs."""

    name: str = "scripted_cook"
    preferences: dict[str, float] = field(default_factory=dict)
    role: str = "both"
    strict_role: bool = False
    handover: str = "when_needed"
    move_order: str = MOVE_ORDER
    goal_temperature: float = 0.0
    move_temperature: float = 0.0
    noise: float = 0.0

    def __post_init__(self):
        where = f"convention {self.name!r}"
        unknown = sorted(set(self.preferences) - set(EVENTS))
        if unknown:
            raise ConventionError(f"{where}: unknown event {', '.join(map(repr, unknown))}; events: "
                                  f"{', '.join(EVENTS)}")
        outside = {event: weight for event, weight in self.preferences.items() if not -1 <= weight <= 1}
        if outside:
            raise ConventionError(f"{where}: preference weights lie in [-1, 1], got {outside}")
        if self.role not in ROLES:
            raise ConventionError(f"{where}: unknown role {self.role!r}; roles: {', '.join(ROLES)}")
        if self.handover not in HANDOVERS:
            raise ConventionError(f"{where}: unknown handover {self.handover!r}; handovers: "
                                  f"{', '.join(HANDOVERS)}")
        if sorted(self.move_order) != sorted(MOVE_ORDER):
            raise ConventionError(f"{where}: move_order must be a permutation of {MOVE_ORDER!r}, got "
                                  f"{self.move_order!r}")
        if self.goal_temperature < 0 or self.move_temperature < 0 or not 0 <= self.noise <= 1:
            raise ConventionError(f"{where}: temperatures are >= 0 and noise lies in [0, 1], got goal_temperature="
                                  f"{self.goal_temperature}, move_temperature={self.move_temperature}, "
                                  f"noise={self.noise}")

    def weight(self, event: str) -> float:
        return float(self.preferences.get(event, 0.0))

    @property
    def roles_of_pair(self) -> tuple[str, str]:
        """Its role as the first cook of the two and as the second (the same but for a split by side or seat)."""
        return SPLITS.get(self.role, (self.role, self.role))

    @property
    def by_seat(self) -> bool:
        """Whether its split goes by seat (`SEATS`) rather than by position."""
        return self.role in SEATS

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def fingerprint(self) -> str:
        """A hash of how it plays (every parameter but its name): the same convention under another name, or drawn
        into another zoo file, has the same fingerprint."""
        values = {key: value for key, value in self.as_dict().items() if key != "name"}
        values["preferences"] = {event: weight for event, weight in sorted(self.preferences.items()) if weight}
        for knob in LATER_KNOBS:  # counted only where set, so that the fingerprints of older zoos stand
            if values[knob] == _DEFAULTS[knob]:
                del values[knob]
        text = json.dumps(values, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    @classmethod
    def from_dict(cls, values: dict) -> Convention:
        """A convention from plain values (a zoo file's entry); unknown keys refused in one line."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            name = values.get("name", "?")
            raise ConventionError(f"convention {name!r}: unknown key {', '.join(map(repr, unknown))}; keys: "
                                  f"{', '.join(sorted(known))}")
        values = dict(values)
        values["preferences"] = {str(k): float(v) for k, v in (values.get("preferences") or {}).items()}
        for key in ("goal_temperature", "move_temperature", "noise"):
            if key in values:
                values[key] = float(values[key])
        return cls(**values)

    def describe(self) -> str:
        """One line: role (strict or not), hand-overs, non-zero preferences, move order, temperatures, noise."""
        preferences = ", ".join(f"{event} {weight:+.1f}" for event, weight in self.preferences.items() if weight)
        role = f"{self.role} (strict)" if self.strict_role else self.role
        return (f"{role}, hand-overs {self.handover}, {preferences or 'no preferences'}, moves "
                f"{self.move_order}, T goal {self.goal_temperature:g} move {self.move_temperature:g}, "
                f"noise {self.noise:g}")


_DEFAULTS = Convention().as_dict()


def fingerprints(conventions: Iterable[Convention]) -> dict[str, str]:
    """{fingerprint: name} of conventions: what a run records of the conventions it trained or distilled with."""
    return {convention.fingerprint: convention.name for convention in conventions}


# How often a drawn convention takes each role, among those a draw allows: the work split by side or seat is the
# convention of a pair (a cook of it beside its own kind splits the work; beside the mirror both take one part), so it
# is drawn most, and strict (`strict_role`) with probability STRICT_SIDES, where a mismatched split costs deliveries.
ROLE_WEIGHTS = {"both": 2, "loader": 1, "server": 1, "west_loads": 3, "west_serves": 3, "seat0_loads": 3,
                "seat0_serves": 3}
STRICT_SIDES = 0.75


def draw_convention(rng: random.Random, name: str, roles: Sequence[str] = ROLES) -> Convention:
    """A convention drawn from `rng`: one to three preferred or avoided events, a role among `roles` (by
    `ROLE_WEIGHTS`; a split by side strict or not), a hand-over habit, a move order, and a little irrationality (a
    third of them plan without temperatures, as the scripted cook). With roles ("both", "loader", "server") it draws
    what it drew before the split by side existed, convention for convention."""
    events = rng.sample(EVENTS, rng.randint(1, MAX_PREFERENCES))
    preferences = {event: round(rng.choice((-1, 1)) * rng.uniform(0.3, 1.0), 2) for event in events}
    role = rng.choices(list(roles), weights=[ROLE_WEIGHTS[role] for role in roles])[0]
    strict = role in SPLITS and rng.random() < STRICT_SIDES
    handover = rng.choices(HANDOVERS, weights=(2, 1, 1))[0]
    order = list(MOVE_ORDER)
    rng.shuffle(order)
    rational = rng.random() < 1 / 3
    return Convention(
        name=name, preferences=preferences, role=role, strict_role=strict, handover=handover,
        move_order="".join(order),
        goal_temperature=0.0 if rational else round(rng.choice((0.0, 0.5, 1.0, 2.0)), 2),
        move_temperature=0.0 if rational else round(rng.choice((0.0, 0.5, 1.0)), 2),
        noise=0.0 if rational else round(rng.choice((0.0, 0.02, 0.05, 0.1)), 2),
    )


# ------------------------------------------------------------------------------------------------------ zoo
ZOO_FILE = "configs/zoo/zoo.yaml"  # the zoo the project ships: its strangers are held out of every shipped config
TRAIN, STRANGER = "train", "stranger"
ZOO_HEADER = "# Written by `kitchen-zoo draw` (trainers/zoo.py): the conventions, their split and what they did.\n"


@dataclass
class ZooMember:
    """One convention of a zoo: its split ("train" or "stranger") and what it did with itself on the zoo's levels:
    mean deliveries, the share of levels it cooked on, mean events per episode and seat."""

    convention: Convention
    split: str
    self_play: float
    cooked: float
    events: dict[str, float]

    @property
    def name(self) -> str:
        return self.convention.name


@dataclass
class Zoo:
    """Conventions drawn from `seed` and kept for their diversity, with the kitchens they were measured in."""

    seed: int
    kitchen_size: int
    generator: dict
    members: list[ZooMember]
    drawn: int = 0
    levels: int = 0
    similarity: dict[str, float] = field(default_factory=dict)

    def split(self, split: str) -> list[Convention]:
        return [member.convention for member in self.members if member.split == split]

    @property
    def strangers(self) -> list[Convention]:
        """The held-out strangers: evaluation partners only."""
        return self.split(STRANGER)

    @property
    def training(self) -> list[Convention]:
        """The conventions a team may train with."""
        return self.split(TRAIN)

    def convention(self, name: str, splits: Sequence[str] = (TRAIN, STRANGER)) -> Convention:
        """The member named `name` among `splits` (a ConventionError names what there is)."""
        for member in self.members:
            if member.name == name and member.split in splits:
                return member.convention
        split = next((member.split for member in self.members if member.name == name), None)
        if split == STRANGER:
            raise ConventionError(f"{name!r} is a held-out stranger of the zoo: it evaluates teams and never "
                                  f"trains one; train with one of {', '.join(c.name for c in self.training)}")
        if split == TRAIN:
            raise ConventionError(f"{name!r} is a training convention of the zoo, not a held-out stranger; its "
                                  f"strangers: {', '.join(c.name for c in self.strangers)}")
        raise ConventionError(f"the zoo has no convention {name!r}; its conventions: "
                              f"{', '.join(member.name for member in self.members if member.split in splits)}")


def generator_settings(kitchen_size: int) -> dict:
    """The generator's settings the zoo's levels are drawn with (a zoo file records them; another is refused)."""
    return {key: value for key, value in dataclasses.asdict(GeneratorConfig(size=kitchen_size)).items()}


def save_zoo(zoo: Zoo, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    document = {
        "seed": zoo.seed, "kitchen_size": zoo.kitchen_size, "drawn": zoo.drawn, "levels": zoo.levels,
        "generator": zoo.generator, "similarity": zoo.similarity,
        "members": [{"split": m.split, "self_play": round(m.self_play, 3), "cooked": round(m.cooked, 3),
                     "events": {k: round(v, 2) for k, v in m.events.items()}, "convention": m.convention.as_dict()}
                    for m in zoo.members],
    }  # fmt: skip
    path.write_text(ZOO_HEADER + yaml.safe_dump(document, sort_keys=False, width=120))
    return path


def load_zoo(path: str | Path, kitchen_size: int | None = None) -> Zoo:
    """The zoo of a file; with `kitchen_size`, one drawn for kitchens of that size by this generator (else a
    ConventionError in one line)."""
    path = Path(path)
    if not path.is_file():
        raise ConventionError(f"zoo file {path} does not exist: `kitchen-zoo draw` writes one ({ZOO_FILE} is "
                              "shipped)")
    try:
        document = yaml.safe_load(path.read_text())
        members = [ZooMember(Convention.from_dict(m["convention"]), m["split"], float(m["self_play"]),
                             float(m["cooked"]), dict(m["events"])) for m in document["members"]]
        zoo = Zoo(int(document["seed"]), int(document["kitchen_size"]), dict(document["generator"]), members,
                  int(document.get("drawn", 0)), int(document.get("levels", 0)), dict(document.get("similarity", {})))
    except ConventionError as error:
        raise ConventionError(f"zoo file {path}: {error}") from None
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as error:
        raise ConventionError(f"{path} is not a zoo file ({type(error).__name__}: {error}); `kitchen-zoo draw` "
                              "writes one") from None
    if kitchen_size is not None:
        if zoo.kitchen_size != kitchen_size:
            raise ConventionError(f"zoo file {path} was drawn for {zoo.kitchen_size}x{zoo.kitchen_size} kitchens, "
                                  f"not {kitchen_size}x{kitchen_size}: draw one at this size with `kitchen-zoo draw "
                                  f"--kitchen-size {kitchen_size}`")
        expected = generator_settings(kitchen_size)
        changed = sorted(key for key in expected.keys() | zoo.generator.keys()
                         if expected.get(key) != zoo.generator.get(key))
        if changed:
            raise ConventionError(f"zoo file {path} was drawn with another generator (settings "
                                  f"{', '.join(changed)} differ): draw it again with `kitchen-zoo draw`")
    return zoo
