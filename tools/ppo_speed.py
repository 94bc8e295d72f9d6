"""PPO speed measurements for `ocn-bench ppo`: where one iteration's time goes, collecting episodes
against updating the controller, for the two ways a controller decides.

The flat pool (`primitive_action_pool`) decides at every step, as MoE and flat PPO do, so its update
replays one controller step per env step: the most replay work per frame PPO can have. The OCN pool
is a random 4-option OCN under hard execution, whose controller decides only where its sampled
terminations fire. Both are built in memory over Craft's S2 tasks (no checkpoint, no dataset).
Random policies rarely finish a task, so their episodes run to the step limit; the rates are per
frame and the decisions per frame are reported with them.

The baseline of the replay's speed-up is `critic_inside_the_loop`: the critic evaluated at every
controller step inside the recurrence, as `replay_controller` did before it read all the states at
once after it (same values, same gradients).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

import tools.ppo as ppo
from policies.ocn import OCNPolicy
from tools.ocn_finetune import primitive_action_pool
from tools.ppo import Acting, Decisions, PPOConfig, PPOTrainer, collect, env_tasks
from tools.worlds import craft

S2_TASKS = "BADC,ACBD,CABD"
POOLS = ("flat", "ocn")


def bench_pool(kind: str, tasks: list[str], seed: int = 0) -> OCNPolicy:
    """The flat pool (a decision per step), or a random 4-option OCN of the same widths (`kind` "ocn")."""
    torch.manual_seed(seed)
    flat = primitive_action_pool(tasks, hidden_size=128)
    if kind == "flat":
        return flat
    if kind != "ocn":
        raise ValueError(f"pool must be one of {POOLS}, got {kind!r}")
    return OCNPolicy(dataclasses.replace(flat.config, hierarchy="ocn", n_options=4)).eval()


@contextmanager
def critic_inside_the_loop() -> Iterator[None]:
    """Within, `replay_controller` runs the critic at every controller step: the baseline."""

    def per_step(policy: OCNPolicy, critic: nn.Module, state: Tensor, task_index: Tensor) -> tuple[Tensor, Tensor]:
        core = policy.core
        projected = core.controller.project(policy.encoder(state.transpose(0, 1).contiguous()))
        controller_h = core.controller_init[task_index]
        logits, values = [], []
        for x in projected.unbind(0):
            step_logits, controller_h = core.decide(x, controller_h)
            logits.append(step_logits)
            values.append(critic(controller_h))
        return torch.stack(logits, 1), torch.stack(values, 1)

    hoisted = ppo.replay_controller
    ppo.replay_controller = per_step
    try:
        yield
    finally:
        ppo.replay_controller = hoisted


def _timed_update(policy: OCNPolicy, weights: dict[str, Tensor], batch: Decisions, config: PPOConfig) -> float:
    """Seconds of one `update` from `weights`, by a fresh trainer whose critic is drawn from one seed."""
    policy.load_state_dict(weights)
    torch.manual_seed(1)
    trainer = PPOTrainer(policy, config)
    start = time.perf_counter()
    trainer.update(batch)
    return time.perf_counter() - start


def compare_replays(policy: OCNPolicy, batch: Decisions, config: PPOConfig, rounds: int = 3) -> dict[str, float]:
    """Seconds of one PPO update of `batch`, the critic after the recurrence against inside it, from
    the same weights, alternated for `rounds` rounds, best of each (the policy ends updated)."""
    weights = {name: value.clone() for name, value in policy.state_dict().items()}
    best = {"after": float("inf"), "inside": float("inf")}
    for _ in range(rounds):
        best["after"] = min(best["after"], _timed_update(policy, weights, batch, config))
        with critic_inside_the_loop():
            best["inside"] = min(best["inside"], _timed_update(policy, weights, batch, config))
    return {"update_s": best["after"], "update_critic_inside_s": best["inside"],
            "speedup": best["inside"] / best["after"]}


def bench_pool_iterations(kind: str, n_envs: int = 64, iterations: int = 3, seed: int = 0) -> dict[str, Any]:
    """PPO iterations of `kind`'s pool on S2 with sparse reward, `n_envs` envs, one math thread (as
    `ocn-finetune` runs): collect and update timed apart, best iteration of `iterations` after a
    warm-up, and the replay comparison on the last batch."""
    world = craft()
    tasks = [world.task_description(task) for task in world.parse_task_list(S2_TASKS)]
    policy = bench_pool(kind, tasks, seed)
    acting = Acting(world.rollouts())  # identity processors: the pools are built in memory
    envs = acting.world.new_batch(n_envs, "sparse", None)
    config = PPOConfig()
    trainer = PPOTrainer(policy, config)
    env_task = env_tasks(tasks, n_envs)
    seeds = np.random.default_rng(seed)
    rows = []
    for _ in range(iterations + 1):
        start = time.perf_counter()
        batch = collect(policy, envs, acting, env_task, seeds.integers(0, 2**31 - 1, n_envs), config.gamma)
        collected = time.perf_counter()
        trainer.update(batch)
        rows.append({"collect_s": collected - start, "update_s": time.perf_counter() - collected,
                     "frames": int(batch.frames.sum()), "decisions": int(batch.count.sum())})
    best = min(rows[1:], key=lambda row: (row["collect_s"] + row["update_s"]) / row["frames"])
    return {
        "pool": kind,
        "envs": n_envs,
        **best,
        "frames_per_s": best["frames"] / (best["collect_s"] + best["update_s"]),
        "decisions_per_frame": best["decisions"] / best["frames"],
        "replay": compare_replays(policy, batch, config),
    }

