"""What the evaluation and annotation tools need to know of a dataset's world (Craft or Dial), chosen once per dataset.

`ocn-eval`, `ocn-view` and `ocn-annotate` read the world from the dataset
(`ocn_data.episodes_table.dataset_world`) and get one `World` here: how subtasks are named, which
subtasks a task string holds, how results name a task, which batched rollouts act in the world and
which rerun scene draws it. Everything else in those tools is the same code for every world.
Rollouts and scenes import torch, LeRobot or rerun, so a `World` builds them only when asked.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ocn_data.episodes_table import dataset_world
from ocn_data.provenance import load_provenance

if TYPE_CHECKING:
    from tools.rollouts import RolloutWorld
    from tools.view_scenes import Scene


@dataclass(frozen=True)
class World:
    """One world as the tools see it.

    `subtask_codes` and `subtask_labels` name each subtask id briefly ("A", "1": table columns, a
    one-subtask task for the rollouts, entity names) and in full ("A get wood", "press 1": lanes,
    legends); `subtask_names` as the dataset's task strings spell it ("get wood", "press 1":
    annotation segments named by subtask); `task_subtasks` gives the subtask ids of a dataset task
    string; `task_key` is how results name a task; `rollouts` and `scene` build the world's rollout
    adapter and rerun scene.
    """

    name: str
    subtask_codes: tuple[str, ...]
    subtask_labels: tuple[str, ...]
    subtask_names: tuple[str, ...]
    task_subtasks: Callable[[str], tuple[int, ...]]
    task_key: Callable[[str], str]
    rollouts: Callable[[], RolloutWorld]
    scene: Callable[[], Scene]

    def used_subtasks(self, tasks: Sequence[str]) -> list[str]:
        """Codes of the subtasks the tasks hold, in order of first use: the option table's columns."""
        used = dict.fromkeys(s for task in tasks for s in self.task_subtasks(task))
        return [self.subtask_codes[s] for s in used]


def _craft(root: Path) -> World:
    """Craft in the env mode record_demos' provenance names (paper mode if it names none)."""
    from envs.craft.world import SUBTASK_LETTERS, SUBTASK_NAMES, parse_task

    sessions = load_provenance(root)["sessions"]
    mode = sessions[-1]["mode"] if sessions else "paper"

    def rollouts() -> RolloutWorld:
        from tools.craft_rollouts import craft_world

        return craft_world(mode)

    def scene() -> Scene:
        from tools.view_scenes import CraftScene

        return CraftScene()

    return World(
        name="craft",
        subtask_codes=tuple(SUBTASK_LETTERS),
        subtask_labels=tuple(f"{letter} {name}" for letter, name in zip(SUBTASK_LETTERS, SUBTASK_NAMES, strict=True)),
        subtask_names=SUBTASK_NAMES,
        task_subtasks=lambda task: tuple(parse_task(task, mode)),
        task_key=str,
        rollouts=rollouts,
        scene=scene,
    )


def _dial(root: Path) -> World:
    """Dial: a subtask is a digit, a task a PIN, named in results by its digits ("12")."""
    from envs.dial.task import DIGITS, SUBTASK_NAMES, parse_pin, pin_code

    def rollouts() -> RolloutWorld:
        from tools.dial_rollouts import DIAL_WORLD

        return DIAL_WORLD

    def scene() -> Scene:
        from tools.view_scenes import DialScene

        return DialScene()

    return World(
        name="dial",
        subtask_codes=tuple(str(d) for d in DIGITS),
        subtask_labels=SUBTASK_NAMES,
        subtask_names=SUBTASK_NAMES,
        task_subtasks=parse_pin,
        task_key=lambda task: pin_code(parse_pin(task)),
        rollouts=rollouts,
        scene=scene,
    )


BUILDERS: dict[str, Callable[[Path], World]] = {"craft": _craft, "dial": _dial}


def world_of(root: Path) -> World:
    """The `World` of the dataset at `root`; a dataset of another world is a ValueError."""
    return BUILDERS[dataset_world(root)](Path(root))
