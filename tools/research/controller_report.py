"""What a finetuned controller does over its frozen options, and how far it is from their ceiling.

`python -m lerobot_policy_ocn.tools.research.controller_report --policy RUN/pretrained_model --tasks BADC,ACBD,CABD
--out F.json`
runs an OCN checkpoint whose controller `ocn-finetune` trained (any OCN over self-terminating options)
on its tasks, under hard execution with sampling as PPO trained it, and writes:

- `option_subtask_success`: each frozen option alone on each subtask the tasks hold (paper table 1),
  and from it the option each subtask is best served by (`option_of_subtask`);
- `oracle_controller`: success per task when that option is started on the current subtask wherever
  the running option terminates: the ceiling of any controller over these options;
- per task, `success_rate`, mean episode length of successes and failures, and every decision the
  learnt controller made, grouped by (subtasks done, current subtask, option chosen, the subtask
  that option serves best): how often, and how many steps the option then ran. A decision whose
  option serves another subtask than the current one is a detour (`detour_share`).

No dataset is needed: the world is read from the checkpoint's widths, the subtasks from the tasks.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lerobot_policy_ocn.ocn import OCNPolicy
from lerobot_policy_ocn.tools.rl import rollouts
from lerobot_policy_ocn.tools.eval.parsing import Processor, load_policy
from lerobot_policy_ocn.tools.rl.rollouts import RolloutWorld, policy_inputs, step_envs
from lerobot_policy_ocn.tools.worlds import World, policy_world


@torch.no_grad()
def controller_decisions(
    policy: OCNPolicy, preprocessor: Processor, postprocessor: Processor, world: RolloutWorld,
    task: str, option_subtask: dict[int, str], subtask_codes: tuple[str, ...], episodes: int, seed: int = 0,
) -> dict[str, Any]:
    """`episodes` episodes of `task` (as the world's rollouts take it) with the whole policy, each
    decision of its controller recorded with the subtask in progress; `option_subtask` names the
    subtask each option serves best."""
    named = [world.policy_task(task)] * episodes
    batch, obs = world.start([task] * episodes, [seed + k for k in range(episodes)])
    rows = np.arange(episodes)
    running: list[tuple[tuple[int, str, int, str], int] | None] = [None] * episodes
    durations: dict[tuple[int, str, int, str], list[int]] = defaultdict(list)
    policy.reset()
    while not batch.done.all():
        active = ~batch.done
        current = batch.tasks[rows, np.minimum(batch.progress, batch.task_len - 1)]
        action = postprocessor(policy.select_action(policy_inputs(obs, named, preprocessor)))
        step = policy.last_step
        for e in np.flatnonzero(step.decided.cpu().numpy() & active):
            if running[e] is not None:
                key, began = running[e]
                durations[key].append(int(batch.t[e]) - began)
            option = int(step.option[e])
            key = (int(batch.progress[e]), subtask_codes[current[e]], option, option_subtask[option])
            running[e] = (key, int(batch.t[e]))
        obs, _ = step_envs(world, batch, action)
    policy.reset()
    for e, last in enumerate(running):
        if last is not None:
            durations[last[0]].append(int(batch.t[e]) - last[1])
    success = batch.progress == batch.task_len
    decisions = [
        {"done": done, "subtask": subtask, "option": option, "option_serves": serves, "count": len(steps),
         "mean_steps": round(float(np.mean(steps)), 2)}
        for (done, subtask, option, serves), steps in sorted(durations.items())
    ]
    total = sum(d["count"] for d in decisions)
    return {
        "success_rate": float(success.mean()),
        "mean_length_success": float(batch.t[success].mean()) if success.any() else None,
        "mean_length_failure": float(batch.t[~success].mean()) if (~success).any() else None,
        "decisions_per_episode": total / episodes,
        "detour_share": sum(d["count"] for d in decisions if d["option_serves"] != d["subtask"]) / max(total, 1),
        "decisions": decisions,
    }


def report(policy_path: Path, task_spec: str, episodes: int, rollouts_per_cell: int, seed: int) -> dict[str, Any]:
    """Everything the module docstring lists, as the JSON it writes."""
    policy, preprocessor, postprocessor = load_policy(policy_path)
    rollouts.check_self_terminating(policy)
    world: World = policy_world(policy.config.state_dim, policy.config.action_dim)
    parsed = world.parse_task_list(task_spec)
    codes = [world.task_code(task) for task in parsed]
    descriptions = [world.task_description(task) for task in parsed]
    keys = [world.task_key(description) for description in descriptions]  # as the rollouts take them
    subtasks = world.used_subtasks(descriptions)
    acting = world.rollouts()
    torch.manual_seed(seed)
    table = rollouts.option_subtask_success(policy, preprocessor, postprocessor, acting, subtasks,
                                            rollouts_per_cell, seed).success
    option_subtask = {i: subtasks[int(table[i].argmax())] for i in range(table.shape[0])}
    return {
        "policy": str(policy_path),
        "tasks": codes,
        "seed": seed,
        "option_subtask_success": {"subtasks": subtasks, "table": table.round(4).tolist()},
        "oracle_controller": rollouts.oracle_report(policy, preprocessor, postprocessor, acting, codes, subtasks,
                                                    table, world.subtask_codes, rollouts_per_cell, seed),
        "controller": {
            code: controller_decisions(policy, preprocessor, postprocessor, acting, key, option_subtask,
                                       world.subtask_codes, episodes, seed)
            for code, key in zip(codes, keys, strict=True)
        },
    }


def summary_lines(result: dict[str, Any]) -> list[str]:
    """One line per task: the learnt controller against the oracle, and its detours."""
    oracle = result["oracle_controller"]["success_rate"]
    return [
        f"{task}: controller {c['success_rate']:.3f}, oracle {oracle[task]:.3f}, "
        f"{c['decisions_per_episode']:.2f} decisions per episode, {c['detour_share']:.2f} of them detours"
        for task, c in result["controller"].items()
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lerobot_policy_ocn.tools.research.controller_report",
                                     description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--policy", type=Path, required=True, help="a pretrained_model folder written by ocn-finetune")
    parser.add_argument("--tasks", required=True, help="the tasks to run, as ocn-finetune --tasks writes them")
    parser.add_argument("--episodes", type=int, default=300, help="episodes per task of the learnt controller")
    parser.add_argument("--rollouts", type=int, default=200,
                        help="episodes per option x subtask cell and per task under the oracle")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    result = report(args.policy, args.tasks, args.episodes, args.rollouts, args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print("\n".join(summary_lines(result)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
