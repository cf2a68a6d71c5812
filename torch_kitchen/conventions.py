"""Conventions: how a scripted cook plays, as data. A convention is a named, typed config; the cook
(`torch_kitchen.scripted.ScriptedCook`) reads it, so cooks of different conventions are one class.

    preferences       event -> weight in [-1, 1]: goals that lead to the event are taken earlier (> 0) or later
                      (< 0); ZSC-Eval's evaluation partners are such weight vectors, with at most three non-zero
    role              "both"; "loader": takes plates and soups only where no onion can go in a pot; "server": takes
                      onions only where no plate or soup can be taken
    handover          "when_needed": puts an item on a counter the partner can reach where it cannot carry it to its
                      goal itself; "prefer": also where the partner is nearer that goal; "avoid": never
    move_order        the move taken among equally short ones (a permutation of "NSEW")
    goal_temperature  0: the best goal it can reach; > 0: a goal drawn with probability ~ exp(score / temperature)
    move_temperature  0: a shortest way; > 0: a move drawn with probability ~ exp(-steps left after it / temperature)
    noise             the probability of an action drawn uniformly instead

The default convention is the scripted cook of every earlier run, action for action. `draw_convention` draws one
from a seed, as the zoo (`trainers.zoo`) does.
"""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass, field

from torch_kitchen.events import EVENTS

ROLES = ("both", "loader", "server")
HANDOVERS = ("when_needed", "prefer", "avoid")
MOVE_ORDER = "NSEW"  # the move a cook takes where several are equally short: the first of them in this order
MAX_PREFERENCES = 3  # ZSC-Eval's partners: at most three events with a non-zero weight


class ConventionError(ValueError):
    """A convention that no cook can play; the message says what is allowed."""


@dataclass(frozen=True)
class Convention:
    """How a scripted cook plays (see the module docstring); `Convention()` is the scripted cook of earlier runs."""

    name: str = "scripted_cook"
    preferences: dict[str, float] = field(default_factory=dict)
    role: str = "both"
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

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

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
        """One line: role, hand-overs, non-zero preferences, move order, temperatures, noise."""
        preferences = ", ".join(f"{event} {weight:+.1f}" for event, weight in self.preferences.items() if weight)
        return (f"{self.role}, hand-overs {self.handover}, {preferences or 'no preferences'}, moves "
                f"{self.move_order}, T goal {self.goal_temperature:g} move {self.move_temperature:g}, "
                f"noise {self.noise:g}")


def draw_convention(rng: random.Random, name: str) -> Convention:
    """A convention drawn from `rng`: one to three preferred or avoided events, a role, a hand-over habit, a move
    order, and a little irrationality (a third of them plan without temperatures, as the scripted cook)."""
    events = rng.sample(EVENTS, rng.randint(1, MAX_PREFERENCES))
    preferences = {event: round(rng.choice((-1, 1)) * rng.uniform(0.3, 1.0), 2) for event in events}
    role = rng.choices(ROLES, weights=(2, 1, 1))[0]
    handover = rng.choices(HANDOVERS, weights=(2, 1, 1))[0]
    order = list(MOVE_ORDER)
    rng.shuffle(order)
    rational = rng.random() < 1 / 3
    return Convention(
        name=name, preferences=preferences, role=role, handover=handover, move_order="".join(order),
        goal_temperature=0.0 if rational else round(rng.choice((0.0, 0.5, 1.0, 2.0)), 2),
        move_temperature=0.0 if rational else round(rng.choice((0.0, 0.5, 1.0)), 2),
        noise=0.0 if rational else round(rng.choice((0.0, 0.02, 0.05, 0.1)), 2),
    )

