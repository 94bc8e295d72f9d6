"""`record_demos`: record scripted-expert demonstrations into a LeRobot v3.0 dataset (+ MCAP log).

The dataset is written chunk by chunk, so Ctrl-C or a crash leaves a finalized dataset with every
episode finished before it, and `--resume` appends to it. Ground-truth subtask labels are stored
for evaluation only (columns `subtask.*` and LeRobot `language_persistent` subtask rows).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from tqdm import tqdm

from envs.craft.render import TILE
from envs.craft.world import GRID_SIZE, MODES, REWARDS, parse_task_list, task_description
from envs.dial.expert import NOISE_LEVELS
from envs.dial.task import parse_digits, parse_pin_list
from envs.dial.task import task_description as dial_task_description
from ocn_data.craft_recorder import CRAFT_DART_NOISE
from ocn_data.craft_recorder import FPS as CRAFT_FPS
from ocn_data.craft_recorder import CraftRecorder, craft_features
from ocn_data.dial_recorder import FPS as DIAL_FPS
from ocn_data.dial_recorder import DialRecorder, dial_features, random_pins
from ocn_data.datacard import dataset_card
from ocn_data.lerobot_writer import ColumnarDatasetWriter, DatasetExistsError
from ocn_data.mcap_log import DemoMcapWriter, check_new_log
from ocn_data.recorder import ExpertRecorder
from ocn_data.provenance import load_provenance, write_provenance


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="record_demos",
        description="Record scripted-expert demonstrations into a LeRobot v3.0 dataset, with a dataset "
        "card and optionally an MCAP log. Ground-truth subtask labels are kept for evaluation only.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--env", choices=["craft", "dial"], default="craft", help="world to record in")
    p.add_argument(
        "--tasks",
        help="comma-separated tasks. Craft (required): subtask letters (AC,CD,DA) or, in full mode, named tasks "
        "(make bed,get gem). Dial: PINs (12,48) instead of random ones",
    )
    p.add_argument("--episodes-per-task", type=int, help="successful episodes to record per task in --tasks")
    p.add_argument("--episodes", type=int, help="Dial: successful episodes of random PINs to record")
    p.add_argument("--pin-length", type=int, default=2, help="Dial: digits per random PIN")
    p.add_argument("--digits", default="1,2,4,8", help="Dial: digit set random PINs are drawn from")
    p.add_argument("--root", type=Path, required=True, help="dataset directory (must not exist unless --resume)")
    p.add_argument("--repo-id", required=True, help="dataset id, ORG/NAME")
    p.add_argument("--seed", type=int, default=0, help="base seed; every episode attempt gets its own map seed")
    p.add_argument("--reward", choices=REWARDS, default="dense")
    p.add_argument(
        "--mode", choices=MODES, help="Craft: the paper's 4 resources or the full recipe book (default paper)"
    )
    p.add_argument("--mcap", type=Path, help="also write every step to this MCAP file (must not exist)")
    p.add_argument(
        "--dart-noise",
        type=float,
        default=None,
        help=f"Craft: probability per step that the env executes a random action instead of the expert's, "
        f"which stays the recorded label (DART; 0: the expert's own path; default {CRAFT_DART_NOISE}, what OCN's "
        "recipe was measured on). Dial draws its own noise",
    )
    p.add_argument(
        "--video", action="store_true", help="Craft: also store rendered frames as the video feature observation.image"
    )
    p.add_argument(
        "--subtask-annotations",
        action="store_true",
        help="also store the ground-truth segmentation as LeRobot language_persistent subtask rows "
        "(lerobot-train reads them; LeRobot 0.6.1's lerobot-dataset-viz cannot batch them)",
    )
    p.add_argument("--resume", action="store_true", help="append to the existing dataset at --root")
    p.add_argument("--val-fraction", type=float, default=0.2, help="last fraction of episodes that forms the val split")
    p.add_argument("--batch-size", type=int, help="envs stepped together (Craft 256, 16 with --video; Dial 64)")
    p.add_argument("--chunk-episodes", type=int, default=2000, help="episodes per written data file")
    return p


def _write_card_and_provenance(root: Path, repo_id: str, provenance: dict) -> None:
    write_provenance(root, provenance)
    (root / "README.md").write_text(dataset_card(root, repo_id))


def _positive(value: int | None, flag: str) -> int:
    if value is None or value < 1:
        raise ValueError(f"{flag} must be given and >= 1, got {value}")
    return value


def _craft_setup(args: argparse.Namespace, first_attempt: int) -> tuple[Callable[[], ExpertRecorder], dict, int, dict]:
    """Craft's recorder (made later, once the output is known to be writable), features, fps and session record."""
    if args.tasks is None:
        raise ValueError("--env craft needs --tasks (e.g. --tasks AC,CD,DA)")
    if args.episodes is not None:
        raise ValueError("--episodes is for Dial's random PINs; Craft records --episodes-per-task")
    mode = args.mode or "paper"
    tasks = parse_task_list(args.tasks, mode)
    episodes_per_task = _positive(args.episodes_per_task, "--episodes-per-task")
    image_shape = (GRID_SIZE * TILE, GRID_SIZE * TILE, 3) if args.video else None
    if args.dart_noise is None:
        args.dart_noise = CRAFT_DART_NOISE
    session = {"mode": mode, "tasks": [task_description(t) for t in tasks], "dart_noise": args.dart_noise}

    def make() -> ExpertRecorder:
        return CraftRecorder(
            tasks, episodes_per_task, mode=mode, reward=args.reward, seed=args.seed, first_attempt=first_attempt,
            batch_size=args.batch_size or (16 if args.video else 256), video=args.video, dart_noise=args.dart_noise,
        )

    return make, craft_features(image_shape), CRAFT_FPS, session


def _dial_setup(args: argparse.Namespace, first_attempt: int) -> tuple[Callable[[], ExpertRecorder], dict, int, dict]:
    """Dial's recorder maker, features, fps and session record: given PINs, or random ones."""
    if args.video or args.mode or args.dart_noise is not None:
        raise ValueError(
            "--video, --mode and --dart-noise are Craft options; Dial records states only, with noise of its own"
        )
    digits = parse_digits(args.digits)
    if args.tasks is not None:
        if args.episodes is not None:
            raise ValueError("give either --tasks with --episodes-per-task, or --episodes for random PINs")
        given = parse_pin_list(args.tasks)
        episodes_per_task = _positive(args.episodes_per_task, "--episodes-per-task")
        pins, pin_length = [pin for _ in range(episodes_per_task) for pin in given], None
        tasks = {"tasks": [dial_task_description(pin) for pin in given]}
    else:
        if args.episodes_per_task is not None:
            raise ValueError("--episodes-per-task needs --tasks; random PINs take --episodes")
        pin_length = _positive(args.pin_length, "--pin-length")
        pins = random_pins(_positive(args.episodes, "--episodes"), pin_length, digits, args.seed, first_attempt)
        tasks = {}
    session = {"digits": list(digits), "pin_length": pin_length, "noise_levels": list(NOISE_LEVELS), **tasks}

    def make() -> ExpertRecorder:
        return DialRecorder(
            pins, reward=args.reward, seed=args.seed, first_attempt=first_attempt, batch_size=args.batch_size or 64
        )

    return make, dial_features(), DIAL_FPS, session


SETUPS = {"craft": _craft_setup, "dial": _dial_setup}
# Session fields that set how the demonstrations are drawn. A resumed recording must keep them, or
# one dataset would mix two distributions without its card saying so.
RESUME_KEEPS = {"craft": ("mode", "dart_noise"), "dial": ("digits", "noise_levels")}
# What a session recorded before the field existed meant by it.
RECORDED_BEFORE_THE_FIELD = {"env": "craft", "dart_noise": 0.0}


def check_resumable(last: dict, env: str, session: dict) -> None:
    """Refuse to append a session whose env or sampling settings differ from the dataset's last one."""
    recorded_env = last.get("env", RECORDED_BEFORE_THE_FIELD["env"])
    if recorded_env != env:
        raise ValueError(f"--resume: the dataset was recorded in env {recorded_env!r}, not {env!r}")
    for key in RESUME_KEEPS[env]:
        recorded = last.get(key, RECORDED_BEFORE_THE_FIELD.get(key))
        if recorded != session.get(key):
            raise ValueError(
                f"--resume: the dataset was recorded with {key} {recorded!r}, not {session.get(key)!r}; "
                "resume with the same setting or record into a new --root"
            )


def record(args: argparse.Namespace) -> int:
    """Run one recording session; returns the process exit code."""
    provenance = load_provenance(args.root) if args.resume else {"sessions": []}
    first_attempt = sum(s["attempts"] for s in provenance["sessions"])
    make_recorder, features, fps, world_session = SETUPS[args.env](args, first_attempt)
    if args.mcap is not None:
        check_new_log(args.mcap)
    if provenance["sessions"]:
        check_resumable(provenance["sessions"][-1], args.env, world_session)
    writer = ColumnarDatasetWriter(
        args.root, args.repo_id, fps, features,
        resume=args.resume,
        robot_type=args.env,
        language=args.subtask_annotations,
    )
    recorder = make_recorder()
    mcap = DemoMcapWriter(args.mcap, fps, features["observation.state"]["names"]) if args.mcap else None
    start_episodes = writer.total_episodes
    session = {
        "command": shlex.join(["record_demos", *args.argv]),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "env": args.env,
        "seed": args.seed,
        "reward": args.reward,
        **world_session,
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
    args.argv = sys.argv[1:] if argv is None else list(argv)  # the session's command, in-process calls too
    try:
        return record(args)
    except (ValueError, FileExistsError, FileNotFoundError, DatasetExistsError) as err:
        parser.exit(2, f"record_demos: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
