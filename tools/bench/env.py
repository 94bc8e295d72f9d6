"""`ocn-bench env`: Craft env steps per second (one gymnasium env; 64 envs batched through `CraftBatch`
and through the gymnasium vector env) and `record_demos` frames per second end to end (a subprocess
writing a real LeRobot dataset, with and without the MCAP log)."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.tools.bench.common import add_common_arguments, best_rate, header, run_timed, typed

S1_TASKS = "AC,CD,DA"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "env")
    parser.add_argument("--steps", type=int, default=20000, help="single-env steps per timing")
    parser.add_argument("--episodes-per-task", type=int, default=2000,
                        help="record_demos size, per task of S1 (AC, CD, DA), as the plain S1 command records")


def env_rates(n_steps: int) -> dict[str, float]:
    """Env steps per second: one `CraftEnv` under random actions, and 64 envs batched both ways."""
    import numpy as np

    from lerobot_policy_ocn.envs.craft import CraftBatch, CraftEnv, CraftVectorEnv

    rng = np.random.default_rng(0)
    env = CraftEnv(task="ADC")
    env.reset(seed=0)

    def single() -> None:
        _, _, terminated, truncated, _ = env.step(int(rng.integers(5)))
        if terminated or truncated:
            env.reset()

    batch = CraftBatch(64, reward="dense", max_steps=10**9)
    batch.reset(seeds=list(range(64)), tasks=["ADC"] * 64)
    moves = rng.integers(0, 4, size=(1024, 64))  # moves only: no env finishes mid-benchmark
    vector = CraftVectorEnv(64, task="ADC")
    vector.reset(seed=0)
    actions = rng.integers(0, 5, size=(1024, 64))
    counter = iter(range(10**12))
    return {
        "single_env_steps_per_s": best_rate(single, n_steps, 1),
        "batched_64_core_steps_per_s": best_rate(lambda: batch.step(moves[next(counter) % 1024]), n_steps // 4, 64),
        "vector_env_64_steps_per_s": best_rate(lambda: vector.step(actions[next(counter) % 1024]), n_steps // 4, 64),
    }


def record_rate(episodes_per_task: int, mcap: bool) -> dict[str, Any]:
    """Wall time of a `record_demos` subprocess of S1, from process start to exit."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        command = [console_script("record_demos"), "--env", "craft", "--tasks", S1_TASKS, "--episodes-per-task",
                   str(episodes_per_task), "--root", str(root), "--repo-id", "local/s1"]
        if mcap:
            command += ["--mcap", str(Path(tmp) / "demo.mcap")]
        wall, _ = run_timed(command)
        frames = json.loads((root / "meta" / "info.json").read_text())["total_frames"]
    return {"episodes": 3 * episodes_per_task, "frames": frames, "wall_s": wall, "frames_per_s": frames / wall,
            "command": typed(command).replace(str(root), "R").replace(str(Path(tmp) / "demo.mcap"), "demo.mcap")}


def import_seconds(repeats: int = 3) -> float:
    """Seconds a fresh interpreter takes to import `record_demos` (LeRobot and torch with it); best of `repeats`."""
    command = [sys.executable, "-c", "import lerobot_policy_ocn.ocn_data.record_demos"]
    return min(run_timed(command)[0] for _ in range(repeats))


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    return {
        "env_steps": env_rates(args.steps),
        "record_demos": record_rate(args.episodes_per_task, mcap=False),
        "record_demos_with_mcap": record_rate(args.episodes_per_task, mcap=True),
        "record_demos_import_s": import_seconds(),
    }


def markdown(r: dict[str, Any]) -> str:
    s, rec, mc = r["env_steps"], r["record_demos"], r["record_demos_with_mcap"]
    return (
        header("Craft env and recording throughput", r)
        + "| what | rate |\n|---|---|\n"
        f"| one `CraftEnv` (gymnasium API), random actions | {s['single_env_steps_per_s']:,.0f} steps/s |\n"
        f"| 64 envs batched, `CraftBatch.step` | {s['batched_64_core_steps_per_s']:,.0f} env steps/s |\n"
        f"| 64 envs, `CraftVectorEnv.step` (gymnasium vector API, autoreset) | "
        f"{s['vector_env_64_steps_per_s']:,.0f} env steps/s |\n"
        f"| `{rec['command']}` ({rec['episodes']} episodes, {rec['frames']} frames) end to end | "
        f"{rec['frames_per_s']:,.0f} frames/s ({rec['wall_s']:.1f} s) |\n"
        f"| the same with `--mcap` | {mc['frames_per_s']:,.0f} frames/s ({mc['wall_s']:.1f} s) |\n\n"
        "The env rates are the best of 3 timings. Recording times are whole subprocesses (interpreter start and "
        "imports included) writing a LeRobot v3.0 dataset with per-episode statistics and the dataset card; of "
        f"each, {r['record_demos_import_s']:.1f} s is a fresh interpreter importing `record_demos` (LeRobot and "
        "torch with it).\n"
    )
