"""The work of `record_demos` (its command line is `ocn_data.record_demos`): check every input and output,
then record session by session, chunk by chunk, each chunk one atomic commit of the dataset.

The dataset is published chunk by chunk, each chunk one atomic commit carrying the data, the
metadata, the splits, the card and the session's provenance (its seed position and settings), so a
SIGKILL or a crash at any instant leaves a loadable dataset of every published chunk, and `--resume`
goes on with the seed stream after it. Ctrl-C (SIGINT) and SIGTERM stop at the next chunk boundary:
the episodes finished so far are published, and the exit code is 130 or 143. See ocn_data/README.md.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import signal
import sys
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from tqdm import tqdm

from lerobot_policy_ocn.envs.craft.render import TILE
from lerobot_policy_ocn.envs.craft.world import GRID_SIZE, parse_task_list, task_description
from lerobot_policy_ocn.envs.dial.expert import NOISE_LEVELS
from lerobot_policy_ocn.envs.dial.task import parse_digits, parse_pin_list
from lerobot_policy_ocn.envs.dial.task import task_description as dial_task_description
from lerobot_policy_ocn.ocn_data.craft_recorder import CRAFT_DART_NOISE
from lerobot_policy_ocn.ocn_data.craft_recorder import FPS as CRAFT_FPS
from lerobot_policy_ocn.ocn_data.craft_recorder import CraftRecorder, craft_features
from lerobot_policy_ocn.ocn_data.dial_recorder import FPS as DIAL_FPS
from lerobot_policy_ocn.ocn_data.dial_recorder import DialRecorder, dial_features, random_pins
from lerobot_policy_ocn.ocn_data.datacard import dataset_card
from lerobot_policy_ocn.ocn_data.doctor import diagnose
from lerobot_policy_ocn.ocn_data.durable import FolderTransaction, previous_path, recover
from lerobot_policy_ocn.ocn_data.episodes import EpisodeChunk
from lerobot_policy_ocn.ocn_data.episodes_table import read_info
from lerobot_policy_ocn.ocn_data.lerobot_writer import (
    STOP_SIGNALS,
    ColumnarDatasetWriter,
    DatasetExistsError,
    NoDatasetError,
    held_stop_signals,
)
from lerobot_policy_ocn.ocn_data.mcap_log import DemoMcapWriter, check_new_log
from lerobot_policy_ocn.ocn_data.preflight import check_can_create, check_repo_id
from lerobot_policy_ocn.ocn_data.provenance import PROVENANCE, load_provenance, write_provenance
from lerobot_policy_ocn.ocn_data.recorder import ExpertRecorder


class DamagedDatasetError(Exception):
    """`--resume` on a dataset that must be repaired (or resumed with another seed) first."""


class WriteFailedError(Exception):
    """Writing failed mid-way (disk full, a file size limit, a read-only mount): what was published stays."""


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


def check_outputs(args: argparse.Namespace) -> None:
    """Everything about the outputs that can be refused before anything is written."""
    check_repo_id(args.repo_id)
    if args.chunk_episodes < 1:
        raise ValueError(f"--chunk-episodes must be >= 1, got {args.chunk_episodes}")
    if not 0.0 <= args.val_fraction < 1.0:
        raise ValueError(f"--val-fraction must be in [0, 1), got {args.val_fraction}")
    if args.mcap is not None:
        check_new_log(args.mcap)
        check_can_create(args.mcap, "--mcap")
    recoverable = previous_path(args.root).exists()
    if args.resume and not (args.root.exists() or recoverable):
        raise NoDatasetError(args.root)
    if not args.resume:
        if args.root.exists() or recoverable:
            raise DatasetExistsError(args.root)
        check_can_create(args.root, "--root")


def check_sound(root: Path) -> None:
    """`--resume` appends only to a dataset that ocn-doctor finds sound (what an interrupted commit
    left beside it is removed before)."""
    diagnosis = diagnose(root)
    if diagnosis.findings:
        raise DamagedDatasetError(
            f"--resume: {diagnosis.findings[0]} Run `ocn-doctor --repair {root}` first (`ocn-doctor {root}` lists "
            "every problem)."
        )


def check_accounted(root: Path, provenance: dict, seed: int) -> None:
    """Refuse a resume that would draw again the seeds of episodes no session accounts for (a
    session cut off before record_demos committed its record with each chunk), unless the seed is new."""
    sessions = provenance["sessions"]
    accounted = sum(session["episodes"] for session in sessions)
    total = read_info(root)["total_episodes"]
    used = sorted({session["seed"] for session in sessions})
    if sessions and accounted < total and seed in used:
        raise DamagedDatasetError(
            f"--resume: {root / PROVENANCE} accounts for {accounted} of its {total} episodes (a session was cut off "
            f"before its record was written), so --seed {seed} could record some of them again; resume with a "
            f"--seed no session used (used: {', '.join(map(str, used))})."
        )


class StopRequest:
    """SIGINT and SIGTERM during a recording: both stop it at the next chunk boundary (the chunk
    being published is finished first, see `held_stop_signals`); `signum` says which came."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __call__(self, signum: int, frame: object) -> None:
        self.signum = signum
        raise KeyboardInterrupt

    @property
    def name(self) -> str:
        return signal.Signals(self.signum or signal.SIGINT).name

    @property
    def exit_code(self) -> int:
        """The shell's convention: 128 + the signal (130 for SIGINT, 143 for SIGTERM)."""
        return 128 + (self.signum or signal.SIGINT)


def record(args: argparse.Namespace) -> int:
    """Run one recording session; returns the process exit code."""
    check_outputs(args)
    for done in recover(args.root):
        print(f"record_demos: {done}", file=sys.stderr)
    provenance = {"sessions": []}
    if args.resume:
        check_sound(args.root)
        provenance = load_provenance(args.root)
        check_accounted(args.root, provenance, args.seed)
    first_attempt = sum(s["attempts"] for s in provenance["sessions"])
    make_recorder, features, fps, world_session = SETUPS[args.env](args, first_attempt)
    if provenance["sessions"]:
        check_resumable(provenance["sessions"][-1], args.env, world_session)
        if provenance["sessions"][-1].get("status") == "recording":
            print(f"record_demos: the last session was cut off (SIGKILL or a crash) after "
                  f"{provenance['sessions'][-1]['episodes']} episodes; its seed stream goes on here", file=sys.stderr)
    writer = ColumnarDatasetWriter(
        args.root, args.repo_id, fps, features,
        resume=args.resume,
        robot_type=args.env,
        language=args.subtask_annotations,
        val_fraction=args.val_fraction,
    )
    recorder = make_recorder()
    start_episodes = writer.total_episodes
    session = {
        "command": shlex.join(["record_demos", *args.argv]),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "env": args.env,
        "seed": args.seed,
        "reward": args.reward,
        "val_fraction": args.val_fraction,
        **world_session,
        "status": "recording",
        "interrupted": True,
        "episodes": 0,
        "attempts": 0,
        "expert_failures": 0,
    }
    sessions = [*provenance["sessions"], session]
    bar = tqdm(total=recorder.total, unit="ep", desc=f"record {args.repo_id}")
    log: DemoMcapWriter | None = None

    def finish(transaction: FolderTransaction) -> None:
        """Each published version carries the session as far as it got, and its card."""
        transaction.fresh(PROVENANCE)
        write_provenance(transaction.staging, {**provenance, "sessions": sessions})
        transaction.fresh("README.md").write_text(dataset_card(transaction.staging, args.repo_id))

    def save(chunk: EpisodeChunk) -> None:
        """The chunk goes to the MCAP log first (flushed), then into the dataset; a stop request
        waits for both, so the log never holds a chunk under episode indices the dataset gives others."""
        nonlocal log
        with held_stop_signals():
            if args.mcap is not None and chunk.num_episodes:
                try:
                    if log is None:
                        log = DemoMcapWriter(args.mcap, fps, features["observation.state"]["names"])
                    log.write(chunk, writer.total_episodes)
                    log.flush()
                except OSError as error:
                    error.filename = error.filename or str(args.mcap)
                    raise
            session.update(
                episodes=writer.total_episodes + chunk.num_episodes - start_episodes,
                attempts=recorder.attempts - first_attempt,
                expert_failures=recorder.failures,
            )
            writer.write(chunk, finish)
        bar.update(chunk.num_episodes)

    stop = StopRequest()
    handlers = {signum: signal.signal(signum, stop) for signum in STOP_SIGNALS}
    try:
        try:
            for chunk in recorder.chunks(args.chunk_episodes):
                save(chunk)
            session["status"] = "finished"
        except KeyboardInterrupt:
            session["status"] = f"interrupted by {stop.name}"
        except Exception:
            session["status"] = "stopped by an error"
            with contextlib.suppress(Exception):  # the first error is the one to report
                save(recorder.take_finished())
            raise
        session["interrupted"] = session["status"] != "finished"
        for signum in STOP_SIGNALS:  # the last save is short: a second stop request must not cut it off
            signal.signal(signum, signal.SIG_IGN)
        save(recorder.take_finished())
    except OSError as error:
        raise WriteFailedError(
            f"{error.strerror or error} writing {error.filename or args.root}; {args.root} keeps its "
            f"{writer.total_episodes} published episodes" + (f" and {args.mcap} the flushed ones" if log else "")
            + ": make room (or fix the path), then record the rest with --resume"
        ) from error
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        bar.close()
    if log is not None:
        log.close()
    recorded = writer.total_episodes - start_episodes
    interrupted = session["interrupted"]
    print(
        f"{'interrupted: ' if interrupted else ''}recorded {recorded} episodes "
        f"({writer.total_episodes} in total, {writer.total_frames} frames) into {args.root}"
        + (f"; MCAP log {args.mcap}" if log else "")
        + ("" if writer.total_episodes else " (no dataset written: no episode was finished)")
    )
    return stop.exit_code if interrupted else 0
