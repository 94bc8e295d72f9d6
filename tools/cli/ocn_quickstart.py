"""`ocn-quickstart`: the small end-to-end job of the README, which shows skills.

Four plain commands, as a user would type them: `record_demos` (Craft's S1 tasks AC, CD and DA, with
its default DART noise), `lerobot-train --policy.type=ocn` (no `--policy.*` flag: the policy's
default recipe), `ocn-eval` (parsing scores against the subtasks, the option x subtask table, free-run
success) and `ocn-view` (a rerun file and a PNG of the options over validation episodes). Then it
prints the option x subtask table: each option, run alone, on each subtask.

Its budget, chosen to induce the three skills within the 4-minute goal: 2,000 demonstrations per
task and 2,000 steps of 64 episodes, a step costing about half of one of 128. `ocn-bench skills
--steps 2000,2500 --batch-size 64` (results/bench_skills.md) parsed seeds 1 and 3 at 2,000 steps
(NMI 0.978, 0.997) and not seed 2 (0.829), and all three at 2,500, which would take the quickstart
past 4 minutes. Seed 1 is the default. Its wall time on 2 cores is results/bench_quickstart.md; the
paper-size run is `ocn-reproduce imitation-s1`.

Training runs with `--num_workers=0`: the policy holds the episodes in memory and reads only the
sampled frames' episode indices, so LeRobot's data workers (4 by default) only take CPU from the
update on a small machine. Measured on 2 cores, 250 steps of the quickstart's training (then of 128
episodes): 0.145 s a step with no worker, 0.150 with 4 and 0.156 with 1, and 13 s less start-up.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from lerobot_policy_ocn.tools import console_script

EPISODES_PER_TASK = 2000
STEPS = 2000
BATCH_SIZE = 64
REPO_ID = "local/craft_quickstart"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ocn-quickstart", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=Path("outputs/quickstart"),
                        help="scratch folder, replaced on every run")
    parser.add_argument("--seed", type=int, default=1, help="lerobot-train's seed")
    parser.add_argument("--steps", type=int, default=STEPS, help="lerobot-train steps")
    parser.add_argument("--episodes-per-task", type=int, default=EPISODES_PER_TASK)
    return parser


def commands(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    """The quickstart's commands, each with what it does, run in `--workdir`."""
    return [
        ("recording the expert's demonstrations", [
            console_script("record_demos"), "--env", "craft", "--tasks", "AC,CD,DA", "--episodes-per-task",
            str(args.episodes_per_task), "--root", "craft_demo", "--repo-id", REPO_ID, "--mcap", "craft_demo.mcap"]),
        ("training OCN with lerobot-train", [
            console_script("lerobot-train"), "--policy.type=ocn", "--policy.device=cpu", f"--dataset.repo_id={REPO_ID}",
            "--dataset.root=craft_demo", f"--steps={args.steps}", f"--batch_size={BATCH_SIZE}", "--num_workers=0",
            "--output_dir=train", f"--seed={args.seed}", "--wandb.enable=false", "--policy.push_to_hub=false",
            f"--save_freq={args.steps}", f"--log_freq={max(1, args.steps // 6)}"]),
        ("scoring the options with ocn-eval", [
            console_script("ocn-eval"), "--policy", "train/checkpoints/last/pretrained_model", "--root", "craft_demo",
            "--repo-id", REPO_ID, "--out", "eval.json", "--rollouts", "50", "--mcap", "policy_runs.mcap"]),
        ("drawing the options with ocn-view", [
            console_script("ocn-view"), "--root", "craft_demo", "--repo-id", REPO_ID, "--policy",
            "train/checkpoints/last/pretrained_model", "--episodes", "20", "--save", "viewer.rrd", "--png",
            "segmentation.png"]),
    ]


def option_table(eval_json: Path) -> str:
    """The option x subtask table of an `ocn-eval` result as text: each option's success on each subtask."""
    result = json.loads(eval_json.read_text())
    table = result["option_subtask_success"]
    lines = ["option x subtask success (each option run alone on each subtask):",
             "          " + "".join(f"{subtask:>10}" for subtask in table["subtasks"])]
    for row, values in zip(table["rows"], table["table"], strict=True):
        lines.append(f"{row:>10}" + "".join(f"{value:>10.2f}" for value in values))
    lines.append(f"NMI {result['nmi']:.3f}  F1@1 {result['f1_tol1']:.3f}  "
                 f"free-run success {result['mean_success_rate']:.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    shutil.rmtree(args.workdir, ignore_errors=True)
    args.workdir.mkdir(parents=True)
    started = time.perf_counter()
    steps = commands(args)
    for number, (what, command) in enumerate(steps, start=1):
        shown = " ".join([Path(command[0]).name, *command[1:]])
        print(f"[{number}/{len(steps)}] {what}: {shown}", flush=True)
        if subprocess.run(command, cwd=args.workdir).returncode != 0:
            print(f"ocn-quickstart: step {number} ({what}) failed; its output is above.", file=sys.stderr)
            return 1
    print(option_table(args.workdir / "eval.json"))
    print(f"done in {time.perf_counter() - started:.0f} s: {args.workdir}/eval.json (scores), eval.png (option "
          f"table), segmentation.png, viewer.rrd (open with `rerun {args.workdir}/viewer.rrd`)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
