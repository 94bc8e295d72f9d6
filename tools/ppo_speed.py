"""PPO speed measurements for `ocn-bench ppo`: where one iteration's time goes, collecting episodes
against updating the controller, for the two ways a controller decides.

The flat pool (`primitive_action_pool`) decides at every step, as MoE and flat PPO do, so its update
replays one controller step per env step: the most replay work per frame PPO can have. The OCN pool
is a random 4-option OCN under hard execution, whose controller decides only where its sampled
terminations fire. Both are built in memory over Craft's S2 tasks (no checkpoint, no dataset).
Random policies rarely finish a task, so their episodes run to the step limit; the rates are per
frame and the decisions per frame are reported with them.

The baseline of the replay's speed-up is `critic_per_step`: the critic evaluated on one decision
step at a time, as `replay_controller` evaluated it inside the recurrence before it read all the
states at once after it (same values, same gradients).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
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


class PerStep(nn.Module):
    """A network applied to the states [E, J, H] of one decision step at a time, each [E, H]."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, states: Tensor) -> Tensor:
        return torch.stack([self.net(step) for step in states.unbind(1)], 1)


@contextmanager
def critic_per_step(critic: ppo.ValueHead) -> Iterator[None]:
    """Within, `critic` (its own weights) evaluates one decision step at a time: the baseline."""
    net = critic.net
    critic.net = PerStep(net)
    try:
        yield
    finally:
        critic.net = net


def _timed_update(
    policy: OCNPolicy, weights: dict[str, Tensor], batch: Decisions, config: PPOConfig, per_step: bool
) -> float:
    """Seconds of one `update` from `weights`, by a fresh trainer whose critic is drawn from one seed
    (evaluated one step at a time with `per_step`)."""
    policy.load_state_dict(weights)
    torch.manual_seed(1)
    trainer = PPOTrainer(policy, config)
    with critic_per_step(trainer.critic) if per_step else nullcontext():
        start = time.perf_counter()
        trainer.update(batch)
        return time.perf_counter() - start


def compare_replays(policy: OCNPolicy, batch: Decisions, config: PPOConfig, rounds: int = 3) -> dict[str, float]:
    """Seconds of one PPO update of `batch`, the critic on all steps at once against one step at a
    time, from the same weights, alternated for `rounds` rounds, best of each (the policy ends updated)."""
    weights = {name: value.clone() for name, value in policy.state_dict().items()}
    best = {"at_once": float("inf"), "per_step": float("inf")}
    for _ in range(rounds):
        best["at_once"] = min(best["at_once"], _timed_update(policy, weights, batch, config, per_step=False))
        best["per_step"] = min(best["per_step"], _timed_update(policy, weights, batch, config, per_step=True))
    return {"update_s": best["at_once"], "update_critic_per_step_s": best["per_step"],
            "speedup": best["per_step"] / best["at_once"]}


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

