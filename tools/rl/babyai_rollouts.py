"""BabyAI as a world of the batched rollouts (`lerobot_policy_ocn.tools.rl.rollouts`: free-run success per
mission, and each option alone on each subgoal), the counterpart of `lerobot_policy_ocn.tools.rl.craft_rollouts`.

`BabyAIBatch` runs one `lerobot_policy_ocn.envs.babyai.env.BabyAIEnv` per episode with the bookkeeping every
batch simulator keeps (`lerobot_policy_ocn.envs.batching.EpisodeBatch`), so that the rollouts run BabyAI as they
run Craft and Dial: one policy call per step for every episode side by side, as
`lerobot_policy_ocn.envs.babyai.rollout.run_missions` runs any policy, and the same verdicts: minigrid's own
success (`info["is_success"]`), the subgoals completed so far (`info["progress"]`), the level's step limit
(64 steps a subgoal). An env seed and a mission per episode, as `run_missions` takes them, so the bot's rate
on the same (mission, seed) pairs (`bot_success`) is what a policy's is compared with.

Tasks are mission strings, or a subgoal's short code ("open_red", the option table's columns), run
as the one-subgoal mission the level accepts for evaluations.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lerobot_policy_ocn.envs.babyai.missions import SINGLE, SUBGOALS, Mission, parse_mission
from lerobot_policy_ocn.envs.batching import EpisodeBatch, reset_ids
from lerobot_policy_ocn.tools.rl import rollouts

# Short names of the six subgoals, by subtask id (`missions.SUBGOALS`): table columns and entity names.
SUBGOAL_CODES = ("open_red", "open_green", "open_blue", "pick_ball", "pick_box", "pick_key")
REWARDS = ("sparse", "dense")


def mission_of(task: str) -> Mission:
    """The mission a task names: a subgoal code alone, or a mission string of the level."""
    if task in SUBGOAL_CODES:
        return Mission(SINGLE, (SUBGOAL_CODES.index(task),))
    return parse_mission(task)


def policy_task(task: str) -> str:
    """How the policy's task table names a task: the mission string (a code becomes its subgoal's text)."""
    return SUBGOALS[SUBGOAL_CODES.index(task)] if task in SUBGOAL_CODES else task


class BabyAIBatch(EpisodeBatch):
    """`num_envs` BabyAI episodes stepped together; the level decides success and the step limit."""

    def __init__(self, num_envs: int, reward: str = "sparse") -> None:
        from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv
        from lerobot_policy_ocn.envs.babyai.level import STEPS_PER_SUBGOAL

        super().__init__(num_envs, reward, REWARDS, None)
        self.envs = [BabyAIEnv() for _ in range(num_envs)]
        self.steps_per_subgoal = STEPS_PER_SUBGOAL
        self.obs: np.ndarray | None = None

    def reset(self, seeds: Sequence[int], tasks: Sequence[str]) -> np.ndarray:
        """Every env starts the mission of its task on the map of its seed; returns the states [envs, 148]."""
        ids = reset_ids(self.num_envs, None, seeds=seeds, tasks=tasks)
        missions = [mission_of(task) for task in tasks]
        self._store_tasks(ids, [m.subgoals for m in missions], lambda n: self.steps_per_subgoal * n)
        self._restart(ids)
        self.obs = np.stack([env.reset(seed=int(seed), options={"mission": mission.text})[0]
                             for env, seed, mission in zip(self.envs, seeds, missions, strict=True)])
        return self.obs

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """One action index per env; finished envs keep their last state and ignore theirs."""
        active = ~self.done
        progress = self.progress.copy()
        success = np.zeros(self.num_envs, dtype=bool)
        for i in np.flatnonzero(active):
            env = self.envs[i]
            self.obs[i], _, _, _, info = env.step(int(actions[i]))
            progress[i], success[i] = info["progress"], info["is_success"]
        sub_done = progress - self.progress
        self.progress, self.t = progress, self.t + active
        over = np.array([env.over for env in self.envs])
        terminated, truncated = success & active, over & ~success & active
        self.done = self.done | over
        reward = (sub_done if self.reward == "dense" else terminated).astype(np.float32)
        return self.obs, reward, terminated, truncated, {"progress": progress.copy(), "is_success": success}


def _new_batch(num_envs: int, reward: str, max_steps: int | None) -> BabyAIBatch:
    """A batch at the level's own step limit (minigrid's env ends the episode there)."""
    if max_steps is not None:
        raise ValueError(f"BabyAI episodes run to the level's step limit; a limit of {max_steps} cannot be set.")
    return BabyAIBatch(num_envs, reward)


BABYAI_WORLD = rollouts.RolloutWorld(
    new_batch=_new_batch, env_action=lambda actions: np.rint(actions.reshape(len(actions), -1)[:, 0]).astype(np.int64),
    policy_task=policy_task,
)


def bot_success(missions: Sequence[str], episodes: int, seed: int) -> dict[str, float]:
    """The BabyAI bot's success rate per mission on the (mission, seed) pairs the rollouts draw
    (`episodes` per mission, env seeds seed, seed + 1, ...), run by
    `lerobot_policy_ocn.envs.babyai.rollout.run_missions`."""
    from lerobot_policy_ocn.envs.babyai.expert import BotPolicy
    from lerobot_policy_ocn.envs.babyai.rollout import run_missions

    rows = [mission for mission in missions for _ in range(episodes)]
    seeds = [seed + k for _ in missions for k in range(episodes)]
    success = run_missions(BotPolicy(), rows, seeds).reshape(len(missions), episodes)
    return {mission: float(success[k].mean()) for k, mission in enumerate(missions)}
