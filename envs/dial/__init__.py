"""Dial (paper 4.2, OMPN / TACO setup): a JACO arm dials PINs on a 10-key pad in MuJoCo.

Batched simulator, gym wrappers, IK poses and the scripted PD expert; the scene is built from the
JACO model that the `dm-control` package ships (see lerobot_policy_ocn.envs.dial.scene).
"""

from lerobot_policy_ocn.envs.dial.batch import CONTROL_DT, FRAME_SKIP, OBS_DIM, PRESS_L1, RELEASE_L1, DialBatch
from lerobot_policy_ocn.envs.dial.env import FPS, DialEnv, DialVectorEnv, dial_action_space, dial_observation_space
from lerobot_policy_ocn.envs.dial.expert import DialExpert, RestDynamics
from lerobot_policy_ocn.envs.dial.poses import DialPoses, dial_poses, solve_ik
from lerobot_policy_ocn.envs.dial.scene import DIGIT_CELLS, GEARS, N_JOINTS, dial_model, key_positions
from lerobot_policy_ocn.envs.dial.task import (
    DEFAULT_DIGITS,
    SUBTASK_NAMES,
    default_max_steps,
    parse_digits,
    parse_pin,
    parse_pin_list,
    pin_code,
    sample_pin,
    task_description,
)

__all__ = [
    "CONTROL_DT",
    "DEFAULT_DIGITS",
    "DIGIT_CELLS",
    "FPS",
    "FRAME_SKIP",
    "GEARS",
    "N_JOINTS",
    "OBS_DIM",
    "PRESS_L1",
    "RELEASE_L1",
    "SUBTASK_NAMES",
    "DialBatch",
    "DialEnv",
    "DialExpert",
    "DialPoses",
    "DialVectorEnv",
    "RestDynamics",
    "default_max_steps",
    "dial_action_space",
    "dial_model",
    "dial_observation_space",
    "dial_poses",
    "key_positions",
    "parse_digits",
    "parse_pin",
    "parse_pin_list",
    "pin_code",
    "sample_pin",
    "solve_ik",
    "task_description",
]
