"""`python -m lerobot_policy_ocn.ocn_data.record_babyai`: BabyAI bot demonstrations as a LeRobot v3.0 dataset,
written by LeRobot's own `LeRobotDataset` writer (`create`, `add_frame`, `save_episode`, `finalize`).

Episode k is the bot's demonstration of mission `MISSIONS[k % 150]`, so every run of 150
consecutive episodes holds each mission once and both splits hold the missions evenly (the
validation split is the last `--val-fraction` of episodes, as record_demos writes it; from 187
episodes on, the training split holds every mission that validation does). Attempt a
gets the env seed `seed * 2**32 + a`, distinct for every (seed, attempt); an attempt the bot does
not finish is dropped and its mission retried with the next attempt's seed. `robot_type` is
"babyai". The columns `subtask.*` are ground truth for evaluation only (envs/babyai/README.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lerobot_policy_ocn.envs.babyai import MinigridMissing, minigrid_installed
from lerobot_policy_ocn.ocn_data.recorder import LABEL_FEATURES

WORLD = "babyai"
FPS = 10
SEED_STRIDE = 2**32
MAX_FAILURES = 100  # consecutive failed attempts at one mission before giving up


class UsageError(ValueError):
    """Bad command-line input: reported as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m lerobot_policy_ocn.ocn_data.record_babyai",
        description="Record BabyAI bot demonstrations (level OpenPickupSeq) into a LeRobot v3.0 dataset "
        "with LeRobot's own writer. Needs the babyai extra.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--root", type=Path, required=True, help="dataset directory (must not exist)")
    p.add_argument("--repo-id", required=True, help="dataset id, ORG/NAME")
    p.add_argument("--episodes", type=int, required=True, help="successful episodes to record")
    p.add_argument("--seed", type=int, default=0, help="base seed (>= 0); every attempt gets its own env seed")
    p.add_argument("--val-fraction", type=float, default=0.2, help="last fraction of episodes that forms the val split")
    return p


def check_args(args: argparse.Namespace) -> None:
    """Refuse bad input before anything is written."""
    if args.root.exists():
        raise UsageError(f"--root {args.root} already exists; give a new folder (LeRobot creates it)")
    org, slash, name = args.repo_id.partition("/")
    if not (slash and org and name) or "/" in name:
        raise UsageError(f"--repo-id must be ORG/NAME with exactly one slash, got {args.repo_id!r}")
    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    if not 0 <= args.seed < SEED_STRIDE:
        raise UsageError(f"--seed must be in [0, 2**32), got {args.seed}")
    if not 0.0 <= args.val_fraction < 1.0:
        raise UsageError(f"--val-fraction must be in [0, 1), got {args.val_fraction}")


def env_seed(seed: int, attempt: int) -> int:
    """The env seed of attempt `attempt` under base seed `seed`: one integer per pair, never repeated."""
    return seed * SEED_STRIDE + attempt


def babyai_features() -> dict[str, dict]:
    """LeRobot features of a BabyAI demonstration dataset (the state layout: envs.babyai.observation)."""
    from lerobot_policy_ocn.envs.babyai.observation import STATE_DIM, STATE_NAMES

    return {
        "observation.state": {"dtype": "int64", "shape": (STATE_DIM,), "names": list(STATE_NAMES)},
        "action": {"dtype": "int64", "shape": (1,), "names": ["action"]},
        **LABEL_FEATURES,
    }


def split_ranges(n: int, val_fraction: float) -> dict[str, str]:
    """meta/info.json `splits`: the first episodes train, the last `val_fraction` validate."""
    n_train = n - int(round(n * val_fraction))
    return {"train": f"0:{n_train}", **({"val": f"{n_train}:{n}"} if n_train < n else {})}


def record(root: Path, repo_id: str, episodes: int, seed: int, val_fraction: float = 0.2) -> dict:
    """Record `episodes` successful bot episodes; returns counts and the seconds spent recording
    (imports and dataset creation excluded) for the summary line."""
    from lerobot.datasets.io_utils import write_info
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_policy_ocn.envs.babyai.env import BabyAIEnv
    from lerobot_policy_ocn.envs.babyai.expert import demonstrate
    from lerobot_policy_ocn.envs.babyai.missions import MISSIONS

    env = BabyAIEnv()
    dataset = LeRobotDataset.create(repo_id, FPS, babyai_features(), root=root, robot_type=WORLD, use_videos=False)
    attempt = frames = 0
    start = time.perf_counter()
    for k in tqdm(range(episodes), desc="episodes", unit="ep", disable=None):
        mission = MISSIONS[k % len(MISSIONS)].text
        for _ in range(MAX_FAILURES):
            demo = demonstrate(env, mission, env_seed(seed, attempt))
            attempt += 1
            if demo is not None:
                break
        else:
            raise RuntimeError(f"the bot failed {MAX_FAILURES} attempts in a row at {mission!r}")
        ends = np.append(demo.subtask_index[1:] != demo.subtask_index[:-1], True)
        for t in range(len(demo)):
            dataset.add_frame({
                "observation.state": demo.state[t],
                "action": demo.action[t : t + 1],
                "next.reward": demo.reward[t : t + 1],
                "next.done": np.array([t == len(demo) - 1]),
                "subtask.index": demo.subtask_index[t : t + 1],
                "subtask.id": demo.subtask_id[t : t + 1],
                "subtask.end": ends[t : t + 1],
                "task": demo.mission,
            })
        dataset.save_episode()
        frames += len(demo)
    dataset.finalize()
    dataset.meta.info.splits = split_ranges(episodes, val_fraction)
    write_info(dataset.meta.info, root)
    seconds = time.perf_counter() - start
    return {"episodes": episodes, "frames": frames, "attempts": attempt, "missions": min(episodes, len(MISSIONS)),
            "seconds": seconds}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        check_args(args)
        if not minigrid_installed():
            raise MinigridMissing()
    except (UsageError, MinigridMissing) as error:
        print(f"record_babyai: {error}", file=sys.stderr)
        return 2
    # LeRobot's save_episode runs a Hugging Face `datasets` map per episode, each with its own bar.
    from datasets import disable_progress_bars

    disable_progress_bars()
    summary = record(args.root, args.repo_id, args.episodes, args.seed, args.val_fraction)
    elapsed = summary["seconds"]
    print(
        f"record_babyai: {summary['episodes']} episodes ({summary['frames']} frames, {summary['missions']} missions, "
        f"{summary['attempts']} attempts) in {elapsed:.1f} s ({summary['episodes'] / elapsed:.1f} episodes/s) "
        f"-> {args.root}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
