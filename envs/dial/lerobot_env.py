"""DialEnv as `lerobot-eval` drives it (see lerobot_policy_ocn.envs.lerobot_env): policy actions are float rows of the
9 motor controls."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from lerobot_policy_ocn.envs.dial.env import DialEnv
from lerobot_policy_ocn.envs.dial.scene import N_JOINTS
from lerobot_policy_ocn.envs.dial.task import DEFAULT_DIGITS, default_max_steps
from lerobot_policy_ocn.envs.lerobot_env import lerobot_env


def motor_controls(action: Any) -> np.ndarray:
    """The 9 motor controls held by one policy action (a float row of width 9)."""
    if np.size(action) != N_JOINTS:
        raise ValueError(f"Dial takes {N_JOINTS} motor controls per step, got an action of shape {np.shape(action)}.")
    return np.asarray(action, dtype=np.float64).reshape(N_JOINTS)


def make_lerobot_dial_env(
    task: str | None = "12",
    reward: str = "dense",
    max_steps: int | None = None,
    digits: str | Sequence[int] = DEFAULT_DIGITS,
    pin_length: int = 2,
    render_mode: str | None = None,
) -> gym.Env:
    """Gymnasium entry point of `OCN/DialLeRobot-v0`."""
    dial = DialEnv(
        task=task, reward=reward, max_steps=max_steps, digits=digits, pin_length=pin_length, render_mode=render_mode
    )
    length = pin_length if dial.task_spec is None else len(dial.task_spec)
    return lerobot_env(dial, dial.action_space, max_steps or default_max_steps(length), motor_controls)
