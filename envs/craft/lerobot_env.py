"""CraftEnv as `lerobot-eval` drives it.

LeRobot's rollout reads observations from the `agent_pos` key (-> `observation.state`), sends every
action as a float row of shape (action_dim,), asks each sub-env for `_max_episode_steps` and its
`task_description`, and reads `info["is_success"]`. This wrapper supplies the first three; CraftEnv
already has the others, so its own API stays as it is.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from lerobot.envs.utils import FreezeAfterEpisodeEnd

from envs.craft.env import CraftEnv
from envs.craft.world import ACTION_NAMES, N_ACTIONS, default_max_steps

STATE_KEY = "agent_pos"


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


class LeRobotCraftEnv(gym.Wrapper):
    """Dict observations {"agent_pos": state}, float action rows, and the step limit LeRobot asks for."""

    def __init__(self, env: CraftEnv, max_steps: int | None = None) -> None:
        super().__init__(env)
        self.observation_space = spaces.Dict({STATE_KEY: env.observation_space})
        self.action_space = spaces.Box(low=0.0, high=N_ACTIONS - 1, shape=(1,), dtype=np.float32)
        self._max_episode_steps = max_steps or default_max_steps(len(env.subtasks))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        obs, info = self.env.reset(seed=seed, options=options)
        return {STATE_KEY: obs}, info

    def step(self, action: Any) -> tuple[dict, float, bool, bool, dict]:
        obs, reward, terminated, truncated, info = self.env.step(action_index(action))
        return {STATE_KEY: obs}, reward, terminated, truncated, info


def make_lerobot_craft_env(
    task: str = "AC",
    mode: str = "paper",
    reward: str = "dense",
    max_steps: int | None = None,
    render_mode: str | None = None,
) -> gym.Env:
    """Gymnasium entry point of `OCN/CraftLeRobot-v0`.

    LeRobot's default vector env autoresets in the same step, so a finished sub-env would start a
    new episode whose first reward `lerobot-eval` still adds to the finished one (its mask keeps
    one step past the first done). LeRobot's `FreezeAfterEpisodeEnd` replays the terminal step
    with reward 0 instead, until the next rollout's reset.
    """
    craft = CraftEnv(task=task, mode=mode, reward=reward, max_steps=max_steps, render_mode=render_mode)
    return FreezeAfterEpisodeEnd(LeRobotCraftEnv(craft, max_steps))
