"""`record_demos` (also `ocn-record`): record scripted-expert demonstrations into a LeRobot v3.0 dataset
(+ MCAP log). This module is the command line; the recording is `ocn_data.recording`, imported once the
arguments are parsed, so that `--help` answers without loading LeRobot and torch.

Ground-truth subtask labels are stored for evaluation only (columns `subtask.*` and LeRobot
`language_persistent` rows). Every input and output is checked before anything is written; a SIGKILL
leaves every published chunk loadable, and SIGINT/SIGTERM stop at the next chunk boundary.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lerobot_policy_ocn.envs.craft.world import MODES, REWARDS
from lerobot_policy_ocn.ocn_data.craft_recorder import CRAFT_DART_NOISE


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
    p.add_argument("--mcap", type=Path,
                   help="also write every step to this MCAP file (must not exist); flushed with every chunk, so a "
                        "killed recording leaves every published episode in it (`ocn-doctor --repair FILE` "
                        "finishes it)")
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
    p.add_argument("--resume", action="store_true",
                   help="append to the existing dataset at --root, going on with its seed stream after any kind of "
                        "end (refused for a damaged dataset: see `ocn-doctor`)")
    p.add_argument("--val-fraction", type=float, default=0.2, help="last fraction of episodes that forms the val split")
    p.add_argument("--batch-size", type=int, help="envs stepped together (Craft 256, 16 with --video; Dial 64)")
    p.add_argument("--chunk-episodes", type=int, default=2000, help="episodes per written data file")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)  # the session's command, in-process calls too
    from lerobot_policy_ocn.ocn_data.doctor import NotRepairableError
    from lerobot_policy_ocn.ocn_data.recording import DamagedDatasetError, WriteFailedError, record

    try:
        return record(args)
    except (ValueError, FileExistsError, FileNotFoundError, DamagedDatasetError, NotRepairableError) as err:
        parser.exit(2, f"record_demos: error: {err}\n")
    except WriteFailedError as err:
        parser.exit(1, f"record_demos: error: {err}\n")


if __name__ == "__main__":
    sys.exit(main())
