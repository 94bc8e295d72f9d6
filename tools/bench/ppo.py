"""`ocn-bench ppo`: how far PPO finetuning (`ocn-finetune`, `tools.rl.ppo`) scales with the envs it steps
together in one process: env frames per second at 64, 256 and 1024 envs on Craft's S1 and S2
finetuning tasks, with one iteration's time split into the policy's `select_action` calls, the batch
simulator's steps, the rest of collecting (processors, bookkeeping) and the PPO update.

The options are those of an OCN checkpoint (`--checkpoint`) under a fresh controller, pooled as
`ocn-finetune --checkpoint` pools them; without one, a random 3-option OCN built in memory stands in
(its options rarely finish a subtask, so its episodes run to the step limit). Either way the run is
`ocn-finetune`'s: sparse reward, the paper's PPO, one math thread.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import add_common_arguments, header, int_list

TASK_SETS = {"s1": "ADC,CAD,DCA", "s2": "BADC,ACBD,CABD"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "ppo")
    parser.add_argument("--envs", type=int_list, default="64,256,1024", help="envs stepped together, e.g. 64,256")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="a pretrained_model folder of a Craft ocn checkpoint whose options PPO finetunes "
                             "(default: a random 3-option OCN built in memory)")
    known = ", ".join(f"{name} ({tasks})" for name, tasks in TASK_SETS.items())
    parser.add_argument("--task-sets", type=task_sets, default="s1,s2",
                        help=f"finetuning task sets, comma-separated, of {known}")
    parser.add_argument("--iterations", type=int, default=2, help="timed PPO iterations per setting, after a warm-up")
    parser.add_argument("--threads", type=int, default=1, help="torch math threads (ocn-finetune's default is 1)")


def task_sets(text: str) -> list[str]:
    """Comma-separated names of `TASK_SETS`."""
    names = text.split(",")
    unknown = sorted(set(names) - set(TASK_SETS))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown task sets {unknown}; known: {sorted(TASK_SETS)}")
    return names


class Stopwatch:
    """Seconds spent inside the calls it wraps, summed until `take`."""

    def __init__(self) -> None:
        self.seconds = 0.0

    def wrap(self, call: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return call(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
        return timed

    def take(self) -> float:
        seconds, self.seconds = self.seconds, 0.0
        return seconds


def finetuning_start(checkpoint: Path | None, task_spec: str, seed: int = 0) -> tuple[Any, Any, list[str]]:
    """The policy PPO trains and how it acts (`tools.rl.ppo.Acting`) for the new tasks `task_spec`: the
    checkpoint's options under a fresh controller, or a random 3-option OCN; and the policy's task strings."""
    import dataclasses

    import torch

    from lerobot_policy_ocn.ocn import OCNPolicy
    from lerobot_policy_ocn.tools.eval.parsing import load_policy
    from lerobot_policy_ocn.tools.rl.finetuning import merge_option_pools, primitive_action_pool
    from lerobot_policy_ocn.tools.rl.ppo import Acting
    from lerobot_policy_ocn.tools.worlds import craft, policy_world

    torch.manual_seed(seed)
    if checkpoint is None:
        world = craft()
        tasks = [world.task_description(task) for task in world.parse_task_list(task_spec)]
        config = dataclasses.replace(primitive_action_pool(tasks, hidden_size=128).config, hierarchy="ocn",
                                     n_options=3)
        return OCNPolicy(config).eval(), Acting(world.rollouts()), tasks
    source, preprocessor, postprocessor = load_policy(checkpoint, types=("ocn",))
    world = policy_world(source.config.state_dim, source.config.action_dim)
    if world.name != "craft":
        raise SystemExit(f"--checkpoint {checkpoint}: this benchmark finetunes on Craft, not {world.name}")
    tasks = [world.task_description(task) for task in world.parse_task_list(task_spec)]
    policy = merge_option_pools([source], tasks, names=[str(checkpoint)])
    return policy, Acting(world.rollouts(), preprocessor, postprocessor), tasks


def iteration_times(checkpoint: Path | None, task_spec: str, n_envs: int, iterations: int) -> dict[str, Any]:
    """PPO iterations (one episode in every env, then the update) with `n_envs` envs: each part's seconds
    per env frame, from the best iteration of `iterations` after a warm-up."""
    import numpy as np

    from lerobot_policy_ocn.tools.rl.ppo import PPOConfig, PPOTrainer, collect, env_tasks

    policy, acting, tasks = finetuning_start(checkpoint, task_spec)
    envs = acting.world.new_batch(n_envs, "sparse", None)
    acting_time, stepping_time = Stopwatch(), Stopwatch()
    policy.select_action = acting_time.wrap(policy.select_action)
    envs.step = stepping_time.wrap(envs.step)
    config = PPOConfig()
    trainer = PPOTrainer(policy, config)
    env_task = env_tasks(tasks, n_envs)
    seeds = np.random.default_rng(0)
    rows = []
    for _ in range(iterations + 1):
        start = time.perf_counter()
        batch = collect(policy, envs, acting, env_task, seeds.integers(0, 2**31 - 1, n_envs), config.gamma)
        collected = time.perf_counter()
        trainer.update(batch)
        rows.append({"collect_s": collected - start, "update_s": time.perf_counter() - collected,
                     "select_action_s": acting_time.take(), "env_step_s": stepping_time.take(),
                     "frames": int(batch.frames.sum()), "decisions": int(batch.count.sum()),
                     "success": float(batch.success.mean())})
    best = min(rows[1:], key=lambda row: (row["collect_s"] + row["update_s"]) / row["frames"])
    wall = best["collect_s"] + best["update_s"]
    return {"envs": n_envs, **best, "frames_per_s": best["frames"] / wall,
            "collect_frames_per_s": best["frames"] / best["collect_s"],
            "decisions_per_frame": best["decisions"] / best["frames"],
            "trainable_params": sum(parameter.numel() for parameter in trainer.trainable)}


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    import torch

    torch.set_num_threads(args.threads)
    settings = [(name, n_envs) for name in args.task_sets for n_envs in args.envs]
    rows = [{"task_set": name, "tasks": TASK_SETS[name],
             **iteration_times(args.checkpoint, TASK_SETS[name], n_envs, args.iterations)}
            for name, n_envs in settings]
    return {"checkpoint": str(args.checkpoint) if args.checkpoint else None, "threads": args.threads,
            "iterations": args.iterations, "rows": rows}


def _share(row: dict[str, Any], key: str) -> str:
    return f"{row[key] / (row['collect_s'] + row['update_s']):.0%}"


def _scaling(r: dict[str, Any]) -> str:
    """Per task set, how the rate grows from the fewest envs to the most."""
    lines = []
    for name in dict.fromkeys(row["task_set"] for row in r["rows"]):
        mine = [row for row in r["rows"] if row["task_set"] == name]
        low, high = mine[0], mine[-1]
        lines.append(f"{name.upper()}: {high['envs']} envs run {high['frames_per_s'] / low['frames_per_s']:.2f}x the "
                     f"frames/s of {low['envs']} ({high['envs'] / low['envs']:g}x the envs); collecting alone "
                     f"{high['collect_frames_per_s'] / low['collect_frames_per_s']:.2f}x.")
    return " ".join(lines)


def markdown(r: dict[str, Any]) -> str:
    options = (f"the options of `{r['checkpoint']}` under a fresh controller" if r["checkpoint"]
               else "a random 3-option OCN built in memory (no checkpoint given)")
    rows = "".join(
        f"| {row['task_set'].upper()} ({row['tasks']}) | {row['envs']} | **{row['frames_per_s']:,.0f}** | "
        f"{row['collect_frames_per_s']:,.0f} | {_share(row, 'select_action_s')} | {_share(row, 'env_step_s')} | "
        f"{_share(row, 'update_s')} | {row['decisions_per_frame']:.2f} | {row['success']:.2f} |\n"
        for row in r["rows"]
    )
    return (
        header("PPO finetuning speed against the number of envs", r)
        + f"`ocn-finetune`'s PPO over {options}, sparse reward, {r['threads']} math thread(s), in one process. One "
        "iteration is one episode in every env, all stepped together, then the PPO update (4 epochs of "
        f"minibatches of about 256 decisions); the best of {r['iterations']} iterations after a warm-up. Each "
        "part's share is of that iteration's time.\n\n"
        "| tasks | envs | env frames/s | collecting alone (frames/s) | `select_action` | env steps | PPO update | "
        "decisions per frame | success |\n|---|---|---|---|---|---|---|---|---|\n" + rows
        + f"\n{_scaling(r)}\n\n"
        "Collecting gains from more envs while each step's fixed costs (one `select_action` call, one batched "
        "env step, the processors) are shared by more envs; the update does not, since its minibatches stay "
        "about 256 decisions: its time grows with the decisions collected. Once the per-frame cost stops "
        "falling, one process runs at what one core gives, and more frames per second need more processes: "
        "each with its own batch of envs and a share of the episodes, the update's gradients averaged between "
        f"them as DDP averages `lerobot-train`'s ({r['rows'][0]['trainable_params']:,} floats: the controller, its "
        "initial states and the critic).\n"
    )
