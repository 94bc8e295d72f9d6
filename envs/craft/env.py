"""Gymnasium front-ends for Craft: a single env and a natively batched vector env.

Both are thin shells around ``CraftBatch`` (the single env is a batch of one), so they share
every rule and every number with the expert and the data recorders.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from lerobot_policy_ocn.envs.batch_vector import BatchVectorEnv
from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.observation import OBS_DIM, OBS_HIGH
from lerobot_policy_ocn.envs.craft.render import render_live
from lerobot_policy_ocn.envs.craft.world import N_ACTIONS, parse_task, task_code, task_description

RENDER_FPS = 8


def craft_observation_space() -> spaces.Box:
    """Box of one compact observation (see lerobot_policy_ocn.envs.craft.observation for the layout)."""
    return spaces.Box(low=np.zeros(OBS_DIM, dtype=np.int64), high=OBS_HIGH, shape=(OBS_DIM,), dtype=np.int64)


def _check_render_mode(render_mode: str | None) -> str | None:
    """Only RGB arrays are produced; anything else is a caller mistake."""
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"unsupported render_mode {render_mode!r}; use None or 'rgb_array'")
    return render_mode


class CraftEnv(gym.Env):
    """One Craft episode at a time; ``task`` is letters, a named task or a description."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}

    def __init__(
        self,
        task: str = "AC",
        mode: str = "paper",
        reward: str = "dense",
        max_steps: int | None = None,
        render_mode: str | None = None,
    ):
        self.batch = CraftBatch(1, mode=mode, reward=reward, max_steps=max_steps)
        self.mode = mode
        self._set_task(task)
        self.render_mode = _check_render_mode(render_mode)
        self.observation_space = craft_observation_space()
        self.action_space = spaces.Discrete(N_ACTIONS)
        self._action = np.zeros(1, dtype=np.int64)

    def _set_task(self, task: str) -> None:
        """Parse and remember the task; it takes effect at the next reset."""
        self.subtasks = parse_task(task, self.mode)
        self.task = task_code(self.subtasks)
        self.task_description = task_description(self.subtasks)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """New random map; ``options={"task": ...}`` switches the task first."""
        super().reset(seed=seed)
        if options and "task" in options:
            self._set_task(options["task"])
        obs = self.batch.reset(seeds=[seed], tasks=[self.subtasks])
        info = {"subtask_index": 0, "progress": 0, "is_success": False, "task": self.task_description}
        return obs[0], info

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One action; after termination or truncation the env stays frozen until reset."""
        self._action[0] = action
        obs, reward, terminated, truncated, info = self.batch.step(self._action)
        out = {
            "subtask_index": int(info["subtask_index"][0]),
            "subtask_done": bool(info["subtask_done"][0]),
            "progress": int(info["progress"][0]),
            "is_success": bool(info["is_success"][0]),
            "task": self.task_description,
        }
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), out

    def render(self) -> np.ndarray | None:
        """HxWx3 uint8 frame when render_mode is "rgb_array"."""
        if self.render_mode != "rgb_array":
            return None
        return render_live(self.batch)[0]


class CraftVectorEnv(BatchVectorEnv):
    """``num_envs`` Craft envs stepped as one batch, with next-step autoreset.

    ``task`` is one task string for all envs or one per env. Infos are dicts of arrays:
    "subtask_index", "subtask_done", "progress", "is_success" and "task" (descriptions).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int,
        task: str | Sequence[str] = "AC",
        mode: str = "paper",
        reward: str = "dense",
        max_steps: int | None = None,
        render_mode: str | None = None,
    ):
        self.mode = mode
        self.render_mode = _check_render_mode(render_mode)
        batch = CraftBatch(num_envs, mode=mode, reward=reward, max_steps=max_steps)
        self._setup(batch, task, craft_observation_space(), spaces.Discrete(N_ACTIONS))

    def _parse_task(self, task: str) -> tuple[int, ...]:
        return parse_task(task, self.mode)

    def _describe(self, env_id: int) -> str:
        return task_description(self.task_specs[env_id])

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One HxWx3 uint8 frame per env when render_mode is "rgb_array"."""
        if self.render_mode != "rgb_array":
            return None
        return tuple(render_live(self.batch))
