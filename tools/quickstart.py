"""`ocn-quickstart`: the small end-to-end job of the README.

Records a little Craft data with the expert (AC, CD, DA), reads it back with LeRobot, prints what
it holds and writes a rerun viewer file of one episode with LeRobot's own dataset viewer. Training
and evaluating OCN join this job once the policy lands (see the README's roadmap).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np


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
    args = parser.parse_args(argv)

    shutil.rmtree(args.workdir, ignore_errors=True)
    root, mcap, viewer = args.workdir / "craft_demo", args.workdir / "craft_demo.mcap", args.workdir / "viewer"
    repo_id = "local/craft_quickstart"
    print(f"[1/3] recording {3 * args.episodes_per_task} expert episodes into {root}", flush=True)
    subprocess.run(
        [sys.executable, "-m", "ocn_data.record_demos", "--tasks", "AC,CD,DA", "--episodes-per-task",
         str(args.episodes_per_task), "--root", str(root), "--repo-id", repo_id, "--seed", str(args.seed),
         "--mcap", str(mcap)],
        check=True,
    )

    print("[2/3] reading it back with LeRobot", flush=True)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=root)
    lengths = np.array([ep["length"] for ep in ds.meta.episodes])
    tasks = [ep["tasks"][0] for ep in ds.meta.episodes]
    print(f"  {ds.num_episodes} episodes, {ds.num_frames} frames, splits {ds.meta.info.splits}")
    for task in dict.fromkeys(tasks):
        mine = lengths[[t == task for t in tasks]]
        print(f"  {task!r}: {len(mine)} episodes, mean length {mine.mean():.1f} steps")

    print(f"[3/3] writing a rerun viewer file of episode 0 into {viewer}", flush=True)
    subprocess.run(
        [str(Path(sys.executable).with_name("lerobot-dataset-viz")), "--repo-id", repo_id, "--root", str(root),
         "--episode-index", "0", "--mode", "local", "--save", "1", "--output-dir", str(viewer)],
        check=True,
        capture_output=True,
    )
    rrd = sorted(viewer.glob("*.rrd"))
    if not rrd:
        raise SystemExit(f"ocn-quickstart: lerobot-dataset-viz wrote no .rrd file into {viewer}")
    print(f"done: dataset {root}, MCAP log {mcap}, viewer file {rrd[0]} (open it with `rerun {rrd[0]}`)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
