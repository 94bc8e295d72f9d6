"""`ocn-bench`: throughput benchmarks whose output is committed under `results/`.

`ocn-bench env` measures Craft env steps per second (one gymnasium env; 64 envs batched through
`CraftBatch` and through the gymnasium vector env) and `record_demos` frames per second end to end
(a subprocess writing a real LeRobot dataset, with and without the MCAP log). Results carry the
machine they ran on.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent.parent / "results"


def machine() -> dict:
    """What the numbers were measured on."""
    cpu = "unknown"
    if Path("/proc/cpuinfo").is_file():
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numpy": np.__version__,
    }


def _rate(step, n_steps: int, envs_per_step: int, repeats: int = 3) -> float:
    """Best of `repeats` timings of `n_steps` calls, in env steps per second."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(n_steps):
            step()
        best = min(best, time.perf_counter() - start)
    return n_steps * envs_per_step / best


def bench_env_steps(n_steps: int) -> dict:
    from envs.craft import CraftBatch, CraftEnv, CraftVectorEnv

    rng = np.random.default_rng(0)
    env = CraftEnv(task="ADC")
    env.reset(seed=0)

    def single() -> None:
        _, _, terminated, truncated, _ = env.step(int(rng.integers(5)))
        if terminated or truncated:
            env.reset()

    batch = CraftBatch(64, reward="dense", max_steps=10**9)
    batch.reset(seeds=list(range(64)), tasks=["ADC"] * 64)
    actions = rng.integers(0, 4, size=(1024, 64))  # moves only: no env finishes mid-benchmark
    counter = iter(range(10**12))

    def batched() -> None:
        batch.step(actions[next(counter) % 1024])

    vec = CraftVectorEnv(64, task="ADC")
    vec.reset(seed=0)
    vec_actions = rng.integers(0, 5, size=(1024, 64))

    def vector() -> None:
        vec.step(vec_actions[next(counter) % 1024])

    return {
        "single_env_steps_per_s": _rate(single, n_steps, 1),
        "batched_64_core_steps_per_s": _rate(batched, n_steps // 4, 64),
        "vector_env_64_steps_per_s": _rate(vector, n_steps // 4, 64),
    }


def bench_record(episodes_per_task: int, mcap: bool) -> dict:
    """Wall time of a `record_demos` subprocess, from process start to exit."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        cmd = [sys.executable, "-m", "ocn_data.record_demos", "--tasks", "AC,CD,DA", "--episodes-per-task",
               str(episodes_per_task), "--root", str(root), "--repo-id", "bench/craft_s1"]
        if mcap:
            cmd += ["--mcap", str(Path(tmp) / "demo.mcap")]
        start = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - start
        frames = json.loads((root / "meta" / "info.json").read_text())["total_frames"]
    return {
        "episodes": 3 * episodes_per_task,
        "frames": frames,
        "wall_s": wall,
        "frames_per_s": frames / wall,
        "command": " ".join(["record_demos", *cmd[3:]]),
    }


def bench_import(repeats: int = 3) -> float:
    """Seconds a fresh interpreter takes to import `record_demos` (LeRobot and torch with it); best of `repeats`."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import ocn_data.record_demos"], check=True, capture_output=True)
        best = min(best, time.perf_counter() - start)
    return best


def run_env_bench(args: argparse.Namespace) -> None:
    result = {
        "benchmark": "ocn-bench env",
        "machine": machine(),
        "note": args.note,
        "env_steps": bench_env_steps(args.steps),
        "record_demos": bench_record(args.episodes_per_task, mcap=False),
        "record_demos_with_mcap": bench_record(args.episodes_per_task, mcap=True),
        "record_demos_import_s": bench_import(),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(_markdown(result))
    print(_markdown(result))


def _markdown(r: dict) -> str:
    m, s, rec, mc = r["machine"], r["env_steps"], r["record_demos"], r["record_demos_with_mcap"]
    conditions = f"Conditions: {r['note']}\n\n" if r["note"] else ""
    return (
        "# Craft env and recording throughput\n\n"
        f"Command: `ocn-bench env`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}.\n\n"
        f"{conditions}"
        "| what | rate |\n|---|---|\n"
        f"| one `CraftEnv` (gymnasium API), random actions | {s['single_env_steps_per_s']:,.0f} steps/s |\n"
        f"| 64 envs batched, `CraftBatch.step` | {s['batched_64_core_steps_per_s']:,.0f} env steps/s |\n"
        f"| 64 envs, `CraftVectorEnv.step` (gymnasium vector API, autoreset) | "
        f"{s['vector_env_64_steps_per_s']:,.0f} env steps/s |\n"
        f"| `record_demos` S1 ({rec['episodes']} episodes, {rec['frames']} frames) end to end | "
        f"{rec['frames_per_s']:,.0f} frames/s ({rec['wall_s']:.1f} s) |\n"
        f"| the same with `--mcap` | {mc['frames_per_s']:,.0f} frames/s ({mc['wall_s']:.1f} s) |\n\n"
        "Recording times are whole subprocesses (interpreter start and imports included) writing a "
        "LeRobot v3.0 dataset with per-episode statistics and the dataset card; of each, "
        f"{r['record_demos_import_s']:.1f} s is a fresh interpreter importing `record_demos` "
        "(LeRobot and torch with it).\n"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="ocn-bench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    env = sub.add_parser("env", help="Craft stepping and record_demos throughput")
    env.add_argument("--steps", type=int, default=20000, help="single-env steps per timing")
    env.add_argument("--episodes-per-task", type=int, default=6000, help="record_demos size (S1 is 6000)")
    env.add_argument("--out", default=str(RESULTS / "bench_env.json"))
    env.add_argument("--note", default="", help="conditions of the run, stored with the results")
    env.set_defaults(func=run_env_bench)
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
