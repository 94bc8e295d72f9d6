"""A copy of a recorded dataset with only the columns a policy trains on, for `lerobot-train`.

LeRobot's windowed `__getitem__` formats every column of every frame of a window, whichever keys the
window asks for, so the evaluation-only columns of a `record_demos` dataset (the ground-truth subtask
labels, rewards and done flags) cost loading time on every training step while no policy reads them.
The view keeps `observation.*`, `action` and LeRobot's bookkeeping columns; it is made once with
LeRobot's own `remove_feature` beside the dataset, remade whenever the dataset's metadata changes, and
the evaluation tools keep reading the full dataset. Same episodes, frames, tasks and splits: the same
training windows (tests/test_training_view.py); `ocn-bench train` measures the loading speed-up.

`python -m ocn_data.training_view --root DATASET` makes (or checks) the view of one dataset.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import shutil
from collections.abc import Callable
from pathlib import Path

from lerobot.utils.constants import DEFAULT_FEATURES

from ocn_data.episodes_table import read_info

# Written last into the view's meta/: the source metadata's fingerprint, so an interrupted or stale view is remade.
MARKER = "meta/ocn_training_view.json"


def training_view_path(root: Path) -> Path:
    """Where the view of the dataset at `root` lives: a sibling folder."""
    root = Path(root)
    return root.parent / f"{root.name}_training_view"


def trained_columns(features: dict) -> list[str]:
    """The features a policy's training reads: observations, the action, LeRobot's own columns."""
    return [
        name for name in features if name.startswith("observation.") or name == "action" or name in DEFAULT_FEATURES
    ]


def metadata_fingerprint(root: Path) -> str:
    """SHA-256 over every file of the dataset's `meta/` folder (info, tasks, per-episode tables and
    statistics): a re-recording changes it even when the episode and frame counts stay the same."""
    digest = hashlib.sha256()
    meta = Path(root) / "meta"
    for path in sorted(p for p in meta.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(meta)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def training_view(root: Path, repo_id: str) -> Path:
    """The training view of the dataset at `root`, made if missing or out of date; returns its root.
    A dataset that has nothing to drop is returned as it is."""
    from lerobot.datasets.dataset_tools import remove_feature
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    features = read_info(root)["features"]
    kept = trained_columns(features)
    dropped = [name for name in features if name not in kept]
    if not dropped:
        return root

    def write(view: Path) -> None:
        print(f"writing the training view of {root} (without {', '.join(dropped)}) to {view}", flush=True)
        remove_feature(LeRobotDataset(repo_id, root=root), dropped, output_dir=view, repo_id=repo_id)

    return derived_dataset(root, training_view_path(root), {"dropped": dropped}, write)


def derived_dataset(root: Path, view: Path, settings: dict, write: Callable[[Path], None],
                    marker: str = MARKER) -> Path:
    """The folder `write(view)` derives from the dataset at `root` (a view of it, or a fit on it),
    written unless `view` holds one made from the same source metadata with the same `settings`;
    returns `view`. `marker`: where in `view` the record of what made it goes.

    Reproductions run side by side (`ocn-reproduce --first-seed`) may ask at once: one writes, the
    others wait. The marker goes in last, so an interrupted write is redone."""
    record = {"source": str(root), "source_meta_sha256": metadata_fingerprint(root), **settings}
    made_by = view / marker
    with open(view.parent / f"{view.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if made_by.is_file() and _same_derivation(json.loads(made_by.read_text()), record):
            return view
        shutil.rmtree(view, ignore_errors=True)
        write(view)
        made_by.write_text(json.dumps(record, indent=2) + "\n")
    return view


def _same_derivation(made: dict, wanted: dict) -> bool:
    return all(made.get(key) == value for key, value in wanted.items() if key != "source")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ocn_data.training_view", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a LeRobot dataset written by record_demos")
    parser.add_argument("--repo-id", default="local/craft", help="the dataset's repo id")
    args = parser.parse_args(argv)
    print(training_view(args.root, args.repo_id))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
