"""Batched rollouts of a trained policy in Craft: free-run success per task, and each option alone
(for a policy made of options, `OptionPolicy`).

All episodes of a task run as one `CraftBatch`, so the policy sees one batch per step. Actions go
through the policy's own pre/post-processors, as under `lerobot-eval`.
"""

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from tqdm import tqdm

from envs.craft.batch import CraftBatch
from envs.craft.lerobot_env import action_indices
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_STATE
from policies.ocn import OCNPolicy
from tools.episode_parsing import Processor
from tools.rollout_mcap import RolloutMcapWriter, RolloutTrace


@runtime_checkable
class OptionPolicy(Protocol):
    """A policy made of options that can act alone (OCN): what the option x subtask table runs, and
    whose per-step option choice (`last_step`, after each `select_action`) a rollout log records."""

    last_step: Any

    def act_with_options(
        self,
        state: torch.Tensor,
        option: torch.Tensor,
        option_h: torch.Tensor | None,
        restart: torch.Tensor,
        greedy: bool,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]: ...


def _observation(obs: np.ndarray, task: str, preprocessor: Processor) -> dict[str, Any]:
    """The env's int states as float32, with the task string, through the preprocessor."""
    return preprocessor({OBS_STATE: torch.from_numpy(obs).float(), "task": [task] * obs.shape[0]})


def _fresh_maps(task: str, episodes: int, mode: str, seed: int) -> tuple[CraftBatch, np.ndarray]:
    """`episodes` envs of one task on the maps of seeds seed, seed+1, ...; returns them and their states."""
    craft = CraftBatch(episodes, mode=mode, reward="sparse")
    return craft, craft.reset(seeds=range(seed, seed + episodes), tasks=[task] * episodes)


def _step(craft: CraftBatch, action: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Step every env with the policy's (float) action indices; returns the new states and rewards."""
    obs, reward, *_ = craft.step(action_indices(action.cpu().numpy()))
    return obs, reward


@torch.no_grad()
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
    rates = {}
    for task in tqdm(tasks, desc="free run", leave=False):
        craft, obs = _fresh_maps(task, episodes, mode, seed)
        trace = RolloutTrace()
        policy.reset()
        while not craft.done.all():
            active = ~craft.done
            action = postprocessor(policy.select_action(_observation(obs, task, preprocessor)))
            if log is not None:
                step = policy.last_step
                trace.add(active=active, state=obs, action=action.cpu().numpy(), p_c=step.p_c.cpu().numpy(),
                          option=step.option.cpu().numpy(), end=step.end.cpu().numpy())
            obs, reward = _step(craft, action)
            if log is not None:
                trace.add(reward=reward, done=craft.done.copy())
        success = craft.progress == craft.task_len
        if log is not None:
            log.write(task, trace, success)
        rates[task] = float(success.mean())
    policy.reset()
    return rates


@torch.no_grad()
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
    greedy = policy.config.inference_mode == "greedy"
    table = np.zeros((policy.config.n_options, len(subtasks)))
    for j, subtask in enumerate(tqdm(subtasks, desc="option x subtask", leave=False)):
        for i in range(policy.config.n_options):
            craft, obs = _fresh_maps(subtask, episodes, mode, seed)
            option = torch.full((episodes,), i, dtype=torch.long)
            stopped = np.zeros(episodes, dtype=bool)
            option_h, first = None, True
            while not (craft.done | stopped).all():
                batch = _observation(obs, subtask, preprocessor)
                restart = torch.full((episodes,), first)
                action, option_h, end = policy.act_with_options(batch[OBS_STATE], option, option_h, restart, greedy)
                if not first:
                    stopped |= (end.cpu().numpy() > 0.5) & ~craft.done
                first = False
                obs, _ = _step(craft, postprocessor(action))
            table[i, j] = float(((craft.progress == 1) & ~stopped).mean())
    return table
