"""CraftEnv as `lerobot-eval` drives it (see lerobot_policy_ocn.envs.lerobot_env): policy actions are float rows that
hold one integral action index."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_policy_ocn.envs.craft.env import CraftEnv
from lerobot_policy_ocn.envs.craft.world import ACTION_NAMES, N_ACTIONS, default_max_steps
from lerobot_policy_ocn.envs.lerobot_env import lerobot_env


def action_indices(actions: Any) -> np.ndarray:
    """Craft action indices (int64) held by policy actions, one per element.

    Policies emit floats, so integral floats are accepted; anything else would silently turn
    into a different move if truncated, hence the error.
    """
    values = np.asarray(actions, dtype=np.float64).reshape(-1)
    valid = np.isfinite(values) & (values == np.round(values)) & (values >= 0) & (values < N_ACTIONS)
    if not valid.all():
        raise ValueError(
            f"Craft actions are integer indices in [0, {N_ACTIONS - 1}] "
            f"({', '.join(ACTION_NAMES)}); got {float(values[~valid][0])!r}."
        )
    return values.astype(np.int64)


def action_index(action: Any) -> int:
    """The Craft action index held by one policy action (a float row of width 1, or a scalar)."""
    if np.size(action) != 1:
        raise ValueError(f"Craft takes one action index per step, got an action of shape {np.shape(action)}.")
    return int(action_indices(action)[0])


def make_lerobot_craft_env(
    task: str = "AC",
    mode: str = "paper",
    reward: str = "dense",
    max_steps: int | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """Gymnasium entry point of `OCN/CraftLeRobot-v0`: actions are float rows holding one index."""
    craft = CraftEnv(task=task, mode=mode, reward=reward, max_steps=max_steps, render_mode=render_mode)
    action_space = spaces.Box(low=0.0, high=N_ACTIONS - 1, shape=(1,), dtype=np.float32)
    return lerobot_env(craft, action_space, max_steps or default_max_steps(len(craft.subtasks)), action_index)
