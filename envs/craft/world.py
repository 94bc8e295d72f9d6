"""Craft world constants, recipes, subtasks and task parsing.

Everything here is plain data shared by the simulator, the expert, the renderer and the
dataset tools, so that kind ids, action codes and task strings have exactly one definition.
The world follows the psketch / OMPN Craft setup: a 10x10 grid with a wall border,
resources to gather, workshops that turn ingredients into products, and tasks that are
sequences of subtasks ("get X" / "use W").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

GRID_SIZE = 10
INTERIOR_SIZE = GRID_SIZE - 2

KIND_NAMES = (
    "empty",
    "boundary",
    "water",
    "stone",
    "toolshed",
    "workbench",
    "factory",
    "iron",
    "grass",
    "wood",
    "gold",
    "gem",
    "plank",
    "stick",
    "axe",
    "rope",
    "bed",
    "shears",
    "cloth",
    "bridge",
    "ladder",
)
N_KINDS = len(KIND_NAMES)
(
    EMPTY,
    BOUNDARY,
    WATER,
    STONE,
    TOOLSHED,
    WORKBENCH,
    FACTORY,
    IRON,
    GRASS,
    WOOD,
    GOLD,
    GEM,
    PLANK,
    STICK,
    AXE,
    ROPE,
    BED,
    SHEARS,
    CLOTH,
    BRIDGE,
    LADDER,
) = range(N_KINDS)

ACTION_NAMES = ("down", "up", "left", "right", "use")
N_ACTIONS = len(ACTION_NAMES)
DOWN, UP, LEFT, RIGHT, USE = range(N_ACTIONS)
# (row, col) displacement of each move action; row grows downwards.
MOVE_DELTAS = np.array([[1, 0], [-1, 0], [0, -1], [0, 1]], dtype=np.int64)

GATHERABLE_KINDS = (IRON, GRASS, WOOD, GOLD, GEM)
WORKSHOP_KINDS = (TOOLSHED, WORKBENCH, FACTORY)

# Recipes in priority order: a workshop crafts the first of its recipes whose ingredients
# are all held. Kept as arrays so crafting is a single vectorized test over the batch.
_RECIPES = (
    (TOOLSHED, PLANK, (WOOD,)),
    (TOOLSHED, AXE, (STICK, IRON)),
    (TOOLSHED, ROPE, (GRASS,)),
    (WORKBENCH, STICK, (WOOD,)),
    (WORKBENCH, BED, (PLANK, GRASS)),
    (WORKBENCH, SHEARS, (STICK, IRON)),
    (FACTORY, CLOTH, (GRASS,)),
    (FACTORY, BRIDGE, (WOOD, IRON)),
    (FACTORY, LADDER, (PLANK, STICK)),
)
RECIPE_WORKSHOP = np.array([w for w, _, _ in _RECIPES], dtype=np.int64)
RECIPE_PRODUCT = np.array([p for _, p, _ in _RECIPES], dtype=np.int64)
RECIPE_INGREDIENTS = np.array([np.isin(np.arange(N_KINDS), i) for _, _, i in _RECIPES], dtype=np.int64)

SUBTASK_LETTERS = "ABCDEFGH"
SUBTASK_NAMES = (
    "get wood",
    "get gold",
    "get iron",
    "get grass",
    "use toolshed",
    "use workbench",
    "use factory",
    "get gem",
)
N_SUBTASKS = len(SUBTASK_NAMES)
# Grid kind a subtask acts on: gathering it ("get") or crafting at it ("use").
SUBTASK_TARGET = np.array([WOOD, GOLD, IRON, GRASS, TOOLSHED, WORKBENCH, FACTORY, GEM], dtype=np.int64)

MODES = ("paper", "full")
REWARDS = ("dense", "sparse")
MODE_SUBTASKS = {"paper": (0, 1, 2, 3), "full": tuple(range(N_SUBTASKS))}

NAMED_TASKS = {
    "make plank": "AE",
    "make stick": "AF",
    "make cloth": "DG",
    "make rope": "DE",
    "make bridge": "CAG",
    "make bed": "AEDF",
    "make axe": "AFCE",
    "make shears": "AFCF",
    "get gold": "CAGB",
    "get gem": "AFCEH",
}

SHORT_TASK_MAX_STEPS = 64
LONG_TASK_MAX_STEPS = 100


def check_mode(mode: str) -> str:
    """Fail early on a misspelled mode instead of silently generating the wrong world."""
    if mode not in MODES:
        raise ValueError(f"unknown Craft mode {mode!r}; valid modes: {', '.join(MODES)}")
    return mode


def default_max_steps(num_subtasks: int) -> int:
    """Step limit of the OMPN setup: 64 for tasks of at most two subtasks, else 100."""
    return SHORT_TASK_MAX_STEPS if num_subtasks <= 2 else LONG_TASK_MAX_STEPS


def task_code(subtasks: Sequence[int]) -> str:
    """Compact letter form of a task, e.g. (0, 2) -> "AC"."""
    return "".join(SUBTASK_LETTERS[s] for s in subtasks)


def task_description(subtasks: Sequence[int]) -> str:
    """Canonical language form of a task, e.g. (0, 2) -> "get wood, get iron"."""
    return ", ".join(SUBTASK_NAMES[s] for s in subtasks)


def _valid_help(mode: str) -> str:
    """List what a task string may contain in this mode, for error messages."""
    letters = ", ".join(f"{SUBTASK_LETTERS[s]} ({SUBTASK_NAMES[s]})" for s in MODE_SUBTASKS[mode])
    text = f"valid subtask letters in {mode} mode: {letters}"
    if mode == "full":
        named = ", ".join(f"{name!r} ({code})" for name, code in NAMED_TASKS.items())
        text += f"; named tasks: {named}"
    else:
        text += "; named tasks such as 'make bed' need mode='full'"
    return text


def parse_task(spec: str, mode: str = "paper") -> tuple[int, ...]:
    """Turn a task string into subtask ids.

    Accepts letters ("ADC", any case), a named task ("make bed", full mode only) or a
    canonical description ("get wood, get iron"). In full mode named tasks win over
    descriptions, so "get gold" means the named task CAGB there, not the one subtask B.
    """
    check_mode(mode)
    text = " ".join(str(spec).lower().split())
    if not text:
        raise ValueError(f"empty task {spec!r}; {_valid_help(mode)}")
    if mode == "full" and text in NAMED_TASKS:
        text = NAMED_TASKS[text].lower()
    if " " in text or "," in text:
        ids = []
        for part in (p.strip() for p in text.split(",")):
            if part not in SUBTASK_NAMES:
                raise ValueError(f"unknown subtask {part!r} in task {spec!r}; {_valid_help(mode)}")
            ids.append(SUBTASK_NAMES.index(part))
    else:
        ids = []
        for letter in text.upper():
            if letter not in SUBTASK_LETTERS:
                raise ValueError(f"unknown subtask letter {letter!r} in task {spec!r}; {_valid_help(mode)}")
            ids.append(SUBTASK_LETTERS.index(letter))
    for s in ids:
        if s not in MODE_SUBTASKS[mode]:
            raise ValueError(
                f"subtask {SUBTASK_LETTERS[s]} ({SUBTASK_NAMES[s]}) in task {spec!r} is not available "
                f"in {mode} mode; {_valid_help(mode)}"
            )
    return tuple(ids)


def parse_task_list(spec: str, mode: str = "paper") -> list[tuple[int, ...]]:
    """A comma-separated task list (`--tasks AC,CD,DA`) as subtask ids; an empty entry or a task
    named twice is an error (task lists hold letters or named tasks, not comma descriptions)."""
    tasks = [parse_task(part, mode) for part in spec.split(",")]
    if len(set(tasks)) != len(tasks):
        raise ValueError(f"--tasks lists a task twice: {spec!r}")
    return tasks


def check_task(subtasks: Sequence[int], mode: str) -> tuple[int, ...]:
    """Validate an already-parsed task against a mode (same errors as parse_task)."""
    ids = tuple(int(s) for s in subtasks)
    if not ids:
        raise ValueError(f"empty task; {_valid_help(mode)}")
    for s in ids:
        if s not in MODE_SUBTASKS[check_mode(mode)]:
            name = f"{SUBTASK_LETTERS[s]} ({SUBTASK_NAMES[s]})" if 0 <= s < N_SUBTASKS else str(s)
            raise ValueError(f"subtask {name} is not available in {mode} mode; {_valid_help(mode)}")
    return ids
