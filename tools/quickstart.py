"""`ocn-quickstart`: the small end-to-end job of the README.

Records a little Craft data with the expert (AC, CD, DA), reads it back with LeRobot, trains OCN
briefly with `lerobot-train --policy.type=ocn`, scores it with `ocn-eval` (parsing metrics, option x
subtask table, free-run success, the free runs logged to MCAP) and draws the model's options over
20 validation episodes with `ocn-view` (a rerun .rrd file and a PNG). A brief run shows the loop
working, not the paper's figures: those come from `ocn-reproduce imitation-s1`.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from tools import console_script


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="ocn-quickstart",
        description=__doc__.splitlines()[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--workdir", type=Path, default=Path("outputs/quickstart"),
                        help="scratch directory, replaced on every run")
    parser.add_argument("--episodes-per-task", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-steps", type=int, default=200, help="lerobot-train steps")
    parser.add_argument("--batch-size", type=int, default=32, help="lerobot-train windows per step")
    args = parser.parse_args(argv)

    shutil.rmtree(args.workdir, ignore_errors=True)
    root, mcap = args.workdir / "craft_demo", args.workdir / "craft_demo.mcap"
    repo_id = "local/craft_quickstart"
    print(f"[1/5] recording {3 * args.episodes_per_task} expert episodes into {root}", flush=True)
    subprocess.run(
        [sys.executable, "-m", "ocn_data.record_demos", "--tasks", "AC,CD,DA", "--episodes-per-task",
         str(args.episodes_per_task), "--root", str(root), "--repo-id", repo_id, "--seed", str(args.seed),
         "--mcap", str(mcap)],
        check=True,
    )

    print("[2/5] reading it back with LeRobot", flush=True)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=root)
    lengths = np.array([ep["length"] for ep in ds.meta.episodes])
    tasks = [ep["tasks"][0] for ep in ds.meta.episodes]
    print(f"  {ds.num_episodes} episodes, {ds.num_frames} frames, splits {ds.meta.info.splits}")
    for task in dict.fromkeys(tasks):
        mine = lengths[[t == task for t in tasks]]
        print(f"  {task!r}: {len(mine)} episodes, mean length {mine.mean():.1f} steps")

    train_dir, eval_json, runs = args.workdir / "train", args.workdir / "eval.json", args.workdir / "policy_runs.mcap"
    print(f"[3/5] training OCN for {args.train_steps} steps with lerobot-train into {train_dir}", flush=True)
    subprocess.run(
        [console_script("lerobot-train"), "--policy.type=ocn", f"--dataset.repo_id={repo_id}", f"--dataset.root={root}",
         "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false", "--env_eval_freq=0",
         f"--steps={args.train_steps}", f"--batch_size={args.batch_size}", "--num_workers=1",
         f"--save_freq={args.train_steps}", f"--log_freq={max(1, args.train_steps // 4)}",
         f"--policy.window_size={int(lengths.max())}", "--policy.usage_balance=1.0", f"--seed={args.seed}",
         f"--output_dir={train_dir}"],
        check=True,
    )

    checkpoint = train_dir / "checkpoints" / "last" / "pretrained_model"
    print(f"[4/5] evaluating {checkpoint} with ocn-eval", flush=True)
    subprocess.run(
        [console_script("ocn-eval"), "--policy", str(checkpoint), "--root", str(root), "--repo-id", repo_id,
         "--out", str(eval_json), "--rollouts", "20", "--mcap", str(runs)],
        check=True,
    )

    rrd, png = args.workdir / "viewer.rrd", args.workdir / "segmentation.png"
    print(f"[5/5] writing the rerun viewer file {rrd} and the segmentation plot {png} with ocn-view", flush=True)
    subprocess.run(
        [console_script("ocn-view"), "--root", str(root), "--repo-id", repo_id, "--policy", str(checkpoint),
         "--episodes", "20", "--save", str(rrd), "--png", str(png)],
        check=True,
    )
    print(f"done: dataset {root}, MCAP logs {mcap} (demos) and {runs} (policy runs), checkpoint {checkpoint}, "
          f"scores {eval_json}, option table {eval_json.with_suffix('.png')}, segmentation {png}, "
          f"viewer file {rrd} (open it with `rerun {rrd}`)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
