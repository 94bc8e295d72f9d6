"""`ocn-reproduce craft-images`: OCN trained on Craft's rendered frames alone, against OCN trained on its
state, on the same episodes; and the training throughput of each.

The recordings: `record_demos --tasks AC,CD,DA` (Craft S1) twice from the same seed and env batch, once
with `--video` (the rendered 160 x 160 frames as the video feature `observation.image`, beside the
state) and once without: the same episodes (record_demos draws them from the seed alone), so the two
models parse the same validation episodes.

The models, plain `lerobot-train --policy.type=ocn` runs of the same size and seed at the policy's
defaults (Craft's recipe):

- `state`: on the recording without video (the state is its only input);
- `images`: on the video recording with `--policy.drop_features=[observation.state]`: the frames alone,
  decoded once when the policy is built and shrunk to 40 x 40 (4 px a tile), through the small
  convolutional encoder;
- `state_on_video` (timed only): the state model again on the video recording (`--policy.drop_features=
  [observation.image]`): what the images cost when they are not even read, since LeRobot decodes the
  image of every frame it samples for the batch (it loads every feature of a dataset).

`ocn-eval` scores `state` and `images` on the validation split (NMI, F1, alignment; the image model
has no env to act in: Craft's batch env gives states, so its free runs are not run). Throughput comes
from runs of their own, `--throughput-steps` steps of each of the three, back to back after the
scored runs, so that the three share one machine's conditions (a long scored run may share the
machine with other work for part of its hour). It is read from each timed run's log: frames trained
per second = the episode frames in a step's loss (`frames_used`) over the step's update and data time
(LeRobot's `updt_s`, `data_s`), over the log lines after the first; and per second of the whole run's
wall time, start-up and the images' one decode included. Beside them, the image encoder's own cost
(`encoder_timing`): forward and backward over a batch of frames, with and without the training
shift, against the three 3 x 3 convolutions of stride 2 it replaced. Writes
`results/bench_images.{json,md}`.
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import RESULTS
from lerobot_policy_ocn.tools.reproduce.clones import Demos, Size, add_size_arguments, record, size_of
from lerobot_policy_ocn.tools.reproduce.report import check, checks_table, origin_words, provenance
from lerobot_policy_ocn.tools.reproduce.runs import Evaluation, Recording, Training, train_command

STUDY = "bench_images"
TASKS = ("--tasks", "AC,CD,DA", "--batch-size", "16")
VIDEO = Demos("craft_s1_video", (*TASKS, "--video"))
STATES = Demos("craft_s1_states", TASKS)
# The full size: the S1 recipe's (results/imitation_s1.md), with record_demos' batch of video envs.
SIZE = Size(episodes_per_task=2000, steps=6000, batch_size=128)
RUNS = {
    "state": (STATES, None),
    "images": (VIDEO, "observation.state"),
    "state_on_video": (VIDEO, "observation.image"),
}
SCORED = ("state", "images")  # trained at the study's size and scored; every run is also timed
SCORES = {"f1_tol0": "F1@0", "f1_tol1": "F1@1", "align_acc": "align", "nmi": "NMI"}
LOG_LINE = re.compile(r"updt_s:([\d.]+) data_s:([\d.]+).*?frames_used:([\d.]+)")
DECODED = re.compile(r"decoded .* in ([\d.]+) s")


def train(args: argparse.Namespace, name: str, data: Recording, timed: bool = False) -> Training:
    """One run (trained unless it is there): the plain command, plus the feature it drops, if any; `timed`:
    the short run of `--throughput-steps` that measures its speed."""
    demos, dropped = RUNS[name]
    folder = f"train/{demos.name}/ocn_{name}{'_timed' if timed else ''}/seed{args.seed}"
    command = train_command("ocn", data.root, demos.repo_id, folder, args.throughput_steps if timed else args.steps,
                            args.batch_size, args.seed, {})
    if dropped:
        command.append(f"--policy.drop_features=[{dropped}]")
    return Training(args.workdir, folder, command).run()


def throughput(trained: Training, steps: int) -> dict[str, Any]:
    """Frames trained per second, from the run's log (see the module docstring)."""
    log = (trained.path / "log.txt").read_text()
    lines = [tuple(float(v) for v in match) for match in LOG_LINE.findall(log)][1:]
    if not lines:
        raise SystemExit(f"ocn-reproduce craft-images: {trained.path / 'log.txt'} logs no step after the first: "
                         "train for more than 200 steps.")
    frames = sum(line[2] for line in lines) / len(lines)
    step_s = sum(line[0] + line[1] for line in lines) / len(lines)
    decoded = DECODED.search(log)
    wall = trained.wall_s
    return {"frames_per_step": round(frames, 1), "step_s": round(step_s, 4), "frames_per_s": round(frames / step_s, 1),
            "data_s": round(sum(line[1] for line in lines) / len(lines), 4),
            "wall_s": wall, "frames_per_wall_s": None if not wall else round(frames * steps / wall, 1),
            "images_decoded_s": float(decoded.group(1)) if decoded else None}


ENCODER_FRAMES = 2600  # about a batch of 128 Craft S1 episodes


def encoder_timing(repeats: int = 3) -> dict[str, Any]:
    """Seconds of one forward and backward pass over ENCODER_FRAMES random 40 x 40 frames, one thread, the
    best of `repeats`: the policy's `ConvEncoder` on the frames as they are and in training (each frame
    shifted at random first), and three 3 x 3 convolutions of stride 2 (16, 32, 32 channels) with its
    linear read-out, the design it replaced (the frames as they are)."""
    import torch
    from torch import nn

    from lerobot_policy_ocn.ocn.encoders import ConvEncoder

    torch.set_num_threads(1)
    torch.manual_seed(0)
    policy = ConvEncoder(3, 40)
    stacked = nn.Sequential(nn.Conv2d(3, 16, 3, 2, 1), nn.ReLU(), nn.Conv2d(16, 32, 3, 2, 1), nn.ReLU(),
                            nn.Conv2d(32, 32, 3, 2, 1), nn.ReLU(), nn.Flatten(), nn.Linear(32 * 5 * 5, 128), nn.ReLU())
    frames = torch.randint(0, 256, (ENCODER_FRAMES, 3, 40, 40)).float()
    timing = {}
    for name, encoder, training in (("patch 4x4 stride 4, 3x3 stride 2 (the policy's)", policy, False),
                                    ("the policy's in training (each frame shifted at random)", policy, True),
                                    ("three 3x3 stride 2", stacked, False)):
        encoder.train(training)
        best = float("inf")
        for _ in range(repeats):
            started = time.perf_counter()
            encoder(frames / 255.0 if encoder is stacked else frames).sum().backward()
            best = min(best, time.perf_counter() - started)
        timing[name] = {"seconds": round(best, 3), "weights": sum(p.numel() for p in encoder.parameters())}
    return {"frames": ENCODER_FRAMES, "encoders": timing}


def markdown(result: dict[str, Any]) -> str:
    settings, rows = result["settings"], result["rows"]
    smaller = [f"{key} {settings[key]} (full: {getattr(SIZE, key)})" for key in ("episodes_per_task", "steps",
                                                                                   "batch_size")
               if settings[key] < getattr(SIZE, key)]
    lines = [
        "# Craft S1 from pixels: OCN on the rendered frames alone against OCN on the state", "",
        f"{origin_words(result)} Demonstrations: `record_demos --tasks AC,CD,DA --batch-size 16` with and without "
        f"`--video`, {settings['episodes_per_task']} per task, the same episodes; every model a plain `lerobot-train "
        f"--policy.type=ocn` run of {settings['steps']} steps of {settings['batch_size']} episodes, seed "
        f"{settings['seed']}; scores: `ocn-eval` on the validation split; throughput: a run of "
        f"{settings['throughput_steps']} steps of each model, the three back to back after the scored runs. "
        f"Wall time {result['wall_s'] / 60:.0f} min.",
        "",
        *([f"**Reduced size**: {', '.join(smaller)}, to fit one shared CPU core; the full size is `ocn-reproduce "
           "craft-images` with the defaults.", ""] if smaller else []),
        "## Checks", "", *checks_table(result["checks"]), "",
        "## Parse of the validation episodes", "",
        "| model | " + " | ".join(SCORES.values()) + " | NLL | command |", "|---|" + "---|" * (len(SCORES) + 2),
    ]
    for name in SCORED:
        if name in rows and "scores" in rows[name]:
            scores = rows[name]["scores"]
            lines.append(f"| {name} | " + " | ".join(f"{scores[key]:.3f}" for key in SCORES)
                         + f" | {scores['action_nll']:.3f} | `{rows[name]['train_command']}` |")
    lines += ["", "## Training throughput", "",
              "Frames trained per second: the episode frames in a step's loss over the step's update and data "
              "time (LeRobot's log), and over the whole run's wall time (start-up and the one decode of the images "
              "included).", "",
              "| run | frames per step | s per step | of it data s | frames/s | frames/s of wall time | "
              "images decoded once in s |", "|---|---|---|---|---|---|---|"]
    for name, row in rows.items():
        if "throughput" not in row:
            continue
        t = row["throughput"]
        decoded = "n/a" if t["images_decoded_s"] is None else f"{t['images_decoded_s']:.1f}"
        wall = "n/a" if t["frames_per_wall_s"] is None else f"{t['frames_per_wall_s']:.0f}"
        lines.append(f"| {name} | {t['frames_per_step']:.0f} | {t['step_s']:.3f} | {t['data_s']:.3f} | "
                     f"{t['frames_per_s']:.0f} | {wall} | {decoded} |")
    timing = result.get("encoder_timing")
    if timing:
        lines += ["", f"## The image encoder: forward and backward over {timing['frames']:,} frames of 40 x 40, "
                  "one thread", "", "| encoder | s | weights |", "|---|---|---|"]
        lines += [f"| {name} | {row['seconds']:.3f} | {row['weights']:,} |" for name, row in timing["encoders"].items()]
    lines.append("")
    return "\n".join(lines)


def checks(rows: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    def nmi(name: str) -> float | None:
        return rows[name]["scores"]["nmi"] if "scores" in rows.get(name, {}) else None

    return [check("images alone: NMI >= 0.9", nmi("images"), lambda v: v >= 0.9),
            check("images alone: NMI within 0.05 of the state model's",
                  nmi("images") if nmi("state") is not None else None, lambda v: v >= nmi("state") - 0.05)]


def reproduce(args: argparse.Namespace) -> int:
    """Record both, then train each run (scoring `state` and `images`), rewriting the results after each."""
    if len(args.seeds) != 1:
        raise SystemExit(f"ocn-reproduce craft-images: one seed, the one every run shares; got {args.seeds}")
    args.seed = args.seeds[0]
    started = time.perf_counter()
    settings = {"episodes_per_task": args.episodes_per_task, "steps": args.steps, "batch_size": args.batch_size,
                "throughput_steps": args.throughput_steps, "seed": args.seed, "workdir": str(args.workdir),
                "results": str(args.results)}
    size = size_of(args)
    timing = encoder_timing()
    data = {demos.name: record(args.workdir, demos, size) for demos in (STATES, VIDEO)}
    rows: dict[str, dict[str, Any]] = {name: {} for name in RUNS}

    def save() -> dict[str, Any]:
        result = {**provenance(args.argv, settings), "study": STUDY, "rows": rows, "checks": checks(rows),
                  "encoder_timing": timing, "wall_s": round(time.perf_counter() - started)}
        write(args.results, result)
        return result

    for name in SCORED:
        demos = RUNS[name][0]
        trained = train(args, name, data[demos.name])
        job = Evaluation(args.workdir, f"{trained.folder}/eval", trained.checkpoint, data[demos.name].root,
                         demos.repo_id, args.rollouts).run()
        scores = job.scores()
        rows[name] |= {"train_command": trained.shown, "train_wall_s": trained.wall_s, "eval_command": job.shown,
                       "scores": {key: scores[key] for key in (*SCORES, "action_nll", "mean_success_rate")}}
        save()
    for name, (demos, _) in RUNS.items():
        timed = train(args, name, data[demos.name], timed=True)
        rows[name] |= {"timed_command": timed.shown,
                       "throughput": throughput(timed, args.throughput_steps)}
        result = save()
    print(markdown(result))
    return 0


def write(results: Path, result: dict[str, Any]) -> None:
    """`results/bench_images.{json,md}` (a benchmark: no figure)."""
    import json

    results.mkdir(parents=True, exist_ok=True)
    (results / f"{STUDY}.json").write_text(json.dumps(result, indent=2) + "\n")
    (results / f"{STUDY}.md").write_text(markdown(result))


def add_parser(sub: argparse._SubParsersAction) -> None:
    """The `craft-images` subcommand."""
    parser = sub.add_parser("craft-images", help="Craft S1: OCN from the rendered frames alone against the state",
                            description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_size_arguments(parser, SIZE)
    parser.set_defaults(seeds=[1])
    parser.add_argument("--throughput-steps", type=int, default=500,
                        help="steps of each model's timed run (the throughput table)")
    parser.add_argument("--rollouts", type=int, default=200,
                        help="ocn-eval env episodes per task and per option-table cell (the state model)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of bench_images.{json,md}")
    parser.set_defaults(func=reproduce)
