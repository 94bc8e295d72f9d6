"""`ocn-bench skills` (time-to-skills, issue 71): the wall time from an empty folder to an S1 model whose
options parse the held-out demonstrations (NMI >= 0.95), through the plain commands a user runs:

    record_demos --env craft --tasks AC,CD,DA --episodes-per-task 2000 --root R --repo-id local/s1
    lerobot-train --policy.type=ocn --policy.device=cpu --dataset.repo_id=local/s1 --dataset.root=R --steps=6000
        --batch_size=128 --output_dir=O --seed=S --wandb.enable=false --policy.push_to_hub=false
    ocn-eval --policy O/checkpoints/last/pretrained_model --root R --repo-id local/s1 --out M.json

each seed from its own empty folder, as real subprocesses timed from the first command's start to the
last one's end, and set against the OMPN release's 500-step run.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.tools.bench.common import add_common_arguments, header, int_list, run_timed, typed

# The OMPN release (Ordered-Memory-RL/ompn_craft) trains Craft for 500 steps to F1 0.98; that run took
# 15 minutes of wall time when measured on this project's development machine. The reference time to skills.
OMPN_RELEASE_WALL_S = 900.0
OMPN_RELEASE_F1 = 0.98
NMI_GOAL = 0.95
REPO_ID = "local/s1"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "skills")
    parser.add_argument("--steps", type=int_list, default=[2000, 3000], help="lerobot-train --steps: each budget "
                        "is timed on every seed (the smallest that parses is the time to skills)")
    parser.add_argument("--episodes-per-task", type=int, default=2000, help="record_demos --episodes-per-task")
    parser.add_argument("--batch-size", type=int, default=128, help="lerobot-train --batch_size")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 1..N, each from an empty folder")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="lerobot-train --policy.device")


def plain_commands(folder: Path, seed: int, steps: int, args: argparse.Namespace) -> dict[str, list[str]]:
    """The three plain commands of one seed and budget, in `folder`: the dataset R, the run O and the scores
    M.json."""
    root, out = folder / "R", folder / "O"
    return {
        "record_demos": [console_script("record_demos"), "--env", "craft", "--tasks", "AC,CD,DA",
                         "--episodes-per-task", str(args.episodes_per_task), "--root", str(root),
                         "--repo-id", REPO_ID],
        "lerobot-train": [console_script("lerobot-train"), "--policy.type=ocn", f"--policy.device={args.device}",
                          f"--dataset.repo_id={REPO_ID}", f"--dataset.root={root}", f"--steps={steps}",
                          f"--batch_size={args.batch_size}", f"--output_dir={out}", f"--seed={seed}",
                          "--wandb.enable=false", "--policy.push_to_hub=false"],
        "ocn-eval": [console_script("ocn-eval"), "--policy", str(out / "checkpoints" / "last" / "pretrained_model"),
                     "--root", str(root), "--repo-id", REPO_ID, "--out", str(folder / "M.json")],
    }


def timed_pipeline(commands: dict[str, list[str]], folder: Path) -> dict[str, Any]:
    """Run the commands one after the other in `folder`: each one's wall seconds, the span from the first
    one's start to the last one's end, and the scores of the `M.json` the last one writes there."""
    start = time.perf_counter()
    walls = {name: run_timed(command, cwd=folder)[0] for name, command in commands.items()}
    total = time.perf_counter() - start
    scores = json.loads((folder / "M.json").read_text())
    return {"wall_s": walls, "total_wall_s": total, "nmi": scores["nmi"], "f1_tol1": scores["f1_tol1"],
            "reached_goal": scores["nmi"] is not None and scores["nmi"] >= NMI_GOAL,
            "against_ompn_release": total / OMPN_RELEASE_WALL_S,
            "commands": {name: typed(command).replace(f"{folder}/", "") for name, command in commands.items()}}


def time_to_skills(seed: int, steps: int, args: argparse.Namespace) -> dict[str, Any]:
    """One seed's plain commands at one budget, from an empty folder of its own (`timed_pipeline`)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        return {"seed": seed, "steps": steps, **timed_pipeline(plain_commands(folder, seed, steps, args), folder)}


def fastest(runs: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The time to skills: the quickest run that met the goal (None if none did)."""
    met = [run for run in runs if run["reached_goal"]]
    return min(met, key=lambda run: run["total_wall_s"]) if met else None


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    seeds = [time_to_skills(seed, steps, args) for steps in args.steps for seed in range(1, args.seeds + 1)]
    return {"steps": args.steps, "batch_size": args.batch_size, "fastest": fastest(seeds),
            "episodes_per_task": args.episodes_per_task,
            "device": args.device, "nmi_goal": NMI_GOAL, "ompn_release_wall_s": OMPN_RELEASE_WALL_S,
            "ompn_release_f1": OMPN_RELEASE_F1, "seeds": seeds}


def markdown(r: dict[str, Any]) -> str:
    rows = "".join(
        f"| {s['steps']} | {s['seed']} | {s['wall_s']['record_demos']:.0f} | {s['wall_s']['lerobot-train']:.0f} | "
        f"{s['wall_s']['ocn-eval']:.0f} | **{s['total_wall_s']:.0f}** | {s['nmi']:.3f} | {s['f1_tol1']:.3f} | "
        f"{'yes' if s['reached_goal'] else 'no'} | {s['against_ompn_release']:.2f}x |\n"
        for s in r["seeds"]
    )
    commands = "\n".join(f"    {command}" for command in r["seeds"][0]["commands"].values())
    return (
        header("Time to skills: an empty folder to an S1 model that parses", r)
        + "Each seed runs the plain commands from its own empty folder, as subprocesses, timed from the first "
        f"command's start to the last one's end (seed {r['seeds'][0]['seed']} at {r['seeds'][0]['steps']} steps; "
        "the others differ by `--seed` and `--steps`):\n\n"
        f"{commands}\n\n"
        f"Goal: NMI >= {r['nmi_goal']} on the validation split. Reference: the OMPN release's 500-step run, "
        f"{r['ompn_release_wall_s']:.0f} s of wall time for F1 {r['ompn_release_f1']} (measured on this project's "
        "development machine); the last column is each seed's total over it (below 1: sooner).\n\n"
        + fastest_words(r) +
        "| steps | seed | record_demos (s) | lerobot-train (s) | ocn-eval (s) | total (s) | NMI | F1@1 | goal met | "
        "against OMPN's 900 s |\n|---|---|---|---|---|---|---|---|---|---|\n" + rows
    )


def fastest_words(r: dict[str, Any]) -> str:
    """The headline: the quickest run that met the goal, and how many seeds met it at each budget."""
    per_budget = "; ".join(
        f"{steps} steps: {sum(s['reached_goal'] for s in r['seeds'] if s['steps'] == steps)} of "
        f"{sum(s['steps'] == steps for s in r['seeds'])} seeds" for steps in r["steps"])
    best = r["fastest"]
    if best is None:
        return f"**No run met the goal** ({per_budget}).\n\n"
    return (f"**Time to skills: {best['total_wall_s']:.0f} s** (seed {best['seed']}, {best['steps']} steps; "
            f"{best['against_ompn_release']:.2f}x the OMPN release's {r['ompn_release_wall_s']:.0f} s). Seeds that "
            f"met the goal: {per_budget}.\n\n")
