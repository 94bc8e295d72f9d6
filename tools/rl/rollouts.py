"""Batched rollouts of a trained OCN in any batched world: free-run success per task, and each
frozen option alone on each subtask (paper table 1).

One loop per idea for every world. A world (`RolloutWorld`) says how to start a batch of episodes
(one task and env seed per env) and how the policy's postprocessed actions become env actions; its
batch simulator (`CraftBatch`, `DialBatch`) supplies `step`, `done`, `progress` and `task_len`.
Every episode of a call runs in one batch (all tasks, and for the table all option and subtask
pairs, side by side), so the policy and its pre/post-processors, which actions go through as
under `lerobot-eval`, run once per step for all of them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from lerobot_policy_ocn.envs.batching import EpisodeBatch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_STATE
from lerobot_policy_ocn.ocn import OCNPolicy
from lerobot_policy_ocn.tools.eval.parsing import Processor
from lerobot_policy_ocn.tools.viz.rollout_mcap import RolloutMcapWriter, RolloutTrace


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


@dataclass(frozen=True)
class RolloutWorld:
    """What a world contributes to the rollouts (and to PPO's, `lerobot_policy_ocn.tools.rl.ppo`).

    `new_batch(num_envs, reward, max_steps)` makes the world's batch simulator (`max_steps` None:
    the env's own limits), whose `reset(seeds=..., tasks=...)` takes task strings; `env_action`
    turns postprocessed actions [envs, A] (numpy) into what the simulator's `step` takes;
    `policy_task` names a task as the policy's tasks do.
    """

    new_batch: Callable[[int, str, int | None], EpisodeBatch]
    env_action: Callable[[np.ndarray], np.ndarray]
    policy_task: Callable[[str], str] = str

    def start(self, tasks: Sequence[str], seeds: Sequence[int]) -> tuple[EpisodeBatch, np.ndarray]:
        """A fresh batch with one env per task and env seed (sparse reward, the env's limits) and its
        first states [envs, S]."""
        batch = self.new_batch(len(tasks), "sparse", None)
        return batch, batch.reset(seeds=list(seeds), tasks=list(tasks))


def policy_inputs(obs: np.ndarray, tasks: Sequence[str], preprocessor: Processor) -> dict[str, Any]:
    """The env's states as float32, with one task string per env, through the preprocessor. The batch
    worlds give `observation.state` alone; a policy that reads more features cannot act in them."""
    return preprocessor({OBS_STATE: torch.from_numpy(obs).float(), "task": list(tasks)})


def step_envs(world: RolloutWorld, batch: EpisodeBatch, action: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Step every env with the policy's postprocessed actions; returns the new states and rewards."""
    obs, reward, *_ = batch.step(world.env_action(action.cpu().numpy()))
    return obs, reward


def _episodes_of(items: Sequence[Any], episodes: int, seed: int) -> tuple[list[Any], list[int]]:
    """`episodes` envs per item, item-major, each item's envs on env seeds seed, seed+1, ..."""
    return [item for item in items for _ in range(episodes)], [seed + k for _ in items for k in range(episodes)]


@torch.no_grad()
def free_run_success(
    policy: PreTrainedPolicy,
    preprocessor: Processor,
    postprocessor: Processor,
    world: RolloutWorld,
    tasks: Sequence[str],
    episodes: int,
    seed: int = 0,
    log: RolloutMcapWriter | None = None,
) -> dict[str, float]:
    """Success rate per task (keyed as given) of the whole policy over `episodes` fresh episodes each;
    with `log` (an `OptionPolicy` only), every step and the policy's p^c, option and termination also
    go to that MCAP."""
    rows, seeds = _episodes_of(tasks, episodes, seed)
    named = [world.policy_task(task) for task in rows]
    batch, obs = world.start(rows, seeds)
    trace = RolloutTrace()
    policy.reset()
    while not batch.done.all():
        active = ~batch.done
        action = postprocessor(policy.select_action(policy_inputs(obs, named, preprocessor)))
        if log is not None:
            step = policy.last_step
            trace.add(active=active, state=obs, action=action.cpu().numpy(), p_c=step.p_c.cpu().numpy(),
                      option=step.option.cpu().numpy(), end=step.end.cpu().numpy())
        obs, reward = step_envs(world, batch, action)
        if log is not None:
            trace.add(reward=reward, done=batch.done.copy())
    policy.reset()
    success = (batch.progress == batch.task_len).reshape(len(tasks), episodes)
    if log is not None:
        for k in range(len(tasks)):
            rows_of_task = slice(k * episodes, (k + 1) * episodes)
            log.write(named[k * episodes], trace.rows(rows_of_task), success[k])
    return {task: float(success[k].mean()) for k, task in enumerate(tasks)}


@dataclass(frozen=True)
class OptionTable:
    """Each frozen option alone on each subtask, [n_options, n_subtasks]: the fraction of episodes it
    completed (`success`, paper table 1) and the fraction its own termination stopped before the
    subtask was done (`stopped`; the rest ran out of steps). The split tells an option that gives
    up early from one that wanders."""

    success: np.ndarray
    stopped: np.ndarray


@torch.no_grad()
def option_subtask_success(
    policy: OCNPolicy,
    preprocessor: Processor,
    postprocessor: Processor,
    world: RolloutWorld,
    subtasks: Sequence[str],
    episodes: int,
    seed: int = 0,
) -> OptionTable:
    """Paper table 1: [n_options, len(subtasks)] fraction of fresh episodes of the one-subtask task
    `subtasks[j]` that option i, run alone from its initial state, completes before its termination
    fires (e > 0.5) or the env's step limit; and the fraction its termination stopped before then.

    Options of a fixed length L (MoE: 1, HIL: L) have no termination of their own (their heads are
    untrained): option i then runs on, restarting from its initial state every L steps, which is
    what it does when the controller picks it at every decision."""
    greedy = policy.config.inference_mode == "greedy"
    length = policy.config.fixed_skill_length
    n_options = policy.config.n_options
    pairs = [(i, subtask) for i in range(n_options) for subtask in subtasks]
    rows, seeds = _episodes_of(pairs, episodes, seed)
    named = [world.policy_task(subtask) for _, subtask in rows]
    batch, obs = world.start([subtask for _, subtask in rows], seeds)
    option = torch.tensor([i for i, _ in rows], dtype=torch.long)
    stopped = np.zeros(len(rows), dtype=bool)
    option_h, step = None, 0
    while not (batch.done | stopped).all():
        state = policy.observation(policy_inputs(obs, named, preprocessor))
        restart = torch.full((len(rows),), step == 0 if length is None else step % length == 0)
        action, option_h, end = policy.act_with_options(state, option, option_h, restart, greedy)
        if length is None and step > 0:
            stopped |= (end.cpu().numpy() > 0.5) & ~batch.done
        step += 1
        obs, _ = step_envs(world, batch, postprocessor(action))
    completed = (batch.progress == 1) & ~stopped
    shape = (n_options, len(subtasks), episodes)
    return OptionTable(completed.reshape(shape).mean(axis=2), stopped.reshape(shape).mean(axis=2))


def check_self_terminating(policy: OCNPolicy) -> None:
    """The oracle controller decides where an option's own termination fires: refuse options of a
    fixed length (MoE, HIL), whose termination heads are untrained."""
    if policy.config.fixed_skill_length is not None:
        raise ValueError(f"The oracle controller decides where an option's own termination fires; "
                         f"`hierarchy={policy.config.hierarchy}` options have none.")


# Where the oracle controller chooses: where the running option terminates, or where the env's subtask completes.
ORACLE_SWITCHES = ("termination", "progress")


@torch.no_grad()
def oracle_controller_success(
    policy: OCNPolicy,
    preprocessor: Processor,
    postprocessor: Processor,
    world: RolloutWorld,
    tasks: Sequence[str],
    option_of_subtask: dict[int, int],
    episodes: int,
    seed: int = 0,
    switch: str = "termination",
) -> dict[str, float]:
    """Success rate per task (keyed as given) of the frozen options under an oracle controller: at the
    first step and wherever the running option's termination fires (sampled, as in hard execution
    and PPO; e > 0.5 under greedy inference), it starts `option_of_subtask[s]` for the task's current
    subtask id s. No controller trained over these options decides better at those points, so this
    is the ceiling of finetuning them (paper 3.3): it tells options too weak to chain apart from a
    controller that has not learnt yet. `switch="progress"` takes the options' terminations out too:
    the oracle then switches where the env's subtask completes, which measures how well each option
    carries out its subtask alone; options of a fixed length L (MoE, HIL) then also restart every L
    steps, as they run when the controller picks them at every decision."""
    if switch not in ORACLE_SWITCHES:
        raise ValueError(f"switch must be one of {ORACLE_SWITCHES}, got {switch!r}.")
    if switch == "termination":
        check_self_terminating(policy)
    greedy = policy.config.inference_mode == "greedy"
    rows, seeds = _episodes_of(tasks, episodes, seed)
    named = [world.policy_task(task) for task in rows]
    batch, obs = world.start(rows, seeds)
    missing = sorted({s for e in range(len(rows)) for s in batch.task_of(e)} - option_of_subtask.keys())
    if missing:
        raise ValueError(f"No option is assigned to subtask id(s) {missing} of the tasks {list(tasks)}.")
    lookup = torch.tensor([option_of_subtask.get(s, 0) for s in range(max(option_of_subtask) + 1)])
    env_rows = np.arange(len(rows))
    option, option_h = torch.zeros(len(rows), dtype=torch.long), None
    decide = torch.ones(len(rows), dtype=torch.bool)
    length, step = policy.config.fixed_skill_length, 0
    progress = batch.progress.copy()
    while not batch.done.all():
        state = policy.observation(policy_inputs(obs, named, preprocessor))
        if option_h is not None and switch == "progress":
            decide = torch.from_numpy(batch.progress != progress) | (length is not None and step % length == 0)
        elif option_h is not None:
            _, _, end = policy.act_with_options(state, option, option_h, torch.zeros_like(decide), greedy)
            decide = end > 0.5 if greedy else torch.bernoulli(end).bool()
        progress = batch.progress.copy()
        current = batch.tasks[env_rows, np.minimum(batch.progress, batch.task_len - 1)]
        option = torch.where(decide, lookup[torch.from_numpy(current)], option)
        action, option_h, _ = policy.act_with_options(state, option, option_h, decide, greedy)
        obs, _ = step_envs(world, batch, postprocessor(action))
        step += 1
    success = (batch.progress == batch.task_len).reshape(len(tasks), episodes)
    return {task: float(success[k].mean()) for k, task in enumerate(tasks)}


def oracle_report(
    policy: OCNPolicy,
    preprocessor: Processor,
    postprocessor: Processor,
    world: RolloutWorld,
    tasks: Sequence[str],
    columns: Sequence[str],
    table: np.ndarray,
    subtask_codes: Sequence[str],
    episodes: int,
    seed: int = 0,
    switch: str = "termination",
) -> dict[str, Any]:
    """`oracle_controller_success` on `tasks` (codes), switching as `switch` says, each subtask given the
    option that completes it most often in the option x subtask `table` [options, columns] (ties: the
    lower index), with that assignment and the mean."""
    best = {code: int(table[:, j].argmax()) for j, code in enumerate(columns)}
    success = oracle_controller_success(
        policy, preprocessor, postprocessor, world, list(tasks),
        {list(subtask_codes).index(code): option for code, option in best.items()}, episodes, seed, switch,
    )
    return {"switch": switch, "option_of_subtask": best, "success_rate": success,
            "mean_success_rate": float(np.mean(list(success.values())))}

