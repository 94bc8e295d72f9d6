"""Batched rollouts of a trained policy in Craft: free-run success per task, and each option alone
(for a policy made of options, `tools.rollouts.OptionPolicy`).

The loops live in `tools.rollouts`; Craft supplies fresh maps (one `CraftBatch`, a map seed per
episode: seed, seed+1, ... for each task) and turns the policy's float actions into action indices.
"""

from collections.abc import Sequence

import numpy as np

from envs.craft.batch import CraftBatch
from envs.craft.lerobot_env import action_indices
from lerobot.policies.pretrained import PreTrainedPolicy
from policies.ocn import OCNPolicy
from tools import rollouts
from tools.episode_parsing import Processor
from tools.rollout_mcap import RolloutMcapWriter


def craft_world(mode: str = "paper") -> rollouts.RolloutWorld:
    """Craft for `tools.rollouts`: one fresh map per env, from its seed."""

    def start(tasks: Sequence[str], seeds: Sequence[int]) -> tuple[CraftBatch, np.ndarray]:
        craft = CraftBatch(len(tasks), mode=mode, reward="sparse")
        return craft, craft.reset(seeds=seeds, tasks=tasks)

    return rollouts.RolloutWorld(start=start, env_action=action_indices)


def free_run_success(
    policy: PreTrainedPolicy,
    preprocessor: Processor,
    postprocessor: Processor,
    tasks: Sequence[str],
    episodes: int,
    mode: str = "paper",
    seed: int = 0,
    log: RolloutMcapWriter | None = None,
) -> dict[str, float]:
    """Success rate per task of the whole policy over `episodes` fresh maps each (seeds seed, seed+1, ...);
    with `log` (an `OptionPolicy` only), every step and the policy's p^c, option and termination also
    go to that MCAP."""
    return rollouts.free_run_success(
        policy, preprocessor, postprocessor, craft_world(mode), tasks, episodes, seed, log
    )


def option_subtask_success(
    policy: OCNPolicy,
    preprocessor: Processor,
    postprocessor: Processor,
    subtasks: Sequence[str],
    episodes: int,
    mode: str = "paper",
    seed: int = 0,
) -> np.ndarray:
    """Paper table 1: [n_options, len(subtasks)] fraction of fresh maps on which option i, run alone
    from its initial state, completes subtask j (a one-subtask task) before its termination fires
    (e > 0.5) or the env's step limit."""
    return rollouts.option_subtask_success(
        policy, preprocessor, postprocessor, craft_world(mode), subtasks, episodes, seed
    )
