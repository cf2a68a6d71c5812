"""Who plays what, in which order: a design balanced by construction over conditions, kitchens and positions.

A block of the design has `StudyConfig.block_size` rows: every row of Williams' balanced Latin square over the
conditions (`web_apps.study.design.latin_square`), each with every shift of the kitchens. Row r plays the square's
row r mod R (R rows), repeated until it fills the participant's games, and at position p the kitchen (p + r // R) mod K
of the study's kitchens (K of them, in an order drawn once from the study's seed). Over each block every condition is
played equally often at each position and (Williams) follows every other equally often, every condition meets every
kitchen equally often, and every kitchen appears equally often at each position; each participant plays each kitchen
once before any twice (`design_counts` counts them). A new arrival takes the row of the block with the fewest
participants finished or in progress (`StudyDatabase.register`), so that the block balances over those who finish;
the games' seeds are drawn from the study's seed and the participant's number, so an assignment is the same whenever
it is made again. A visit is a list of stages: consent, instructions, the practice games, then each assigned game
followed by its questions, then the completion code.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

from web_apps.study.config import StudyConfig
from web_apps.study.design import latin_square

CONSENT, INSTRUCTIONS, PRACTICE, GAME, QUESTIONS, COMPLETE = ("consent", "instructions", "practice", "game",
                                                              "questions", "complete")
PLAYED = (PRACTICE, GAME)  # the stages done by playing a game through


@dataclass(frozen=True)
class Slot:
    """One game of a participant's: its position (practice games first, numbered apart), condition, kitchen, seed."""

    position: int
    practice: bool
    condition: str
    kitchen: str
    seed: int


def design_row(config: StudyConfig, row: int) -> list[tuple[str, str]]:
    """(condition, kitchen) of each assigned game of the design's row `row` (see the module docstring)."""
    names = list(config.conditions)
    square = latin_square(len(names))
    order = [names[condition] for condition in square[row % len(square)]] * (config.games // len(names))
    kitchens = random.Random(f"{config.seed}:kitchens").sample(config.kitchens, len(config.kitchens))
    shift = (row // len(square)) % len(kitchens)
    return [(condition, kitchens[(position + shift) % len(kitchens)]) for position, condition in enumerate(order)]


def assign(config: StudyConfig, number: int, row: int | None = None) -> list[Slot]:
    """The games of participant `number`: the practice ones, then the assigned ones of row `row` of the design (the
    server's choice, `StudyDatabase.register`; by default the participant's number)."""
    draw = random.Random(f"{config.seed}:{number}")
    practice = [Slot(i, True, "practice", config.practice_kitchen, draw.randrange(2**31))
                for i in range(config.practice_games)]
    return practice + [Slot(i, False, condition, kitchen, draw.randrange(2**31))
                       for i, (condition, kitchen) in enumerate(design_row(config, number if row is None else row))]


def design_counts(config: StudyConfig, rows: int) -> dict[str, dict[tuple[str, str], int]]:
    """Over rows 0..rows-1 of the design, the games of each condition x kitchen, condition x position and kitchen x
    position (positions counted from 1)."""
    counts: dict[str, dict[tuple[str, str], int]] = {"condition x kitchen": {}, "condition x position": {},
                                                      "kitchen x position": {}}
    for row in range(rows):
        for position, (condition, kitchen) in enumerate(design_row(config, row), 1):
            for table, key in (("condition x kitchen", (condition, kitchen)),
                               ("condition x position", (condition, str(position))),
                               ("kitchen x position", (kitchen, str(position)))):
                counts[table][key] = counts[table].get(key, 0) + 1
    return counts


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
