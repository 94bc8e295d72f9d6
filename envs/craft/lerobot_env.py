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


def action_index(action: Any) -> int:
    """The Craft action index held by one policy action (a float row of width 1, or a scalar).

    Policies emit floats, so an integral float is accepted; anything else would silently turn
    into a different move if truncated, hence the error.
    """
    values = np.asarray(action, dtype=np.float64).reshape(-1)
    if values.size != 1:
        raise ValueError(f"Craft takes one action index per step, got an action of shape {np.shape(action)}.")
    value = float(values[0])
    if not (np.isfinite(value) and value.is_integer() and 0 <= value < N_ACTIONS):
        raise ValueError(
            f"Craft actions are integer indices in [0, {N_ACTIONS - 1}] "
            f"({', '.join(ACTION_NAMES)}); got {value!r}."
        )
    return int(value)


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
