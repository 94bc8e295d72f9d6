"""Dial as a world of the batched rollouts (`tools.rollouts`: free-run success per PIN, and each
option alone), the counterpart of `tools.craft_rollouts`. Every
episode runs in one `DialBatch` from the env's own reset (the home pose, fingertip 0.25 m
above the pad centre, plus the reset's joint noise; env seeds seed, seed+1, ...) with the env's
step limit (150 steps per digit). The policy's postprocessed actions are the 9 motor controls,
which the env clips to [-1, 1].

Tasks may be PINs ("12") or the policy's task strings ("press 1, press 2"); results are keyed as
given. In the option x subtask table each subtask is one digit ("1" or "press 1"), dialled as a
one-digit PIN: an option succeeds when that key is pressed before its termination fires.
"""

from collections.abc import Sequence

import numpy as np

from envs.dial.batch import DialBatch
from envs.dial.lerobot_env import motor_controls
from envs.dial.task import parse_pin, task_description
from tools import rollouts


def _start(tasks: Sequence[str], seeds: Sequence[int]) -> tuple[DialBatch, np.ndarray]:
    """One env per PIN, from the reset pose its seed draws."""
    dial = DialBatch(len(tasks), reward="sparse")
    return dial, dial.reset(seeds=seeds, tasks=[parse_pin(task) for task in tasks])


def _controls(actions: np.ndarray) -> np.ndarray:
    """One row of 9 motor controls per env."""
    return np.stack([motor_controls(row) for row in actions])


DIAL_WORLD = rollouts.RolloutWorld(
    start=_start, env_action=_controls, policy_task=lambda task: task_description(parse_pin(task))
)

