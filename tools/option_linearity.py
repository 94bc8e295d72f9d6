"""`python -m tools.option_linearity`: how much of the demonstrated control an affine map per group of
frames explains, for the true subtasks, the moves between them, and each checkpoint's own options.

A memoryless option is a map from the observation to an action. Any grouping of the frames in which
the observation tells each group's actions apart can be cloned by wide enough options, which is why
wide options on Dial settle on groups of key-to-key moves instead of digits. A grouping that an
affine map per group already explains well is one that options of little capacity can take; the
score compares groupings by that. It is R^2: 1 minus the squared error of least-squares affine
maps from the stored observation to the standardised action, fitted per group on the frames of the
first training episodes, over the actions' total variance. A checkpoint's groups are its parse's
options (argmax p^c), so its row reads no labels.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


def affine_r2(state: np.ndarray, action: np.ndarray, groups: np.ndarray) -> float:
    """R^2 of one least-squares affine map from `state` [F, S] to `action` [F, A] per value of
    `groups` [F], each action dimension standardised first so that every joint counts alike."""
    action = (action - action.mean(0)) / action.std(0).clip(1e-8)
    residual = 0.0
    for group in np.unique(groups):
        rows = groups == group
        inputs = np.c_[state[rows], np.ones(rows.sum())]
        weights, *_ = np.linalg.lstsq(inputs, action[rows], rcond=None)
        residual += float(((action[rows] - inputs @ weights) ** 2).sum())
    return 1.0 - residual / float((action**2).sum())


def frame_groups(episodes: Any) -> dict[str, np.ndarray]:
    """Per real frame, the groupings from the labels: none (one group), the true subtask, and the move
    into it (the previous true subtask and this one)."""
    from tools.episode_parsing import frame_moves

    subtask, previous = frame_moves(episodes)
    move = (previous + 1) * (subtask.max() + 1) + subtask
    return {"one group": np.zeros_like(subtask), "subtask": subtask, "move into the subtask": move}


def option_groups(checkpoint: Path, episodes: Any) -> np.ndarray:
    """Per real frame, the option a checkpoint's parse chooses (argmax p^c)."""
    from tools.episode_parsing import load_ocn, parse_episodes

    policy, preprocessor, _ = load_ocn(checkpoint)
    return np.concatenate([parse.option for parse in parse_episodes(policy, preprocessor, episodes)])


def measure(root: Path, checkpoints: list[Path], max_episodes: int) -> dict[str, Any]:
    """R^2 of the label groupings and of each checkpoint's options, on the first training episodes."""
    from ocn_data.episodes_table import load_episodes, split_episodes

    episodes = load_episodes(root, split_episodes(root, "train"), max_episodes=max_episodes)
    state, action = episodes.state[episodes.mask], episodes.action[episodes.mask]
    groups = frame_groups(episodes)
    scores = {name: affine_r2(state, action, labels) for name, labels in groups.items()}
    for checkpoint in checkpoints:
        options = option_groups(checkpoint, episodes)
        scores[f"options of {checkpoint}"] = affine_r2(state, action, options)
    return {"root": str(root), "episodes": len(episodes.tasks), "frames": int(episodes.mask.sum()),
            "groups": {name: len(np.unique(labels)) for name, labels in groups.items()}, "affine_r2": scores}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.option_linearity", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a record_demos dataset with a train split")
    parser.add_argument("--policy", type=Path, nargs="*", default=[], help="ocn pretrained_model folders")
    parser.add_argument("--max-episodes", type=int, default=2400, help="training episodes fitted (the first ones)")
    parser.add_argument("--out", type=Path, help="also write the result as JSON")
    args = parser.parse_args(argv)
    result = measure(args.root, args.policy, args.max_episodes)
    for name, score in result["affine_r2"].items():
        print(f"{score:.3f}  {name}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
