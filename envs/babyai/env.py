"""`OCN/BabyAI-OpenPickupSeq-v0`: the level as a gymnasium env with integer state vectors.

Observations are `observation.encode`'s int64 vectors (the 7 x 7 x 3 view and the direction);
actions are minigrid's seven indices (0 left, 1 right, 2 forward, 3 pickup, 4 drop, 5 toggle,
6 done; the bot never sends `done` in an episode it finishes, since the level ends the episode
at the action that completes the mission). The mission string, LeRobot's task, is
`task_description` and `info["mission"]`. Each step's info also gives the ground-truth
`progress` (subgoals completed so far, see `subgoals`) and `is_success`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from lerobot_policy_ocn.envs.babyai.level import OpenPickupSeqLevel
from lerobot_policy_ocn.envs.babyai.minigrid_api import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX, Actions
from lerobot_policy_ocn.envs.babyai.observation import STATE_DIM, VIEW_SIZE, encode
from lerobot_policy_ocn.envs.babyai.subgoals import SubgoalTracker

N_ACTIONS = len(Actions)


def observation_space() -> spaces.Box:
    """Box of one state vector: each view channel (object, colour, state) up to its largest minigrid
    index, then the direction."""
    highs = [max(OBJECT_TO_IDX.values()), max(COLOR_TO_IDX.values()), max(STATE_TO_IDX.values())]
    high = np.array(highs * (VIEW_SIZE * VIEW_SIZE) + [3], dtype=np.int64)
    return spaces.Box(low=np.zeros(STATE_DIM, dtype=np.int64), high=high, dtype=np.int64)


class BabyAIEnv(gym.Env):
    """One OpenPickupSeq episode at a time. `mission` fixes the mission of every reset (None: a
    random one each time); `reset(options={"mission": text})` overrides it for one episode."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, mission: str | None = None, render_mode: str | None = None) -> None:
        self.level = OpenPickupSeqLevel(render_mode=render_mode)
        self.fixed_mission = mission
        self.render_mode = render_mode
        self.observation_space = observation_space()
        self.action_space = spaces.Discrete(N_ACTIONS)
        self.tracker: SubgoalTracker | None = None
        self.over = True

    @property
    def task_description(self) -> str:
        """The current episode's mission (LeRobot's task string)."""
        return self.level.mission

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        mission = (options or {}).get("mission", self.fixed_mission)
        obs, _ = self.level.reset(seed=seed, options=None if mission is None else {"mission": mission})
        self.tracker = SubgoalTracker(self.level.instrs, self.level.spec.subgoals)
        self.over = False
        return encode(obs), {"mission": self.level.mission, "progress": 0, "is_success": False}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self.over:
            raise RuntimeError("the episode is over: reset the env before stepping it again")
        obs, reward, terminated, truncated, _ = self.level.step(int(action))
        success = bool(terminated and reward > 0)
        done_now = self.tracker.update(success)
        self.over = bool(terminated or truncated)
        info = {
            "mission": self.level.mission,
            "progress": self.tracker.progress,
            "subtask_done": done_now > 0,
            "is_success": success,
        }
        return encode(obs), float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        """The whole grid as an RGB array when render_mode is "rgb_array"."""
        return self.level.render() if self.render_mode == "rgb_array" else None
