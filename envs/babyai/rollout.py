"""Free runs: any policy acting alone in fresh episodes of given missions, and whether it succeeds.

A policy sees what a LeRobot policy sees, the state vectors [B, STATE_DIM] and the mission
strings, and returns one action index per env; `reset` starts it on a new set of episodes (a
recurrent policy clears its memory there; an expert such as `expert.BotPolicy` takes hold of the
envs). All episodes run side by side, one policy call per step for the whole batch; an env that
has finished keeps its last state and ignores its actions. Success is minigrid's own verdict: the
level ends the episode with a positive reward when the whole mission is done.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv


class MissionPolicy(Protocol):
    def reset(self, envs: Sequence[BabyAIEnv]) -> None: ...

    def __call__(self, states: np.ndarray, missions: Sequence[str]) -> np.ndarray: ...


def run_missions(policy: MissionPolicy, missions: Sequence[str], seeds: Sequence[int]) -> np.ndarray:
    """Success (bool [len(missions)]) of `policy` on each mission, on the map of the matching seed,
    within the level's step limit."""
    if len(missions) != len(seeds):
        raise ValueError(f"got {len(missions)} missions for {len(seeds)} seeds")
    envs = [BabyAIEnv() for _ in missions]
    states = np.stack([env.reset(seed=int(s), options={"mission": m})[0] for env, m, s in zip(
        envs, missions, seeds, strict=True)])
    success = np.zeros(len(envs), dtype=bool)
    policy.reset(envs)
    while not all(env.over for env in envs):
        actions = np.asarray(policy(states, list(missions))).reshape(-1)
        for i, env in enumerate(envs):
            if not env.over:
                states[i], _, _, _, info = env.step(int(actions[i]))
                success[i] = info["is_success"]
    return success
