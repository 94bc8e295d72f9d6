"""Gymnasium front-ends for Dial: a single env and a batched vector env, both shells of ``DialBatch``.

``task`` is a PIN ("124", or "press 1, press 2, press 4") dialled in every episode, or None for a
new random PIN of ``pin_length`` digits from ``digits`` at every reset (no digit directly repeated).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

from lerobot_policy_ocn.envs.batch_vector import BatchVectorEnv
from lerobot_policy_ocn.envs.dial.batch import CONTROL_DT, OBS_DIM, DialBatch
from lerobot_policy_ocn.envs.dial.render import DialRenderer
from lerobot_policy_ocn.envs.dial.scene import N_JOINTS
from lerobot_policy_ocn.envs.dial.task import DEFAULT_DIGITS, parse_pin, pin_code, task_description

FPS = round(1.0 / CONTROL_DT)


def dial_observation_space() -> spaces.Box:
    """Box of one 39-float state: 9 joint angles, then fingertip minus each key's press point."""
    return spaces.Box(low=-np.inf, high=np.inf, shape=(OBS_DIM,), dtype=np.float32)


def dial_action_space() -> spaces.Box:
    """Box of the 9 motor controls in [-1, 1]."""
    return spaces.Box(low=-1.0, high=1.0, shape=(N_JOINTS,), dtype=np.float32)


def _check_render_mode(render_mode: str | None) -> str | None:
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"unsupported render_mode {render_mode!r}; use None or 'rgb_array'")
    return render_mode


def _parse_task(task: str | None) -> tuple[int, ...] | None:
    return None if task is None else parse_pin(task)


class DialEnv(gym.Env):
    """One Dial episode at a time. Info: "subtask" (index in the PIN of the digit being dialled
    during the step), "subtask_done", "progress" (digits dialled), "is_success", "key" (the digit
    whose key was pressed this step, or -1) and "task"."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS}

    def __init__(
        self,
        task: str | None = None,
        reward: str = "dense",
        max_steps: int | None = None,
        digits: str | Sequence[int] = DEFAULT_DIGITS,
        pin_length: int = 2,
        render_mode: str | None = None,
    ):
        self.batch = DialBatch(1, reward=reward, max_steps=max_steps, digits=digits, pin_length=pin_length)
        self.task_spec = _parse_task(task)
        self.render_mode = _check_render_mode(render_mode)
        self.observation_space = dial_observation_space()
        self.action_space = dial_action_space()
        self.task = "" if task is None else pin_code(self.task_spec)
        self.task_description = "" if task is None else task_description(self.task_spec)
        self._renderer: DialRenderer | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """New start pose (and a new PIN if random); ``options={"task": ...}`` switches the task first."""
        super().reset(seed=seed)
        if options and "task" in options:
            self.task_spec = _parse_task(options["task"])
        obs = self.batch.reset(seeds=[seed], tasks=[self.task_spec])
        pin = self.batch.task_of(0)
        self.task = pin_code(pin)
        self.task_description = task_description(pin)
        info = {"subtask": 0, "progress": 0, "is_success": False, "task": self.task_description}
        return obs[0], info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One action (held for 20 physics steps); after the episode ends the env stays frozen until reset."""
        obs, reward, terminated, truncated, info = self.batch.step(np.asarray(action)[None])
        out = {
            "subtask": int(info["subtask_index"][0]),
            "subtask_done": bool(info["subtask_done"][0]),
            "progress": int(info["progress"][0]),
            "is_success": bool(info["is_success"][0]),
            "key": int(info["key"][0]),
            "task": self.task_description,
        }
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), out

    def render(self) -> np.ndarray | None:
        """HxWx3 uint8 frame when render_mode is "rgb_array" (needs an OpenGL backend, see envs.dial.render)."""
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = DialRenderer(self.batch.model)
        return self._renderer.render(self.batch.data[0])

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class DialVectorEnv(BatchVectorEnv):
    """``num_envs`` Dial envs stepped as one batch, with next-step autoreset.

    ``task`` is one PIN (or None: random PINs) for all envs, or a list with one per env. Infos are
    dicts of arrays: "subtask_index", "subtask_done", "progress", "is_success", "key" and "task".
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": FPS, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int,
        task: str | None | Sequence[str | None] = None,
        reward: str = "dense",
        max_steps: int | None = None,
        digits: str | Sequence[int] = DEFAULT_DIGITS,
        pin_length: int = 2,
        render_mode: str | None = None,
    ):
        self.render_mode = _check_render_mode(render_mode)
        batch = DialBatch(num_envs, reward=reward, max_steps=max_steps, digits=digits, pin_length=pin_length)
        self._setup(batch, task, dial_observation_space(), dial_action_space())
        self._renderer: DialRenderer | None = None

    def _parse_task(self, task: str | None) -> tuple[int, ...] | None:
        return _parse_task(task)

    def _describe(self, env_id: int) -> str:
        return task_description(self.batch.task_of(env_id))

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One HxWx3 uint8 frame per env when render_mode is "rgb_array" (needs an OpenGL backend)."""
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = DialRenderer(self.batch.model)
        return tuple(self._renderer.render(data) for data in self.batch.data)
