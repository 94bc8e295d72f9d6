"""Dial as a world of the batched rollouts (`lerobot_policy_ocn.tools.rl.rollouts`: free-run success per PIN, and each
option alone, and PPO's episodes in `tools.rl.ppo`), the counterpart of `tools.rl.craft_rollouts`. Every
episode runs in one `DialBatch` from the env's own reset (the home pose, fingertip 0.25 m
above the pad centre, plus the reset's joint noise; env seeds seed, seed+1, ...) with the env's
step limit (150 steps per digit). The policy's postprocessed actions are the 9 motor controls,
which the env clips to [-1, 1].

Tasks may be PINs ("12") or the policy's task strings ("press 1, press 2"); results are keyed as
given. In the option x subtask table each subtask is one digit ("1" or "press 1"), dialled as a
one-digit PIN: an option succeeds when that key is pressed before its termination fires.
"""

import numpy as np

from lerobot_policy_ocn.envs.dial.batch import DialBatch
from lerobot_policy_ocn.envs.dial.lerobot_env import motor_controls
from lerobot_policy_ocn.envs.dial.task import parse_pin, task_description
from lerobot_policy_ocn.tools.rl import rollouts


def _new_batch(num_envs: int, reward: str, max_steps: int | None) -> DialBatch:
    """Envs whose PINs come with each reset."""
    return DialBatch(num_envs, reward=reward, max_steps=max_steps)


def _controls(actions: np.ndarray) -> np.ndarray:
    """One row of 9 motor controls per env."""
    return np.stack([motor_controls(row) for row in actions])


DIAL_WORLD = rollouts.RolloutWorld(
    new_batch=_new_batch, env_action=_controls, policy_task=lambda task: task_description(parse_pin(task))
)
