"""`record_demos`: record scripted-expert demonstrations into a LeRobot v3.0 dataset (+ MCAP log).

The dataset is written chunk by chunk, so Ctrl-C or a crash leaves a finalized dataset with every
episode finished before it, and `--resume` appends to it. Ground-truth subtask labels are stored
for evaluation only (columns `subtask.*` and LeRobot `language_persistent` subtask rows).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from datetime import UTC, datetime
from pathlib import Path

from tqdm import tqdm

from envs.craft.render import TILE
from envs.craft.world import GRID_SIZE, MODES, REWARDS, parse_task_list, task_description
from ocn_data.craft_recorder import FPS, CraftRecorder, craft_features
from ocn_data.datacard import dataset_card
from ocn_data.lerobot_writer import ColumnarDatasetWriter, DatasetExistsError
from ocn_data.mcap_log import DemoMcapWriter, check_new_log
from ocn_data.provenance import load_provenance, write_provenance


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="record_demos",
        description="Record scripted-expert demonstrations into a LeRobot v3.0 dataset, with a dataset "
        "card and optionally an MCAP log. Ground-truth subtask labels are kept for evaluation only.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--env", choices=["craft"], default="craft", help="world to record in")
    p.add_argument(
        "--tasks",
        required=True,
        help="comma-separated tasks: subtask letters (AC,CD,DA) or, in full mode, named tasks (make bed,get gem)",
    )
    p.add_argument("--episodes-per-task", type=int, required=True, help="successful episodes to record per task")
    p.add_argument("--root", type=Path, required=True, help="dataset directory (must not exist unless --resume)")
    p.add_argument("--repo-id", required=True, help="dataset id, ORG/NAME")
    p.add_argument("--seed", type=int, default=0, help="base seed; every episode attempt gets its own map seed")
    p.add_argument("--reward", choices=REWARDS, default="dense")
    p.add_argument("--mode", choices=MODES, default="paper", help="Craft: the paper's 4 resources or the full recipe book")
    p.add_argument("--mcap", type=Path, help="also write every step to this MCAP file (must not exist)")
    p.add_argument("--video", action="store_true", help="also store rendered frames as the video feature observation.image")
    p.add_argument(
        "--subtask-annotations",
        action="store_true",
        help="also store the ground-truth segmentation as LeRobot language_persistent subtask rows "
        "(lerobot-train reads them; LeRobot 0.6.1's lerobot-dataset-viz cannot batch them)",
    )
    p.add_argument("--resume", action="store_true", help="append to the existing dataset at --root")
    p.add_argument("--val-fraction", type=float, default=0.2, help="last fraction of episodes that forms the val split")
    p.add_argument("--batch-size", type=int, default=256, help="envs stepped together (16 with --video)")
    p.add_argument("--chunk-episodes", type=int, default=2000, help="episodes per written data file")
    return p


def _write_card_and_provenance(root: Path, repo_id: str, provenance: dict) -> None:
    write_provenance(root, provenance)
    (root / "README.md").write_text(dataset_card(root, repo_id))


def record(args: argparse.Namespace) -> int:
    """Run one recording session; returns the process exit code."""
    tasks = parse_task_list(args.tasks, args.mode)
    if args.episodes_per_task < 1:
        raise ValueError(f"--episodes-per-task must be >= 1, got {args.episodes_per_task}")
    if args.mcap is not None:
        check_new_log(args.mcap)
    provenance = load_provenance(args.root) if args.resume else {"sessions": []}
    if args.resume and provenance["sessions"] and provenance["sessions"][-1]["mode"] != args.mode:
        raise ValueError(f"--resume: the dataset was recorded in mode {provenance['sessions'][-1]['mode']!r}")
    video = args.video
    image_shape = (GRID_SIZE * TILE, GRID_SIZE * TILE, 3) if video else None
    writer = ColumnarDatasetWriter(
        args.root, args.repo_id, FPS, craft_features(image_shape),
        resume=args.resume,
        robot_type="craft",
        language=args.subtask_annotations,
    )
    first_attempt = sum(s["attempts"] for s in provenance["sessions"])
    recorder = CraftRecorder(
        tasks,
        args.episodes_per_task,
        mode=args.mode,
        reward=args.reward,
        seed=args.seed,
        first_attempt=first_attempt,
        batch_size=16 if video and args.batch_size == 256 else args.batch_size,
        video=video,
    )
    mcap = DemoMcapWriter(args.mcap, FPS, craft_features()["observation.state"]["names"]) if args.mcap else None
    start_episodes = writer.total_episodes
    session = {
        "command": shlex.join(["record_demos", *sys.argv[1:]]),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "seed": args.seed,
        "mode": args.mode,
        "reward": args.reward,
        "tasks": [task_description(t) for t in tasks],
    }
    interrupted = False
    bar = tqdm(total=recorder.total, unit="ep", desc=f"record {args.repo_id}")

    def save(chunk) -> None:
        if chunk.num_episodes == 0:
            return
        first = writer.total_episodes
        writer.write(chunk)
        if mcap is not None:
            mcap.write(chunk, first)
        bar.update(chunk.num_episodes)

    try:
        for chunk in recorder.chunks(args.chunk_episodes):
            save(chunk)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        save(recorder.take_finished())
        bar.close()
        if mcap is not None:
            mcap.close()
        writer.finalize(args.val_fraction)
        session |= {
            "episodes": writer.total_episodes - start_episodes,
            "attempts": recorder.attempts - first_attempt,
            "expert_failures": recorder.failures,
            "interrupted": interrupted,
        }
        provenance["sessions"].append(session)
        _write_card_and_provenance(args.root, writer.meta.repo_id, provenance)
    recorded = writer.total_episodes - start_episodes
    print(
        f"{'interrupted: ' if interrupted else ''}recorded {recorded} episodes "
        f"({writer.total_episodes} in total, {writer.total_frames} frames) into {args.root}"
        + (f"; MCAP log {args.mcap}" if mcap else "")
    )
    return 130 if interrupted else 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return record(args)
    except (ValueError, FileExistsError, FileNotFoundError, DatasetExistsError) as err:
        parser.exit(2, f"record_demos: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
