"""`ocn-bench train`: OCN training with LeRobot's train loop in 1, 2, ... processes, one run after the other
in one invocation, on the same S1 dataset, the same global batch, steps and seed: real (unpadded) frames
per second from `lerobot-train`'s own step timings, and the parse quality (`ocn-eval` NMI and F1@1) of
each run's checkpoint after the same number of samples.

N processes run `torchrun --standalone --nproc_per_node N lerobot-train ...`, each with batch B / N for a
global batch B (DDP over gloo on the CPU, NCCL on GPUs). What bounds the ratio is measured beside it:
the update alone at batch B and B / N in one process (the recurrence steps through the longest episode
of the batch whatever its size, so halving the batch does not halve the update), the all-reduce of the
gradients and of a single number between N processes (DDP's per-step communication and the
latency of the small all-reduces of the global batch statistics), and the data wait `lerobot-train` logs.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.tools.bench.common import (TEARDOWN_GRACE_S, TEARDOWN_STOPPED, add_common_arguments, header,
                                                  int_list, run_timed, typed)

REPO_ID = "local/s1"
S1_TASKS = "AC,CD,DA"
# The small all-reduces of one training step of the Craft recipe (lerobot_policy_ocn.distributed): the usage
# balance's share (2) and the episode means of the NLL and the expected NLL (1 each) in the forward,
# the share's gradient in the backward. DDP's gradient buckets come on top.
SMALL_ALLREDUCES_PER_STEP = 5


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "train")
    parser.add_argument("--processes", type=int_list, default="1,2",
                        help="process counts to train with, one run each, e.g. 1,2")
    parser.add_argument("--root", type=Path, default=Path("outputs/bench/craft_s1"),
                        help="the S1 dataset (recorded there by record_demos if missing)")
    parser.add_argument("--episodes-per-task", type=int, default=2000, help="record_demos size when --root is missing")
    parser.add_argument("--steps", type=int, default=1000, help="lerobot-train steps of every run")
    parser.add_argument("--batch-size", type=int, default=128,
                        help="global batch: each of N processes trains on batch-size / N")
    parser.add_argument("--workers", type=int, default=1, help="lerobot-train --num_workers of each process")
    parser.add_argument("--threads", type=int, default=1, help="math threads of each process (OMP_NUM_THREADS)")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                        help="--policy.device of the runs (cuda: one GPU per process)")
    parser.add_argument("--seed", type=int, default=1, help="lerobot-train --seed of every run")
    parser.add_argument("--eval-rollouts", type=int, default=10,
                        help="ocn-eval --rollouts (the parse scores do not depend on it)")


def check_setup(args: argparse.Namespace) -> dict[str, Any]:
    """Refuse settings that cannot run before any work; what the model runs on."""
    bad = [n for n in args.processes if args.batch_size % n]
    if bad:
        raise SystemExit(f"--batch-size {args.batch_size} does not split evenly over {bad} processes")
    if args.device == "cpu":
        return {"type": "cpu"}
    import torch

    if torch.cuda.device_count() < max(args.processes):
        raise SystemExit(f"--device cuda with {max(args.processes)} processes needs as many GPUs; torch "
                         f"{torch.__version__} sees {torch.cuda.device_count()}")
    return {"type": "cuda", "name": torch.cuda.get_device_name(0), "count": torch.cuda.device_count(),
            "torch": torch.__version__, "cuda": torch.version.cuda}


def ensure_dataset(root: Path, episodes_per_task: int) -> str | None:
    """Record S1 at `root` with the plain command if nothing is there; returns that command, if run."""
    if (root / "meta" / "info.json").exists():
        return None
    command = [console_script("record_demos"), "--env", "craft", "--tasks", S1_TASKS, "--episodes-per-task",
               str(episodes_per_task), "--root", str(root), "--repo-id", REPO_ID]
    run_timed(command)
    return typed(command)


def train_command(processes: int, args: argparse.Namespace, out: Path) -> list[str]:
    """`lerobot-train` of OCN on the dataset, in `processes` processes through torchrun (one: plainly)."""
    launch = ([console_script("torchrun"), "--standalone", f"--nproc_per_node={processes}"] if processes > 1
              else [])
    return [*launch, console_script("lerobot-train"), "--policy.type=ocn", f"--policy.device={args.device}",
            f"--dataset.repo_id={REPO_ID}", f"--dataset.root={args.root}", f"--steps={args.steps}",
            f"--batch_size={args.batch_size // processes}", f"--num_workers={args.workers}",
            f"--log_freq={max(1, args.steps // 20)}", f"--save_freq={args.steps}", f"--seed={args.seed}",
            f"--output_dir={out}", "--wandb.enable=false", "--policy.push_to_hub=false"]


def logged_steps(log: str) -> list[dict[str, float]]:
    """`lerobot-train`'s periodic lines: the step, update and data-wait seconds (the slowest process's) and
    the real frames of a process's batch (the mean over the processes)."""
    rows = []
    for line in log.splitlines():
        fields = dict(re.findall(r" (step|updt_s|data_s|frames_used):([-0-9.]+[KMB]?)", line))
        if {"step", "updt_s", "data_s", "frames_used"} <= fields.keys():
            rows.append({key: float(value.rstrip("KMB")) * {"K": 1e3, "M": 1e6, "B": 1e9}.get(value[-1], 1)
                         for key, value in fields.items()})
    return rows


def parse_scores(checkpoint: Path, root: Path, out: Path, rollouts: int, device: str) -> dict[str, Any]:
    """`ocn-eval`'s NMI and F1@1 of a checkpoint on the dataset's validation split."""
    command = [console_script("ocn-eval"), "--policy", str(checkpoint), "--root", str(root), "--repo-id", REPO_ID,
               "--out", str(out), "--rollouts", str(rollouts), "--device", device, "--force"]
    wall, _ = run_timed(command)
    scores = json.loads(out.read_text())
    return {"nmi": scores["nmi"], "f1_tol1": scores["f1_tol1"], "eval_wall_s": wall}


def train_run(processes: int, args: argparse.Namespace, workdir: Path) -> dict[str, Any]:
    """One `lerobot-train` run in `processes` processes: its rates from the logged step timings (the first
    logged interval left out: start-up), its whole wall time, and its checkpoint's parse scores."""
    out = workdir / f"processes_{processes}"
    command = train_command(processes, args, out)
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "MKL_NUM_THREADS": str(args.threads)}
    wall, log = run_timed(command, env=env, ends_at="End of training")
    rows = logged_steps(log)[1:]
    if not rows:
        raise RuntimeError(f"lerobot-train logged no step timings:\n{log[-4000:]}")
    update = statistics.fmean(row["updt_s"] for row in rows)
    data = statistics.fmean(row["data_s"] for row in rows)
    frames = statistics.fmean(row["frames_used"] for row in rows) * processes
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    return {
        "processes": processes,
        "batch_per_process": args.batch_size // processes,
        "global_batch": args.batch_size,
        "steps": args.steps,
        "samples": args.batch_size * args.steps,
        "command": typed(command).replace(str(out), "O").replace(str(args.root), "R"),
        "effective_batch_logged": re.search(r"Effective batch size: [^\n]*", log).group(0),
        "wall_s": wall,
        "teardown_stopped": TEARDOWN_STOPPED in log,
        "update_s": update,
        "data_wait_s": data,
        "step_s": update + data,
        "real_frames_per_step": frames,
        "real_frames_per_s": frames / (update + data),
        "num_params": int(re.search(r"num_learnable_params=(\d+)", log).group(1)),
        **parse_scores(checkpoint, args.root, workdir / f"eval_{processes}.json", args.eval_rollouts, args.device),
    }


def _allreduce_worker(rank: int, world: int, rendezvous: str, n_floats: int, device: str, repeats: int,
                      out: str) -> None:
    """One of `world` processes timing all-reduces of `n_floats` floats and of one (rank 0 saves the medians)."""
    import torch
    import torch.distributed as dist

    torch.set_num_threads(1)
    backend = "nccl" if device == "cuda" else "gloo"
    dist.init_process_group(backend, init_method=f"file://{rendezvous}", rank=rank, world_size=world)
    where = torch.device("cuda", rank) if device == "cuda" else torch.device("cpu")
    medians = {}
    for name, size in (("gradients", n_floats), ("one_number", 1)):
        buffer = torch.zeros(size, device=where)
        times = []
        for _ in range(repeats + 1):
            dist.barrier()
            start = time.perf_counter()
            dist.all_reduce(buffer)
            if device == "cuda":
                torch.cuda.synchronize(where)
            times.append(time.perf_counter() - start)
        medians[name] = statistics.median(times[1:])
    if rank == 0:
        Path(out).write_text(json.dumps(medians))
    dist.destroy_process_group()


def allreduce_seconds(n_floats: int, processes: int, device: str, repeats: int = 50) -> dict[str, float]:
    """Median seconds of one all-reduce among `processes` processes of `n_floats` floats (the gradients, as
    DDP sends them each step) and of one float (a global batch statistic's latency)."""
    import torch.multiprocessing as mp

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "medians.json"
        mp.spawn(_allreduce_worker, args=(processes, str(Path(tmp) / "rendezvous"), n_floats, device, repeats,
                                          str(out)), nprocs=processes, join=True)
        return json.loads(out.read_text())


def update_alone(root: Path, batch_sizes: list[int], device: str, threads: int, seed: int = 0) -> list[dict[str, Any]]:
    """Seconds of one forward + backward of the default OCN built from the dataset, for each batch size, on
    frames drawn as LeRobot's sampler draws them (each stands for its episode; held-out episodes leave
    the batch), and the sequential steps of that batch (its longest episode)."""
    import torch

    from lerobot_policy_ocn.tools.bench.models import (dataset_policy, sampled_batch, torch_threads,
                                                       update_seconds)

    rows = []
    with torch_threads(threads):
        policy = dataset_policy(root, REPO_ID, device, seed)
        memory = policy._episodes
        frames = torch.Generator().manual_seed(seed)
        for size in batch_sizes:
            batch = sampled_batch(policy, size, frames)
            episode = batch["episode_index"].cpu()
            trained = episode[memory.trainable[episode]]
            rows.append({"batch": size, "update_s": update_seconds(policy, batch),
                         "sequential_steps": int(memory.length[trained].max()) if len(trained) else 0})
    return rows


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    device = check_setup(args)
    recorded = ensure_dataset(args.root, args.episodes_per_task)
    with tempfile.TemporaryDirectory() as tmp:
        runs = [train_run(processes, args, Path(tmp)) for processes in args.processes]
    params = runs[0]["num_params"]
    return {
        "device": device,
        "dataset": {"root": str(args.root), "recorded_by": recorded},
        "seed": args.seed,
        "threads_per_process": args.threads,
        "workers_per_process": args.workers,
        "runs": runs,
        "update_alone": update_alone(args.root, [args.batch_size // n for n in args.processes], args.device,
                                     args.threads),
        "allreduce_s": {str(n): allreduce_seconds(params, n, args.device) for n in args.processes if n > 1},
    }


def _run_row(run: dict[str, Any], first: dict[str, Any]) -> str:
    return (f"| {run['processes']} | {run['batch_per_process']} | {run['real_frames_per_s']:,.0f} | "
            f"**{run['real_frames_per_s'] / first['real_frames_per_s']:.2f}x** | {run['step_s']:.3f} "
            f"(update {run['update_s']:.3f}, data {run['data_wait_s']:.3f}) | {run['wall_s']:.0f} | "
            f"{run['nmi']:.3f} | {run['f1_tol1']:.3f} |\n")


def _bounds(r: dict[str, Any]) -> str:
    """The measurements that bound the ratio, as Markdown rows."""
    alone = {row["batch"]: row for row in r["update_alone"]}
    full = alone[r["runs"][0]["global_batch"]]
    lines = []
    for run in r["runs"][1:]:
        shard = alone[run["batch_per_process"]]
        comm = r["allreduce_s"][str(run["processes"])]
        lines.append(
            f"| {run['processes']} | {shard['update_s']:.3f} s at batch {shard['batch']} ({shard['sequential_steps']} "
            f"sequential steps) against {full['update_s']:.3f} s at {full['batch']} ({full['sequential_steps']}): "
            f"at most **{full['update_s'] / shard['update_s']:.2f}x** from computing alone | "
            f"{comm['gradients'] * 1e3:.2f} ms for the gradients, {comm['one_number'] * 1e6:.0f} us for one number "
            f"(x {SMALL_ALLREDUCES_PER_STEP} a step) | {run['data_wait_s']:.3f} s |\n")
    return "".join(lines)


def markdown(r: dict[str, Any]) -> str:
    runs, first = r["runs"], r["runs"][0]
    device = "the CPU" if r["device"]["type"] == "cpu" else f"{r['device']['count']} x {r['device']['name']}"
    megabytes = first["num_params"] * 4 / 1e6
    launch = "\n".join(f"    {run['command']}\n      (its log: {run['effective_batch_logged']})" for run in runs)
    bounds = ""
    if len(runs) > 1:
        bounds = (
            "\nWhat bounds the ratio (measured in the same invocation; one process each, one math thread):\n\n"
            "| processes | update alone, one process's share of the batch against the whole | one all-reduce "
            "between the processes | data wait per step |\n|---|---|---|---|\n" + _bounds(r)
            + "\nThe recurrence runs one step after another through the longest episode of the batch, whatever the "
            "batch's size, so a process with half the batch still runs as many sequential steps, each on "
            "narrower matmuls: the update alone does not halve, and that ratio is the ceiling of N processes on "
            f"N free cores. The gradients are {first['num_params']:,} floats ({megabytes:.1f} MB), all-reduced "
            f"by DDP at every step; {SMALL_ALLREDUCES_PER_STEP} all-reduces of single numbers carry the global "
            "batch's statistics (the usage balance and the episode means, `distributed`). Each process "
            f"also has {r['workers_per_process']} data worker(s) and holds the whole dataset in memory; with "
            f"{r['machine']['cores']} cores, N processes and their workers share them.\n"
        )
    return (
        header("OCN training in several processes", r)
        + f"`lerobot-train --policy.type=ocn` on S1 ({r['dataset']['root']}), {first['steps']} steps of a global "
        f"batch of {first['global_batch']} ({first['samples']:,} samples) in every run, seed {r['seed']}, "
        f"on {device}, {r['threads_per_process']} math thread(s) and {r['workers_per_process']} data worker(s) per "
        "process. The runs, one after the other:\n\n"
        f"{launch}\n\n"
        "| processes | batch per process | real frames/s | against 1 process | step (s) | wall (s) | NMI | F1@1 |\n"
        "|---|---|---|---|---|---|---|---|\n"
        + "".join(_run_row(run, first) for run in runs)
        + "\nReal frames/s: the real (unpadded) frames of the global batch per step over `lerobot-train`'s own step "
        "time (update + data wait, the slowest process's), the first logged interval left out. Wall: the whole "
        "command, start-up, dataset loading and checkpoint included. NMI and F1@1: `ocn-eval` on the validation "
        "split, the same number of samples behind each.\n"
        + _teardown_note(runs)
        + bounds
        + _gpu_plan(r)
    )


def _teardown_note(runs: list[dict[str, Any]]) -> str:
    """A line for each run whose processes were stopped after the end of their training (common.run_timed)."""
    stopped = [str(run["processes"]) for run in runs if run["teardown_stopped"]]
    return "".join(f"\n**The {n}-process run did not exit**: its processes were still alive {TEARDOWN_GRACE_S:.0f} s "
                   "after `End of training` (LeRobot's closing `destroy_process_group`) and were stopped; its wall "
                   "time ends at that line and its checkpoint was already written.\n" for n in stopped)


def _gpu_plan(r: dict[str, Any]) -> str:
    """The multi-GPU launch, on paper: what changes and what the per-step all-reduce costs."""
    megabytes = r["runs"][0]["num_params"] * 4 / 1e6
    ring = 2 * (8 - 1) / 8 * megabytes  # megabytes each GPU sends and receives in a ring all-reduce among 8
    return (
        "\nOn N GPUs (a plan; this file measured what its header says): `accelerate launch --multi_gpu "
        "--num_processes N lerobot-train --policy.type=ocn --policy.device=cuda --batch_size=B/N ...` (or the "
        "torchrun line with `--policy.device=cuda`). Accelerate gives each process its GPU and DDP runs over "
        "NCCL; each process copies the episodes to its GPU once (`episode_memory`). Each step all-reduces "
        f"the {megabytes:.1f} MB of gradients: a ring all-reduce moves 2(N - 1)/N of it through each GPU, "
        f"{ring:.1f} MB among 8, so about {ring / 200e3 * 1e6:.0f} us at an NVLink-class 200 GB/s and "
        f"{ring / 20e3 * 1e3:.2f} ms at a PCIe-class 20 GB/s (nominal bandwidths, not measured here), against "
        f"an update of tens of milliseconds; the {SMALL_ALLREDUCES_PER_STEP} single-number all-reduces cost "
        "NCCL's latency, tens of microseconds each. `ocn-bench train --device cuda --processes 1` measures one "
        "GPU; `--processes 1,N` with N GPUs measures the rest.\n"
    )
