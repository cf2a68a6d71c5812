"""Who plays what, in which order: a balanced Latin square over the conditions, kitchens drawn per participant.

Participant k (numbered by arrival from 0) takes row k mod len(square) of `latin_square(n)`, repeated until it
fills the participant's games: over every len(square) participants each condition is played equally often at each
position, and (Williams' design) follows every other condition equally often. Each participant's kitchens and game
seeds are drawn from the study's seed and the participant's number alone, so an assignment is the same whenever it
is made again. A visit is a list of stages: consent, instructions, the practice games, then each assigned game
followed by its questions, then the completion code.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

from web_apps.study.config import StudyConfig

CONSENT, INSTRUCTIONS, PRACTICE, GAME, QUESTIONS, COMPLETE = ("consent", "instructions", "practice", "game",
                                                              "questions", "complete")
PLAYED = (PRACTICE, GAME)  # the stages done by playing a game through


def latin_square(n: int) -> list[list[int]]:
    """Williams' balanced Latin square over conditions 0..n-1: n rows for an even n, 2n (each row and its reverse)
    for an odd one. Each condition appears once per row and equally often at each position."""
    first, low, high = [0], 1, n - 1
    while len(first) < n:  # 0, 1, n-1, 2, n-2, ...
        first.append(low)
        low += 1
        if len(first) < n:
            first.append(high)
            high -= 1
    rows = [[(condition + shift) % n for condition in first] for shift in range(n)]
    return rows if n % 2 == 0 else rows + [row[::-1] for row in rows]


@dataclass(frozen=True)
class Slot:
    """One game of a participant's: its position (practice games first, numbered apart), condition, kitchen, seed."""

    position: int
    practice: bool
    condition: str
    kitchen: str
    seed: int


def assign(config: StudyConfig, number: int) -> list[Slot]:
    """The games of participant `number`: the practice ones, then the assigned ones in their counterbalanced order."""
    names = list(config.conditions)
    row = latin_square(len(names))[number % len(latin_square(len(names)))]
    order = [names[condition] for condition in row] * (config.games // len(names))
    draw = random.Random(f"{config.seed}:{number}")
    kitchens = []
    while len(kitchens) < len(order):  # each kitchen once before any twice
        kitchens += draw.sample(config.kitchens, len(config.kitchens))
    practice = [Slot(i, True, "practice", config.practice_kitchen, draw.randrange(2**31))
                for i in range(config.practice_games)]
    return practice + [Slot(i, False, condition, kitchen, draw.randrange(2**31))
                       for i, (condition, kitchen) in enumerate(zip(order, kitchens))]


@dataclass(frozen=True)
class Stage:
    """One stage of a visit: its kind and, for a game or its questions, the game's slot."""

    index: int
    kind: str
    slot: Slot | None = None

    @property
    def label(self) -> str:
        if self.slot is None:
            return self.kind
        return f"{self.kind} {self.slot.position + 1}"


def stages_of(slots: list[Slot]) -> list[Stage]:
    """A visit's stages in their order (see the module docstring)."""
    kinds = [(CONSENT, None), (INSTRUCTIONS, None)]
    kinds += [(PRACTICE, slot) for slot in slots if slot.practice]
    for slot in (slot for slot in slots if not slot.practice):
        kinds += [(GAME, slot), (QUESTIONS, slot)]
    kinds.append((COMPLETE, None))
    return [Stage(index, kind, slot) for index, (kind, slot) in enumerate(kinds)]
