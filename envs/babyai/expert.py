"""minigrid's BabyAI bot as the expert: whole demonstration episodes, and a policy for free runs.

The bot (`minigrid.utils.baby_ai_bot.BabyAIBot`) plans on the env's full state and its own memory
of what the agent has seen, not on the state vector; it turns the mission's instruction tree
into a stack of subgoals and returns one action per `replan()`. For a pickup it picks the
object up and drops it again at once (to keep its hands free), so a segment that follows a
pickup starts with that drop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv
from lerobot_policy_ocn.envs.babyai.minigrid_api import BabyAIBot


@dataclass
class Demonstration:
    """One successful bot episode, frame by frame: state [T, S], action [T], reward [T] (minigrid's,
    paid on the last frame), and the ground truth `subtask_index` and `subtask_id` [T]."""

    mission: str
    state: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    subtask_index: np.ndarray
    subtask_id: np.ndarray

    def __len__(self) -> int:
        return len(self.action)


def demonstrate(env: BabyAIEnv, mission: str, seed: int) -> Demonstration | None:
    """The bot's episode of `mission` on the map of `seed`, or None if it fails to finish it within
    the step limit."""
    state, _ = env.reset(seed=seed, options={"mission": mission})
    bot = BabyAIBot(env.level)
    states, actions, rewards = [], [], []
    success = False
    while not env.over:
        action = int(bot.replan())
        states.append(state)
        actions.append(action)
        state, reward, _, _, info = env.step(action)
        rewards.append(reward)
        success = info["is_success"]
    if not success:
        return None
    index, subgoal = env.tracker.labels()
    return Demonstration(
        mission=env.task_description,
        state=np.stack(states),
        action=np.asarray(actions, dtype=np.int64),
        reward=np.asarray(rewards, dtype=np.float32),
        subtask_index=index,
        subtask_id=subgoal,
    )


class BotPolicy:
    """The bot as a `rollout.MissionPolicy`: one bot per env, made at `reset` from the env itself."""

    def __init__(self) -> None:
        self.envs: Sequence[BabyAIEnv] = ()
        self.bots: list[BabyAIBot] = []

    def reset(self, envs: Sequence[BabyAIEnv]) -> None:
        self.envs = envs
        self.bots = [BabyAIBot(env.level) for env in envs]

    def __call__(self, states: np.ndarray, missions: Sequence[str]) -> np.ndarray:
        """The bots' actions for the running envs (0 for finished ones, which are not stepped)."""
        return np.array([0 if env.over else bot.replan() for env, bot in zip(self.envs, self.bots, strict=True)])
