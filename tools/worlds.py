"""What the tools need to know of a world (Craft, Dial or BabyAI), chosen once per dataset or checkpoint.

`ocn-eval`, `ocn-view` and `ocn-annotate` read the world from the dataset's `robot_type` (`world_of`),
`ocn-finetune` from the checkpoint's state and action widths (`policy_world`: a finetuned checkpoint
has no dataset beside it), and get one `World` here:
how subtasks are named, which subtasks a task string holds, how results name a task, how a list of
new tasks is written, which batched rollouts act in the world and which rerun scene draws it.
Everything else in those tools is the same code for every world. Rollouts and scenes import
torch, LeRobot or rerun, so a `World` builds them only when asked.

A dataset of no world these tools know (any LeRobot dataset of another robot) gets `foreign`: no
subtasks, no env to act in (`rollouts` None), a plain scene. The tools then parse it and report what
needs no world, and say so where a figure needs one.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from lerobot_policy_ocn.ocn_data.episodes_table import LABELS, read_info
from lerobot_policy_ocn.ocn_data.provenance import load_provenance

if TYPE_CHECKING:
    from lerobot_policy_ocn.tools.rl.rollouts import RolloutWorld
    from lerobot_policy_ocn.tools.viz.scenes import Scene


@dataclass(frozen=True)
class World:
    """One world as the tools see it.

    `subtask_codes` and `subtask_labels` name each subtask id briefly ("A", "1": table columns, a
    one-subtask task for the rollouts, entity names) and in full ("A get wood", "press 1": lanes,
    legends); `subtask_names` as the dataset's task strings spell it ("get wood", "press 1":
    annotation segments named by subtask); `task_subtasks` gives the subtask ids of a dataset task
    string; `task_key` is how results name a task; `parse_task_list` reads a comma-separated list of
    tasks as a command line writes it ("ADC,CAD", "124,481") into subtask ids, which
    `task_description` turns into the task string a policy is keyed by and `task_code` into its
    short label; `state_dim` and `action_dim` are the widths of the policy's `observation.state`
    and `action` in this world; `rollouts` and `scene` build the world's rollout adapter (None: the
    world has no env to act in) and rerun scene.
    """

    name: str
    subtask_codes: tuple[str, ...]
    subtask_labels: tuple[str, ...]
    subtask_names: tuple[str, ...]
    task_subtasks: Callable[[str], tuple[int, ...]]
    task_key: Callable[[str], str]
    parse_task_list: Callable[[str], list[tuple[int, ...]]]
    task_description: Callable[[Sequence[int]], str]
    task_code: Callable[[Sequence[int]], str]
    state_dim: int
    action_dim: int
    rollouts: Callable[[], RolloutWorld] | None
    scene: Callable[[], Scene]

    def used_subtasks(self, tasks: Sequence[str]) -> list[str]:
        """Codes of the subtasks the tasks hold, in order of first use: the option table's columns."""
        used = dict.fromkeys(s for task in tasks for s in self.task_subtasks(task))
        return [self.subtask_codes[s] for s in used]


def craft(mode: str = "paper") -> World:
    """Craft in world mode `mode` ("paper" or "full")."""
    from lerobot_policy_ocn.envs.craft.observation import OBS_DIM
    from lerobot_policy_ocn.envs.craft.world import (
        SUBTASK_LETTERS,
        SUBTASK_NAMES,
        parse_task,
        parse_task_list,
        task_code,
        task_description,
    )

    def rollouts() -> RolloutWorld:
        from lerobot_policy_ocn.tools.rl.craft_rollouts import craft_world

        return craft_world(mode)

    def scene() -> Scene:
        from lerobot_policy_ocn.tools.viz.scenes import CraftScene

        return CraftScene()

    return World(
        name="craft",
        subtask_codes=tuple(SUBTASK_LETTERS),
        subtask_labels=tuple(f"{letter} {name}" for letter, name in zip(SUBTASK_LETTERS, SUBTASK_NAMES, strict=True)),
        subtask_names=SUBTASK_NAMES,
        task_subtasks=lambda task: tuple(parse_task(task, mode)),
        task_key=str,
        parse_task_list=lambda spec: parse_task_list(spec, mode),
        task_description=task_description,
        task_code=task_code,
        state_dim=OBS_DIM,
        action_dim=1,
        rollouts=rollouts,
        scene=scene,
    )


def dial() -> World:
    """Dial: a subtask is a digit, a task a PIN, named in results by its digits ("12")."""
    from lerobot_policy_ocn.envs.dial.batch import OBS_DIM
    from lerobot_policy_ocn.envs.dial.scene import N_JOINTS
    from lerobot_policy_ocn.envs.dial.task import (
        DIGITS, SUBTASK_NAMES, parse_pin, parse_pin_list, pin_code, task_description,
    )

    def rollouts() -> RolloutWorld:
        from lerobot_policy_ocn.tools.rl.dial_rollouts import DIAL_WORLD

        return DIAL_WORLD

    def scene() -> Scene:
        from lerobot_policy_ocn.tools.viz.scenes import DialScene

        return DialScene()

    return World(
        name="dial",
        subtask_codes=tuple(str(d) for d in DIGITS),
        subtask_labels=SUBTASK_NAMES,
        subtask_names=SUBTASK_NAMES,
        task_subtasks=parse_pin,
        task_key=lambda task: pin_code(parse_pin(task)),
        parse_task_list=parse_pin_list,
        task_description=task_description,
        task_code=pin_code,
        state_dim=OBS_DIM,
        action_dim=N_JOINTS,
        rollouts=rollouts,
        scene=scene,
    )


def babyai() -> World:
    """BabyAI OpenPickupSeq: a subtask is one of the six subgoals, a task a mission string."""
    from lerobot_policy_ocn.envs.babyai.missions import AND_THEN, SINGLE, SUBGOALS, THEN, Mission, parse_mission
    from lerobot_policy_ocn.envs.babyai.observation import STATE_DIM
    from lerobot_policy_ocn.tools.rl.babyai_rollouts import SUBGOAL_CODES

    forms = {1: SINGLE, 2: THEN, 3: AND_THEN}

    def describe(subgoals: Sequence[int]) -> str:
        return Mission(forms[len(subgoals)], tuple(subgoals)).text

    def rollouts() -> RolloutWorld:
        from lerobot_policy_ocn.tools.rl.babyai_rollouts import BABYAI_WORLD

        return BABYAI_WORLD

    return World(
        name="babyai",
        subtask_codes=SUBGOAL_CODES,
        subtask_labels=SUBGOALS,
        subtask_names=SUBGOALS,
        task_subtasks=lambda task: parse_mission(task).subgoals,
        task_key=str,
        parse_task_list=lambda spec: [parse_mission(text.strip()).subgoals for text in spec.split(";") if text.strip()],
        task_description=describe,
        task_code=describe,
        state_dim=STATE_DIM,
        action_dim=1,
        rollouts=rollouts,
        scene=_plain_scene,
    )


def foreign(robot_type: str | None, n_subtasks: int = 0) -> World:
    """A dataset of a world the tools do not know: no env, a plain scene, and `n_subtasks` subtasks
    named by their ground-truth ids ("s0", "subtask 0") where the dataset has ground truth."""
    def needs_world(*_: object) -> None:
        raise ValueError(f"robot_type {robot_type!r} is no world these tools know (craft, dial, babyai): task lists "
                         "and free runs need one.")

    ids = range(n_subtasks)
    return World(
        name=str(robot_type or "none"), subtask_codes=tuple(f"s{i}" for i in ids),
        subtask_labels=tuple(f"subtask {i}" for i in ids), subtask_names=tuple(f"subtask {i}" for i in ids),
        task_subtasks=lambda task: (), task_key=str, parse_task_list=needs_world, task_description=needs_world,
        task_code=needs_world, state_dim=0, action_dim=0, rollouts=None, scene=_plain_scene,
    )


def _plain_scene() -> Scene:
    from lerobot_policy_ocn.tools.viz.scenes import PlainScene

    return PlainScene()


def _recorded_craft(root: Path) -> World:
    """Craft in the env mode record_demos' provenance names (paper mode if it names none)."""
    sessions = load_provenance(root)["sessions"]
    return craft(sessions[-1]["mode"] if sessions else "paper")


BUILDERS: dict[str, Callable[[Path], World]] = {"craft": _recorded_craft, "dial": lambda root: dial(),
                                                "babyai": lambda root: babyai()}


def world_of(root: Path) -> World:
    """The `World` of the dataset at `root`, from its `meta/info.json` robot type; a Craft dataset that
    record_demos wrote before it set the field (no robot type, Craft's compact state and the ground
    truth) is Craft; any other dataset is `foreign`."""
    from lerobot_policy_ocn.envs.craft.observation import OBS_DIM

    info = read_info(root)
    robot_type = info.get("robot_type")
    if robot_type in BUILDERS:
        return BUILDERS[robot_type](Path(root))
    features = info["features"]
    state = features.get("observation.state", {}).get("shape")
    labelled = all(key in features for key in LABELS)
    if robot_type is None and list(state or []) == [OBS_DIM] and labelled:
        return _recorded_craft(Path(root))
    return foreign(robot_type, _subtask_count(Path(root)) if labelled else 0)


def _subtask_count(root: Path) -> int:
    """Distinct ground-truth subtask ids a dataset may hold: its `subtask.id` statistics' max + 1."""
    stats = root / "meta" / "stats.json"
    if not stats.is_file():
        return 0
    import numpy as np

    return int(round(float(np.max(json.loads(stats.read_text())["subtask.id"]["max"])))) + 1


def policy_world(state_dim: int, action_dim: int, mode: str = "paper") -> World:
    """The world whose states and actions have these widths (a policy's `state_dim` and `action_dim`;
    Craft in world mode `mode`); widths of no world are a ValueError."""
    for build in (lambda: craft(mode), dial):
        world = build()
        if (world.state_dim, world.action_dim) == (state_dim, action_dim):
            return world
    raise ValueError(
        f"no world has {state_dim}-float states and {action_dim}-float actions (Craft: {craft(mode).state_dim} "
        f"and 1 action index; Dial: {dial().state_dim} and {dial().action_dim} motor controls)."
    )
