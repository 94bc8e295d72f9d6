"""Craft grid world (psketch / OMPN setup): batched simulator, gym wrappers, expert, features."""

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.env import CraftEnv, CraftVectorEnv, craft_observation_space
from lerobot_policy_ocn.envs.craft.expert import CraftExpert
from lerobot_policy_ocn.envs.craft.observation import OBS_DIM, OBS_NAMES, OMPN_DIM, ompn_features
from lerobot_policy_ocn.envs.craft.render import render_batch, render_live, render_state
from lerobot_policy_ocn.envs.craft.world import (
    ACTION_NAMES,
    KIND_NAMES,
    N_ACTIONS,
    N_KINDS,
    NAMED_TASKS,
    SUBTASK_LETTERS,
    SUBTASK_NAMES,
    default_max_steps,
    parse_task,
    task_code,
    task_description,
)

__all__ = [
    "ACTION_NAMES",
    "KIND_NAMES",
    "NAMED_TASKS",
    "N_ACTIONS",
    "N_KINDS",
    "OBS_DIM",
    "OBS_NAMES",
    "OMPN_DIM",
    "SUBTASK_LETTERS",
    "SUBTASK_NAMES",
    "CraftBatch",
    "CraftEnv",
    "CraftExpert",
    "CraftVectorEnv",
    "craft_observation_space",
    "default_max_steps",
    "ompn_features",
    "parse_task",
    "render_batch",
    "render_live",
    "render_state",
    "task_code",
    "task_description",
]
