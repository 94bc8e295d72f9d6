"""The mission language of the BabyAI level `OpenPickupSeq`, as plain data (no minigrid needed).

A mission is a sequence of sub-instructions ("subgoals") drawn from a fixed vocabulary of six:
open one of three doors, or pick up one of three objects. The level records missions of two
forms, "A, then B" and "A and B, then C" (minigrid's `BeforeInstr` over action clauses or an
`AndInstr`), with distinct subgoals: 30 + 120 = 150 missions, each a LeRobot task string. A
one-subgoal mission ("open the red door") is accepted too, for evaluations that run one subtask
alone, but is never recorded. Keeping this module free of minigrid lets tools name subtasks and
tasks on machines without the optional `babyai` extra.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import permutations

DOOR_COLORS = ("red", "green", "blue")
# (color, type) of the objects a mission may ask to pick up; every episode holds each of them once.
PICKUP_OBJECTS = (("yellow", "ball"), ("purple", "box"), ("grey", "key"))

# Global subtask ids are positions in this tuple (the dataset's `subtask.id`).
SUBGOALS = tuple(f"open the {color} door" for color in DOOR_COLORS) + tuple(
    f"pick up the {color} {kind}" for color, kind in PICKUP_OBJECTS
)

THEN = "then"  # "A, then B"
AND_THEN = "and_then"  # "A and B, then C"; A and B may be done in either order
SINGLE = "single"  # "A": evaluation only


@dataclass(frozen=True)
class Mission:
    """A mission as its form and its subgoal ids in the order the text names them (which is the
    order the bot carries them out)."""

    form: str
    subgoals: tuple[int, ...]

    @property
    def text(self) -> str:
        """The mission string, spelt as minigrid's instruction objects spell it (`surface`)."""
        words = [SUBGOALS[s] for s in self.subgoals]
        if self.form == SINGLE:
            return words[0]
        if self.form == THEN:
            return f"{words[0]}, then {words[1]}"
        return f"{words[0]} and {words[1]}, then {words[2]}"


def _enumerate() -> tuple[Mission, ...]:
    ids = range(len(SUBGOALS))
    two = [Mission(THEN, pair) for pair in permutations(ids, 2)]
    three = [Mission(AND_THEN, triple) for triple in permutations(ids, 3)]
    return tuple(two + three)


# The missions the level draws and the recorder records, in a fixed order.
MISSIONS = _enumerate()
_ACCEPTED = {m.text: m for m in (*MISSIONS, *(Mission(SINGLE, (s,)) for s in range(len(SUBGOALS))))}


def parse_mission(text: str) -> Mission:
    """The mission a string names; a string outside the level's language is a ValueError (a policy
    keyed by task strings knows only the missions it was trained on)."""
    mission = _ACCEPTED.get(text)
    if mission is None:
        raise ValueError(
            f"{text!r} is not a mission of BabyAI OpenPickupSeq; missions join the subgoals "
            f"{', '.join(SUBGOALS)} as 'A, then B' or 'A and B, then C' (or one subgoal alone)."
        )
    return mission
