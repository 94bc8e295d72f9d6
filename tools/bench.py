"""`ocn-bench`: throughput benchmarks whose output is committed under `results/`.

`ocn-bench env` measures Craft env steps per second (one gymnasium env; 64 envs batched through
`CraftBatch` and through the gymnasium vector env) and `record_demos` frames per second end to end
(a subprocess writing a real LeRobot dataset, with and without the MCAP log).

`ocn-bench train` measures OCN training: real (unpadded) frames per second through a real
`lerobot-train` run on the S1 data, the same model's update alone, LeRobot's windowed
`__getitem__`, the stacked option cells against a per-option Python loop, and `select_action`
latency under `torch.inference_mode`, as `lerobot-eval` calls it (`--only latency`: that alone,
printed and not written, for checking it without the minutes of training runs).

`ocn-bench stacked` sweeps that stacked-against-looped comparison over batch sizes and math threads,
from the batch of one `select_action` env to the 512 windows that `ocn-bench train` times, to show where
stacking the options pays.

`ocn-bench view` times `ocn-view` writing an .rrd of 50 validation episodes with a trained
checkpoint, as a whole subprocess (interpreter start and imports included) and as the logging
alone that it reports.

`ocn-bench ppo` measures PPO finetuning on Craft's S2 tasks, 64 envs, one math thread: env frames
per second with collecting and updating timed apart, for a controller that decides at every step
(flat PPO and MoE) and for an OCN's, and the update's controller replay with the critic read on all steps
at once against one step at a time (`tools.ppo_speed`).

`ocn-bench dial` measures Dial env steps per second, the env's physics rate against bare
`mujoco.mj_step` on the same model and trajectory, and the expert's success over 200 two-digit
PINs, noise-free and with the DART noise it records with.

`ocn-bench clonability` measures how much of the Dial expert's control a memoryless network predicts
from the observation, with and without the digit (`tools.dial_clonability`). Results carry the
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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from tools import console_script

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
    _write(result, Path(args.out), _markdown(result))


def conditions_paragraph(r: dict) -> str:
    """A report's "Conditions:" paragraph from the run's `--note`, or nothing without one."""
    return f"Conditions: {r['note']}\n\n" if r["note"] else ""


def _write(result: dict, out: Path, markdown: str) -> None:
    """The JSON and its Markdown twin, and the Markdown on stdout."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown)
    print(markdown)


def _markdown(r: dict) -> str:
    m, s, rec, mc = r["machine"], r["env_steps"], r["record_demos"], r["record_demos_with_mcap"]
    conditions = conditions_paragraph(r)
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


def bench_dial_physics(n_steps: int) -> dict:
    """Dial env steps per second, and the env's physics rate against bare `mj_step` replaying the very
    same controls from the same start (so both integrate the identical trajectory, contacts included)."""
    import mujoco

    from envs.dial import FRAME_SKIP, DialEnv, DialVectorEnv

    controls = np.random.default_rng(0).uniform(-0.3, 0.3, size=(n_steps, 9))
    env = DialEnv(task="12", max_steps=10**9)
    env.reset(seed=0)
    start_qpos = env.batch.data[0].qpos.copy()
    counter = iter(range(10**12))

    def env_step() -> None:
        env.step(controls[next(counter) % n_steps])

    def env_run() -> None:
        env.reset(seed=0)
        for u in controls:
            env.step(u)

    model = env.batch.model
    data = mujoco.MjData(model)

    def bare_run() -> None:
        mujoco.mj_resetData(model, data)
        data.qpos[:] = start_qpos
        for u in controls:
            data.ctrl[:] = u
            mujoco.mj_step(model, data, nstep=FRAME_SKIP)

    env_rate = bare_rate = 0.0
    for _ in range(5):  # interleaved, best of 5 each: both see the same load on a shared machine
        env_rate = max(env_rate, _rate(env_run, 1, n_steps, repeats=1))
        bare_rate = max(bare_rate, _rate(bare_run, 1, n_steps, repeats=1))
    vec = DialVectorEnv(16, task="12", max_steps=10**9)
    vec.reset(seed=0)
    vec_controls = np.random.default_rng(1).uniform(-0.3, 0.3, size=(64, 16, 9))

    def vector() -> None:
        vec.step(vec_controls[next(counter) % 64])

    return {
        "frame_skip": FRAME_SKIP,
        "single_env_steps_per_s": _rate(env_step, n_steps, 1),
        "vector_env_16_steps_per_s": _rate(vector, n_steps // 16, 16),
        "replay_env_steps_per_s": env_rate,
        "replay_bare_mj_step_env_steps_per_s": bare_rate,
        "bare_mj_step_physics_steps_per_s": bare_rate * FRAME_SKIP,
        "physics_ratio": env_rate / bare_rate,
        "wrapper_overhead": 1.0 - env_rate / bare_rate,
    }


def bench_dial_expert(pins: int, noise_levels: tuple[float, ...]) -> dict:
    """Success of the Dial expert on `pins` random two-digit PINs from 1, 2, 4, 8, all run as one batch."""
    from envs.dial import DialBatch, DialExpert, sample_pin

    rng = np.random.default_rng(2024)
    tasks = [sample_pin(rng, 2, (1, 2, 4, 8)) for _ in range(pins)]
    batch = DialBatch(pins)
    batch.reset(seeds=list(range(pins)), tasks=tasks)
    expert = DialExpert(batch, noise_levels)
    expert.reset(seeds=list(range(pins)))
    success = np.zeros(pins, dtype=bool)
    start = time.perf_counter()
    while not batch.done.all():
        success |= batch.step(expert.perturb(expert.act()))[2]
    wall = time.perf_counter() - start
    steps = batch.t[success]
    return {
        "pins": pins,
        "noise_levels": list(noise_levels),
        "success": float(success.mean()),
        "failed": [list(tasks[i]) for i in np.flatnonzero(~success)],
        "steps_median": float(np.median(steps)),
        "steps_p99": float(np.percentile(steps, 99)),
        "steps_max": int(steps.max()),
        "step_limit": int(batch.max_steps[0]),
        "wall_s": wall,
    }


def run_dial_bench(args: argparse.Namespace) -> None:
    from envs.dial.expert import NOISE_LEVELS, REFERENCE_NOISE_LEVELS

    result = {
        "benchmark": "ocn-bench dial",
        "machine": machine(),
        "note": args.note,
        "env": bench_dial_physics(args.steps),
        "expert": bench_dial_expert(args.pins, (0.0,)),
        "expert_dart": bench_dial_expert(args.pins, NOISE_LEVELS),
        "expert_reference_dart": bench_dial_expert(args.pins, REFERENCE_NOISE_LEVELS),
    }
    _write(result, Path(args.out), _dial_markdown(result))


def run_clonability_bench(args: argparse.Namespace) -> None:
    import torch

    from tools import dial_clonability

    torch.set_num_threads(args.threads)
    result = {
        "benchmark": "ocn-bench clonability",
        "machine": machine(),
        "note": args.note,
        "clonability": dial_clonability.measure(args.episodes, args.fit_steps),
    }
    _write(result, Path(args.out), dial_clonability.markdown(result))


def _levels(expert: dict) -> str:
    return ", ".join(f"{level:g}" for level in expert["noise_levels"])


def _dial_markdown(r: dict) -> str:
    m, e = r["machine"], r["env"]
    conditions = conditions_paragraph(r)
    rows = "".join(
        f"| expert success, {x['pins']} random two-digit PINs from 1, 2, 4, 8, {name} | **{x['success']:.3f}** "
        f"(median {x['steps_median']:.0f} steps, p99 {x['steps_p99']:.0f}, "
        f"max {x['steps_max']} of {x['step_limit']}) |\n"
        for name, x in (("noise-free", r["expert"]),
                        (f"with DART noise as recorded (levels {_levels(r['expert_dart'])})", r["expert_dart"]),
                        (f"with the reference demonstrations' DART noise (levels "
                         f"{_levels(r['expert_reference_dart'])}; not recorded)", r["expert_reference_dart"]))
    )
    return (
        "# Dial env speed and expert success\n\n"
        f"Command: `ocn-bench dial`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}.\n\n"
        f"{conditions}"
        "| what | result |\n|---|---|\n"
        f"| one `DialEnv` (gymnasium API), random controls | {e['single_env_steps_per_s']:,.0f} env steps/s "
        f"({e['single_env_steps_per_s'] * e['frame_skip']:,.0f} physics steps/s) |\n"
        f"| 16 envs, `DialVectorEnv.step` | {e['vector_env_16_steps_per_s']:,.0f} env steps/s |\n"
        f"| bare `mujoco.mj_step(nstep={e['frame_skip']})`, same model, same controls and start | "
        f"{e['replay_bare_mj_step_env_steps_per_s']:,.0f} env steps/s "
        f"({e['bare_mj_step_physics_steps_per_s']:,.0f} physics steps/s) |\n"
        f"| `DialEnv` replaying those controls | {e['replay_env_steps_per_s']:,.0f} env steps/s |\n"
        f"| physics rate of the env / bare `mj_step` | **{e['physics_ratio']:.3f}** (wrapper overhead "
        f"{e['wrapper_overhead']:.1%}; goal: under 20%) |\n"
        f"{rows}\n"
        "The replay rows integrate the identical trajectory (same start pose, same controls), so their ratio is "
        "the cost of the env around the physics: observation, press detection, rewards, gymnasium API. "
        "The replay timings are interleaved, best of 5 each; the other rates are the best of 3.\n"
    )


def _log_rates(log: str) -> list[dict[str, float]]:
    """`lerobot-train`'s periodic lines: per-step update and data-wait seconds and real frames."""
    rows = []
    for line in log.splitlines():
        if " step:" not in line or "frames_used:" not in line:
            continue
        fields = dict(part.split(":", 1) for part in line.split() if ":" in part and not part.startswith("20"))
        rows.append({k: float(fields[k]) for k in ("step", "updt_s", "data_s", "frames_used") if k in fields})
    return rows


def bench_lerobot_train(root: Path, steps: int, batch_size: int, workers: int, window: int, device: str,
                        packed: bool = False, threads: int = 1) -> dict:
    """A real `lerobot-train --policy.type=ocn` run on `root` (`packed`: a packed view) with `threads` math
    threads; rates from its own step timings, skipping the first logged interval (worker start-up)."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            console_script("lerobot-train"), "--policy.type=ocn", "--dataset.repo_id=local/craft_s1",
            f"--dataset.root={root}", f"--policy.device={device}", "--policy.push_to_hub=false", "--wandb.enable=false",
            "--env_eval_freq=0", f"--steps={steps}", f"--batch_size={batch_size}", f"--num_workers={workers}",
            "--log_freq=25", f"--save_freq={steps}", f"--policy.window_size={window}", f"--output_dir={tmp}/run",
            *(["--policy.window_start=packed"] if packed else []),
        ]
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
        done = subprocess.run(command, check=True, capture_output=True, text=True, env=env)
    rows = _log_rates(done.stdout + done.stderr)[1:]
    if not rows:
        raise RuntimeError("lerobot-train logged no step timings")
    step_s = float(np.mean([r["updt_s"] + r["data_s"] for r in rows]))
    frames = float(np.mean([r["frames_used"] for r in rows]))
    return {
        "steps": steps,
        "batch_size": batch_size,
        "num_workers": workers,
        "threads": threads,
        "window_size": window,
        "step_s": step_s,
        "update_s": float(np.mean([r["updt_s"] for r in rows])),
        "data_wait_s": float(np.mean([r["data_s"] for r in rows])),
        "real_frames_per_step": frames,
        "real_frames_per_s": frames / step_s,
    }


def bench_getitem(roots: list[Path], window: int, packed: Path, items: int = 300, rounds: int = 5) -> list[float]:
    """Seconds per `LeRobotDataset.__getitem__` of one training sample: a window of OCN's episode
    windows for each of `roots`, one row of the `packed` view; interleaved, best of `rounds`, as the
    VM's speed drifts from minute to minute."""
    from lerobot.datasets import LeRobotDataset

    offsets = [i / 10 for i in range(1 - window, window)]
    datasets = [LeRobotDataset("local/craft_s1", root=root,
                               delta_timestamps={"observation.state": offsets, "action": offsets}) for root in roots]
    datasets.append(LeRobotDataset("local/craft_s1", root=packed))
    picks = np.random.default_rng(0).integers(0, min(len(ds) for ds in datasets), items)
    best = [float("inf")] * len(datasets)
    for _ in range(rounds):
        for k, ds in enumerate(datasets):
            ds[0]
            start = time.perf_counter()
            for i in picks:
                ds[int(i)]
            best[k] = min(best[k], (time.perf_counter() - start) / items)
    return best


def bench_update(root: Path, batch_size: int, window: int, threads: int, device: str) -> dict:
    """The model's forward + backward on real S1 episodes, without LeRobot's data loading."""
    from ocn_data.episodes_table import load_episodes
    from policies.ocn import OCNConfig, OCNPolicy
    from policies.ocn.benchmark import (compare_restarts_ahead_vs_each_step, compare_running_vs_every_row,
                                        torch_threads, train_frames_per_second)
    from lerobot.configs.types import FeatureType, PolicyFeature

    import torch

    episodes = load_episodes(root, range(batch_size))
    pad = window - episodes.state.shape[1]
    state = np.pad(episodes.state, ((0, 0), (0, pad), (0, 0)))
    action = np.pad(episodes.action, ((0, 0), (0, pad), (0, 0)))
    config = OCNConfig(
        device=device, window_size=window, window_start="any", tasks=sorted(set(episodes.tasks)),
        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (state.shape[-1],))},
        output_features={"action": PolicyFeature(FeatureType.ACTION, (1,))},
    )
    batch = {
        "observation.state": torch.from_numpy(state).float().to(device),
        "action": torch.from_numpy(action).float().to(device),
        "action_is_pad": torch.from_numpy(np.pad(~episodes.mask, ((0, 0), (0, pad)), constant_values=True)).to(device),
        "task": episodes.tasks,
    }
    with torch_threads(threads):
        policy = OCNPolicy(config).to(device)
        padded_fps = train_frames_per_second(policy, batch)
        against_every_row = compare_running_vs_every_row(policy, batch)
        against_each_step = compare_restarts_ahead_vs_each_step(policy, batch)
    real = float(episodes.lengths.sum()) / (batch_size * window)
    return {"threads": threads, "padded_frames_per_s": padded_fps, "real_frames_per_s": padded_fps * real,
            "running_vs_every_row": against_every_row, "restarts_ahead_vs_each_step": against_each_step}


def bench_select_action(device: str = "cpu") -> dict[str, float]:
    """Seconds per `select_action` step of the benchmark policy, for 1 and 64 envs."""
    from policies.ocn.benchmark import make_bench_policy, select_action_latency

    policy = make_bench_policy(device=device)
    return {
        "batch_1": select_action_latency(policy, batch_size=1),
        "batch_64": select_action_latency(policy, batch_size=64),
    }


def run_train_bench(args: argparse.Namespace) -> None:
    device = accelerator(args.device)  # before any work: a missing GPU is a clear error, not a failed lerobot-train
    if args.only == "latency":
        result = {"machine": machine(), "device": device, "load_average": os.getloadavg(),
                  "select_action_s": bench_select_action(args.device)}
        print(json.dumps(result, indent=2))
        return

    from ocn_data.packed_view import packed_view
    from ocn_data.training_view import training_view
    from policies.ocn.benchmark import compare_stacked_vs_loop

    root = Path(args.root)
    if not (root / "meta" / "info.json").exists():
        subprocess.run(
            [console_script("record_demos"), "--env", "craft", "--tasks", "AC,CD,DA",
             "--episodes-per-task", "6000", "--root", str(root), "--repo-id", "local/craft_s1", "--seed", "0"],
            check=True, capture_output=True,
        )
    view, packed = training_view(root, "local/craft_s1"), packed_view(root, "local/craft_s1", args.window)
    # The recorded dataset, its training view and its packed view in turn, then the packed view with one
    # data worker and two math threads (a packed row loads in well under a millisecond: does the second
    # core serve the update better than a second worker?); best of `--train-rounds` runs each.
    settings = {"lerobot_train": (root, args.workers, 1), "lerobot_train_view": (view, args.workers, 1),
                "lerobot_train_packed": (packed, args.workers, 1), "lerobot_train_packed_threads": (packed, 1, 2)}
    runs: dict[str, list[dict]] = {name: [] for name in settings}
    for _ in range(args.train_rounds):
        for name, (data, workers, threads) in settings.items():
            runs[name].append(bench_lerobot_train(data, args.steps, args.batch_size, workers, args.window, args.device,
                                                  packed=data == packed, threads=threads))
    best = {name: max(done, key=lambda run: run["real_frames_per_s"]) for name, done in runs.items()}
    getitem, getitem_view, getitem_packed = bench_getitem([root, view], args.window, packed)
    result = {
        "benchmark": "ocn-bench train",
        "machine": machine(),
        "device": device,
        "note": args.note,
        "train_rounds": args.train_rounds,
        **best,
        "getitem_s_per_window": getitem,
        "getitem_view_s_per_window": getitem_view,
        "getitem_packed_s_per_row": getitem_packed,
        # CPU threads only matter to a CPU update; a GPU one is measured once.
        "update_only": [bench_update(root, args.batch_size, args.window, t, args.device)
                        for t in ((1, 2) if args.device == "cpu" else (1,))],
        "stacked_vs_loop": compare_stacked_vs_loop(batch_size=512, window=32, threads=2, device=args.device),
        "select_action_s": bench_select_action(args.device),
    }
    _write(result, Path(args.out), _train_markdown(result))


def accelerator(device: str) -> dict:
    """What the model ran on: the CPU, or the named GPU (an error when torch sees none)."""
    import torch

    if device == "cpu":
        return {"type": "cpu"}
    if not torch.cuda.is_available():
        raise SystemExit(f"--device {device}: torch {torch.__version__} sees no CUDA device on this machine")
    return {"type": "cuda", "name": torch.cuda.get_device_name(device), "torch": torch.__version__,
            "cuda": torch.version.cuda}


def _on_cpu(r: dict) -> bool:
    return r["device"]["type"] == "cpu"


def _device_flag(r: dict) -> str:
    return "" if _on_cpu(r) else f" --device {r['device']['type']}"


def _device_words(r: dict) -> str:
    d = r["device"]
    return "the CPU" if _on_cpu(r) else f"{d['name']} (torch {d['torch']}, CUDA {d['cuda']})"


def _lerobot_train_row(what: str, t: dict) -> str:
    threads = t.get("threads", 1)
    return (f"| `lerobot-train --policy.type=ocn` on {what}, batch {t['batch_size']}, {t['num_workers']} "
            f"worker{'s' if t['num_workers'] != 1 else ''}, {threads} math thread{'s' if threads != 1 else ''}, "
            f"window {t['window_size']} | {t['real_frames_per_s']:,.0f} real frames/s "
            f"({t['step_s']:.2f} s/step: update {t['update_s']:.2f} s, waiting for data {t['data_wait_s']:.2f} s) |\n")


def _train_markdown(r: dict) -> str:
    m, t, loop, sa = r["machine"], r["lerobot_train"], r["stacked_vs_loop"], r["select_action_s"]
    view, getitem, getitem_view = r["lerobot_train_view"], r["getitem_s_per_window"], r["getitem_view_s_per_window"]
    packed, getitem_packed = r["lerobot_train_packed"], r["getitem_packed_s_per_row"]
    threaded = r["lerobot_train_packed_threads"]
    conditions = conditions_paragraph(r)
    updates = "".join(
        f"| the same update alone on real S1 episodes, {u['threads']} thread(s) | "
        f"{u['real_frames_per_s']:,.0f} real frames/s ({u['padded_frames_per_s']:,.0f} with padding) |\n"
        + (f"| the same update stepping every row to the window's end, padding included (as before "
           f"`OCNCore.unroll_frames`; alternated, best of 3) | stepping only the rows still in their episode is "
           f"{u['running_vs_every_row']['speedup']:.2f}x faster |\n" if "running_vs_every_row" in u else "")
        + (f"| the same update with the options' restarted branch computed in each step (as before "
           f"`OCNCore.restarts_ahead`; alternated, best of 3) | computing it for the whole window in one call is "
           f"{u['restarts_ahead_vs_each_step']['speedup']:.2f}x faster |\n"
           if "restarts_ahead_vs_each_step" in u else "")
        for u in r["update_only"]
    )
    return (
        "# OCN training and inference speed\n\n"
        f"Command: `ocn-bench train{_device_flag(r)}`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}. "
        f"Model and updates on: {_device_words(r)}.\n\n"
        f"{conditions}"
        "| what | rate |\n|---|---|\n"
        + _lerobot_train_row("S1", t)
        + _lerobot_train_row("S1's training view (`ocn_data.training_view`)", view)
        + f"| the training view's speed-up of `lerobot-train` (runs in turn, best of {r['train_rounds']} each) | "
        f"{view['real_frames_per_s'] / t['real_frames_per_s']:.2f}x |\n"
        + _lerobot_train_row("S1's packed view (`ocn_data.packed_view`, `--policy.window_start=packed`)", packed)
        + f"| the packed view's speed-up of `lerobot-train` over the training view (same runs) | "
        f"{packed['real_frames_per_s'] / view['real_frames_per_s']:.2f}x |\n"
        + _lerobot_train_row("the packed view", threaded)
        + f"| one worker and two math threads against {packed['num_workers']} workers and one (same runs) | "
        f"{threaded['real_frames_per_s'] / packed['real_frames_per_s']:.2f}x |\n"
        f"{updates}"
        f"| LeRobot's windowed `__getitem__` (one episode window, {2 * t['window_size'] - 1} frames) | "
        f"{getitem * 1e3:.1f} ms per window |\n"
        f"| the same on the training view (the two interleaved, best of 5 each) | "
        f"{getitem_view * 1e3:.1f} ms per window ({getitem / getitem_view:.2f}x faster) |\n"
        f"| the same for one row of the packed view (a whole episode) | {getitem_packed * 1e3:.2f} ms per row "
        f"({getitem_view / getitem_packed:.1f}x faster than a window of the training view) |\n"
        f"| stacked options, forward + backward [512 x 32]{', 2 threads' if _on_cpu(r) else ''} | "
        f"{loop['stacked_frames_per_s']:,.0f} frames/s |\n"
        f"| per-option Python loop, same weights and batch | {loop['loop_frames_per_s']:,.0f} frames/s "
        f"(stacked is {loop['speedup']:.2f}x) |\n"
        f"| `select_action` in inference mode (as `lerobot-eval`), 1 env | {sa['batch_1'] * 1e3:.2f} ms per step |\n"
        f"| `select_action` in inference mode, 64 envs | {sa['batch_64'] * 1e3:.2f} ms per step |\n"
    )


def run_stacked_bench(args: argparse.Namespace) -> None:
    """The stacked option cells against the per-option loop, for every pool size, batch size and thread count."""
    from policies.ocn.benchmark import compare_stacked_vs_loop

    hidden_size = 128  # the S1 policy's width
    settings = [(n_options, batch, threads) for n_options in args.options for threads in args.threads
                for batch in args.batch_sizes]
    rows = []
    for n_options, batch, threads in tqdm(settings, desc="stacked vs loop", unit="setting"):
        ratio = compare_stacked_vs_loop(batch_size=batch, window=args.window, threads=threads, rounds=args.rounds,
                                        n_options=n_options, hidden_size=hidden_size)
        rows.append({"n_options": n_options, "batch_size": batch, "threads": threads, **ratio,
                     "overhead_bound": overhead_bound(n_options, args.window)})
    result = {"benchmark": "ocn-bench stacked", "machine": machine(), "note": args.note, "window": args.window,
              "hidden_size": hidden_size, "rounds": args.rounds, "rows": rows}
    _write(result, Path(args.out), _stacked_markdown(result))


def overhead_bound(n_options: int, window: int) -> float:
    """The stacked-against-loop ratio where per-op overhead is all the cost, one matmul chain per cell
    stacked and one per option looped: each of the window's T steps runs the continuing options and the
    controller (1 + N chains looped, 2 stacked), and the restarted options run once for the whole window
    (`OCNCore.restarts_ahead`: N chains looped, 1 stacked)."""
    return (window * (1 + n_options) + n_options) / (2 * window + 1)


def _stacked_markdown(r: dict) -> str:
    m = r["machine"]
    conditions = conditions_paragraph(r)
    rows = "".join(
        f"| {row['n_options']} | {row['batch_size']} | {row['threads']} | {row['stacked_frames_per_s']:,.0f} | "
        f"{row['loop_frames_per_s']:,.0f} | **{row['speedup']:.2f}x** | {row['overhead_bound']:.2f}x |\n"
        for row in r["rows"]
    )
    return (
        "# Stacked option cells against a per-option loop\n\n"
        f"Command: `ocn-bench stacked`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; on the CPU.\n\n"
        f"{conditions}"
        f"One forward + backward of a whole OCN (N options and the controller, width {r['hidden_size']}) over a "
        f"batch of windows of {r['window']} steps, with the cells stacked (`policies.ocn.cell.StackedCell`: one "
        "batched matmul per layer for all options) and with the same weights evaluated one option at a time in a "
        "Python loop (`policies.ocn.benchmark.LoopedCell`). The two alternate, "
        f"{r['rounds']} rounds, and the fastest run of each counts.\n\n"
        "Each step runs the continuing option cells and the controller; the restarted option cells (eq. 17's "
        "other branch) read no recurrent state and run once for the whole window (`OCNCore.restarts_ahead`). "
        "Where per-op overhead is all the cost, the loop launches 1 + N matmul chains per step and N per window "
        "where stacking launches 2 and 1, and the mixing between them is the same, so the ratio stays below "
        f"(T(1 + N) + N) / (2T + 1) for windows of T steps (`overhead bound`: "
        f"{overhead_bound(3, r['window']):.2f}x for 3 options); where the matmuls are large it tends to 1, the "
        "same arithmetic either way.\n\n"
        "| options | windows per batch | math threads | stacked (frames/s) | loop (frames/s) | stacked against loop "
        "| overhead bound |\n"
        "|---|---|---|---|---|---|---|\n" + rows
    )


def run_view_bench(args: argparse.Namespace) -> None:
    """Whole `ocn-view --save` subprocesses, best of `--repeats`, and the .rrd written."""
    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(tmp) / "view.rrd"
        command = [console_script("ocn-view"), "--root", args.root, "--repo-id", args.repo_id, "--split", "val",
                   "--episodes", str(args.episodes), "--policy", args.policy, "--save", str(rrd)]
        walls, outputs = [], []
        for _ in range(args.repeats):
            rrd.unlink(missing_ok=True)
            start = time.perf_counter()
            outputs.append(subprocess.run(command, check=True, capture_output=True, text=True).stdout)
            walls.append(time.perf_counter() - start)
        size = rrd.stat().st_size
    logged = outputs[int(np.argmin(walls))].strip().splitlines()[-1]
    result = {
        "benchmark": "ocn-bench view",
        "machine": machine(),
        "note": args.note,
        "command": " ".join(["ocn-view", *command[1:-1], "FILE.rrd"]),
        "wall_s": min(walls),
        "all_wall_s": walls,
        "ocn_view_says": logged,
        "rrd_bytes": size,
    }
    m = result["machine"]
    conditions = f"Conditions: {args.note}\n\n" if args.note else ""
    markdown = (
        "# ocn-view speed\n\n"
        f"Command: `ocn-bench view`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}.\n\n"
        f"{conditions}"
        f"`{result['command']}` as a whole subprocess: **{result['wall_s']:.1f} s** (best of {args.repeats}; "
        f"goal: under 30 s), writing a {size / 1e6:.1f} MB .rrd. Its own report of the logging alone: "
        f"\"{logged}\".\n"
    )
    _write(result, Path(args.out), markdown)


def run_ppo_bench(args: argparse.Namespace) -> None:
    """`tools.ppo_speed` for each pool, on one math thread."""
    import torch

    from tools.ppo_speed import POOLS, S2_TASKS, bench_pool_iterations

    torch.set_num_threads(1)
    result = {
        "benchmark": "ocn-bench ppo",
        "machine": machine(),
        "note": args.note,
        "tasks": S2_TASKS,
        "iterations": args.iterations,
        "pools": [bench_pool_iterations(kind, args.envs, args.iterations) for kind in POOLS],
    }
    _write(result, Path(args.out), _ppo_markdown(result))


def _ppo_markdown(r: dict) -> str:
    m = r["machine"]
    conditions = conditions_paragraph(r)
    what = {"flat": "flat pool (a decision every step, as flat PPO and MoE)",
            "ocn": "random 4-option OCN (decisions where terminations fire)"}
    rows = []
    for p in r["pools"]:
        replay = p["replay"]
        rows.append(
            f"| {what[p['pool']]} | {p['frames_per_s']:,.0f} | {p['decisions_per_frame']:.2f} | "
            f"{p['collect_s']:.2f} | {p['update_s']:.2f} | {replay['update_critic_per_step_s']:.2f} s against "
            f"{replay['update_s']:.2f} s: **{replay['speedup']:.2f}x** |"
        )
    return (
        "# PPO finetuning speed\n\n"
        f"Command: `ocn-bench ppo`. Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}; "
        "one math thread, as `ocn-finetune` runs.\n\n"
        f"{conditions}"
        f"One PPO iteration is one episode in each of {r['pools'][0]['envs']} Craft envs on S2's tasks "
        f"({r['tasks']}, sparse reward) and the update of the paper's PPO (4 epochs, minibatches of about "
        "256 decisions). The pools are random, built in memory, so their episodes run to the step limit. "
        f"Best of {r['iterations']} iterations after a warm-up. "
        "The last column times one update of the same batch from "
        "the same weights with the critic evaluated one decision step at a time (as it was inside the "
        "controller's recurrence before) and on all steps at once after the recurrence (now), alternated, "
        "best of three each.\n\n"
        "| controller | env frames/s | decisions per frame | collect (s) | update (s) | "
        "update, critic per step against at once |\n|---|---|---|---|---|---|\n"
        + "\n".join(rows) + "\n"
    )


def _int_list(text: str) -> list[int]:
    """A comma-separated list of positive integers, e.g. `1,8,64`."""
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def _bench(sub: Any, name: str, func: Callable[[argparse.Namespace], None], help: str) -> argparse.ArgumentParser:
    """A benchmark's subcommand, with the --out and --note every benchmark takes."""
    parser = sub.add_parser(name, help=help)
    parser.add_argument("--out", default=str(RESULTS / f"bench_{name}.json"))
    parser.add_argument("--note", default="", help="conditions of the run, stored with the results")
    parser.set_defaults(func=func)
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="ocn-bench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    env = _bench(sub, "env", run_env_bench, "Craft stepping and record_demos throughput")
    env.add_argument("--steps", type=int, default=20000, help="single-env steps per timing")
    env.add_argument("--episodes-per-task", type=int, default=6000, help="record_demos size (S1 is 6000)")
    train = _bench(sub, "train", run_train_bench,
                   "OCN training throughput, stacked vs looped options, select_action latency")
    train.add_argument("--root", default="outputs/bench/craft_s1", help="S1 dataset (recorded there if missing)")
    train.add_argument("--steps", type=int, default=150, help="lerobot-train steps")
    train.add_argument("--batch-size", type=int, default=128)
    train.add_argument("--workers", type=int, default=2, help="lerobot-train --num_workers")
    train.add_argument("--window", type=int, default=24, help="--policy.window_size")
    train.add_argument("--train-rounds", type=int, default=2,
                       help="lerobot-train runs on the dataset, its training view and its packed view, in turn; "
                            "the best of each counts")
    train.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                       help="where lerobot-train and the timed updates run; data loading stays on the CPU")
    train.add_argument("--only", choices=["latency"],
                       help="measure select_action latency alone and print it as JSON (nothing is written)")
    dial = _bench(sub, "dial", run_dial_bench,
                  "Dial env steps/s, its physics rate against bare mj_step, expert success")
    dial.add_argument("--steps", type=int, default=2000, help="env steps per timing")
    dial.add_argument("--pins", type=int, default=200, help="random two-digit PINs for the expert success rate")
    clonability = _bench(sub, "clonability", run_clonability_bench,
                         "how much of the Dial expert's control a memoryless MLP predicts, from what")
    clonability.add_argument("--episodes", type=int, default=200, help="two-digit PINs recorded")
    clonability.add_argument("--fit-steps", type=int, default=4000, help="Adam steps per fit")
    clonability.add_argument("--threads", type=int, default=1, help="torch math threads")
    stacked = _bench(sub, "stacked", run_stacked_bench, "stacked option cells against a per-option loop, swept")
    stacked.add_argument("--options", type=_int_list, default=[3, 6],
                         help="options in the pool, e.g. 3,6 (the S1 policy's 3 and the paper's 6-option ablation)")
    stacked.add_argument("--batch-sizes", type=_int_list, default=[1, 8, 64, 512],
                         help="windows per batch, e.g. 1,8,64")
    stacked.add_argument("--threads", type=_int_list, default=[1, 2], help="math threads, e.g. 1,2")
    stacked.add_argument("--window", type=int, default=32, help="steps per window")
    stacked.add_argument("--rounds", type=int, default=3, help="alternated timings of each; the fastest counts")
    view = _bench(sub, "view", run_view_bench, "ocn-view writing an .rrd of 50 episodes with a trained checkpoint")
    view.add_argument("--root", default="outputs/reproduce/craft_s1", help="a recorded Craft dataset")
    view.add_argument("--repo-id", default="local/craft_s1")
    view.add_argument("--policy", default="outputs/reproduce/imitation_s1/3options_T10/seed1/train/checkpoints/last/"
                      "pretrained_model", help="a trained ocn checkpoint (from ocn-reproduce imitation-s1)")
    view.add_argument("--episodes", type=int, default=50, help="validation episodes to log")
    view.add_argument("--repeats", type=int, default=3)
    ppo = _bench(sub, "ppo", run_ppo_bench,
                 "PPO env frames/s on S2, collect against update, the controller replay's speed-up")
    ppo.add_argument("--envs", type=int, default=64, help="envs stepped together (ocn-finetune's default)")
    ppo.add_argument("--iterations", type=int, default=3, help="timed iterations per pool, after one warm-up")
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
