"""`python -m tools.affine_segmentation`: option labels for demonstrations without subtask labels, from a
switching affine policy, for `tools.fast_imitation --supervise-options --option-labels`.

On Dial, one affine map from the state to the action per digit explains the demonstrated control far
better than the groupings that OCN's own loss settles on (`tools.option_linearity`), yet gradient
descent on that loss rarely finds the digits. This fits the simpler model directly: N affine maps, and
per episode a path through them that pays `switch_penalty` per change, scored by the squared error of
the standardised actions. It alternates the best paths (a Viterbi pass, all episodes at once) with a
least-squares refit of each map on its frames. That descent also stops in local optima, so the best of
a few random starts is then improved by split-and-merge moves (Ueda et al., 2000): two maps' frames are
merged, a third map's frames are split at random between it and the freed map, and the descent runs
again; a move is kept when it lowers the total cost. No label is read for the fit; the ground truth
only scores the result in the report.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ocn_data.option_labels import write_labels

RIDGE = 1e-3  # keeps each map's normal equations solvable when its frames span few states


@dataclass
class Frames:
    """Episodes as the fit reads them: inputs [E, T, S + 1] (the state and a 1), standardised actions
    [E, T, A] and the mask of real frames [E, T]."""

    inputs: np.ndarray
    targets: np.ndarray
    mask: np.ndarray


def action_standardisation(action: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean and std (at least 1e-8) of the real frames' actions, so that every action dimension counts alike."""
    real = action[mask]
    return real.mean(0), real.std(0).clip(1e-8)


def episode_frames(state: np.ndarray, action: np.ndarray, mask: np.ndarray,
                   action_stats: tuple[np.ndarray, np.ndarray] | None = None) -> Frames:
    """`Frames` of padded episodes; actions standardised by `action_stats` (mean, std), by default
    their own (`action_standardisation`)."""
    if action_stats is None:
        action_stats = action_standardisation(action, mask)
    inputs = np.concatenate([state, np.ones(state.shape[:2] + (1,))], -1)
    return Frames(inputs, (action - action_stats[0]) / action_stats[1], mask)


def fit_maps(frames: Frames, labels: np.ndarray, n_maps: int, rng: np.random.Generator) -> np.ndarray:
    """Per label, the ridge least-squares affine map [S + 1, A] of its frames, stacked [N, S + 1, A]. A
    label with too few frames to fit (one emptied by the descent) is fitted on a random 1% of all
    frames, which gives it a fresh start instead of a singular system."""
    maps = []
    for option in range(n_maps):
        rows = labels == option
        if rows.sum() < frames.inputs.shape[-1]:
            rows = frames.mask & (rng.random(labels.shape) < 0.01)
        x, y = frames.inputs[rows], frames.targets[rows]
        maps.append(np.linalg.solve(x.T @ x + RIDGE * np.eye(x.shape[1]), x.T @ y))
    return np.stack(maps)


def squared_errors(frames: Frames, maps: np.ndarray) -> np.ndarray:
    """Each frame's squared action error under each map [E, T, N]."""
    n_maps, n_inputs, n_actions = maps.shape
    stacked = maps.transpose(1, 0, 2).reshape(n_inputs, n_maps * n_actions)  # all maps in one matmul
    predicted = (frames.inputs @ stacked).reshape(*frames.inputs.shape[:2], n_maps, n_actions)
    return ((frames.targets[:, :, None] - predicted) ** 2).sum(-1)


def best_paths(errors: np.ndarray, mask: np.ndarray, switch_penalty: float) -> tuple[np.ndarray, float]:
    """Per episode, the sequence of maps [E, T] (-1 on padding) minimising the summed frame errors plus
    `switch_penalty` per change (Viterbi, all episodes in one array), and the summed minimum cost."""
    n_episodes, length, n_maps = errors.shape
    rows = np.arange(n_episodes)
    cost = errors[:, 0].copy()
    came_from = np.zeros((n_episodes, length, n_maps), dtype=np.int64)
    for t in range(1, length):
        cheapest = cost.argmin(1)
        switched = cost[rows, cheapest][:, None] + switch_penalty
        move = switched < cost
        came_from[:, t] = np.where(move, cheapest[:, None], np.arange(n_maps))
        cost = np.where(mask[:, t, None], np.minimum(cost, switched) + errors[:, t], cost)
    lengths = mask.sum(1)
    labels = np.full((n_episodes, length), -1)
    current = cost.argmin(1)
    for t in range(length - 1, -1, -1):
        real = t < lengths
        labels[real, t] = current[real]
        current = np.where(real & (t > 0), came_from[rows, t, current], current)
    return labels, float(cost.min(1).sum())


def descend(frames: Frames, labels: np.ndarray, n_maps: int, switch_penalty: float, rng: np.random.Generator,
            max_rounds: int = 50, tolerance: float = 1e-4) -> tuple[np.ndarray, float]:
    """Alternate refitting the maps and the best paths from `labels` until the paths stop changing or
    the cost falls by less than `tolerance` of itself in a round."""
    cost = np.inf
    for _ in range(max_rounds):
        maps = fit_maps(frames, labels, n_maps, rng)
        new_labels, new_cost = best_paths(squared_errors(frames, maps), frames.mask, switch_penalty)
        settled = np.array_equal(new_labels, labels) or cost - new_cost < tolerance * new_cost
        labels, cost = new_labels, new_cost
        if settled:
            break
    return labels, cost


def random_chunks(mask: np.ndarray, n_maps: int, chunk: int, rng: np.random.Generator) -> np.ndarray:
    """A random start: each run of `chunk` frames of an episode gets a random map (-1 on padding)."""
    n_episodes, length = mask.shape
    draws = rng.integers(n_maps, size=(n_episodes, length // chunk + 1))
    return np.where(mask, np.repeat(draws, chunk, 1)[:, :length], -1)


def split_and_merge(frames: Frames, labels: np.ndarray, cost: float, n_maps: int, switch_penalty: float,
                    rng: np.random.Generator, chunk: int, max_rounds: int = 5,
                    min_gain: float = 1e-3) -> tuple[np.ndarray, float, int]:
    """Try every merge of two maps with a random split of a third; keep each move that lowers the cost
    by more than `min_gain` of itself, and go round again until no move does (at most `max_rounds`).
    Returns the labels, their cost and the moves kept."""
    kept = 0
    moves = [(merged, freed, split) for merged, freed in itertools.combinations(range(n_maps), 2)
             for split in range(n_maps) if split not in (merged, freed)]
    for round_index in range(max_rounds):
        improved = False
        progress = tqdm(moves, desc=f"split-and-merge round {round_index + 1}")
        for merged, freed, split in progress:
            trial = np.where(labels == freed, merged, labels)
            halves = random_chunks(frames.mask, 2, chunk, rng) == 1
            trial[(labels == split) & halves] = freed
            trial, trial_cost = descend(frames, trial, n_maps, switch_penalty, rng)
            if trial_cost < cost * (1 - min_gain):
                labels, cost, improved, kept = trial, trial_cost, True, kept + 1
            progress.set_postfix(cost=f"{cost:.6g}", kept=kept)
        if not improved:
            break
    return labels, cost, kept


@dataclass
class SegmentationFit:
    """The fitted maps [N, S + 1, A], the training episodes' labels [E, T] and the fit's history."""

    maps: np.ndarray
    labels: np.ndarray
    cost: float
    start_costs: list[float]
    moves_kept: int


def fit_segmentation(frames: Frames, n_maps: int, switch_penalty: float, starts: int, seed: int,
                     chunk: int = 20) -> SegmentationFit:
    """The best of `starts` random descents, then improved by split-and-merge (which moves three maps
    at a time, so fewer than three are left as the descents leave them)."""
    if starts < 1:
        raise ValueError(f"--starts must be at least 1, got {starts}.")
    rng = np.random.default_rng(seed)
    results = [descend(frames, random_chunks(frames.mask, n_maps, chunk, rng), n_maps, switch_penalty, rng)
               for _ in tqdm(range(starts), desc="random starts")]
    labels, cost = min(results, key=lambda result: result[1])
    labels, cost, kept = split_and_merge(frames, labels, cost, n_maps, switch_penalty, rng, chunk)
    return SegmentationFit(fit_maps(frames, labels, n_maps, rng), labels, cost,
                           [result[1] for result in results], kept)


def ground_truth_scores(episodes: Any, labels: np.ndarray) -> dict[str, float]:
    """F1 at tolerance 0 and 1, task alignment and NMI of per-frame labels against the episodes' truth."""
    from tools.episode_parsing import Segmentation, score_segmentations
    from tools.parsing_metrics import boundaries_from_labels

    parses = []
    for row, length in enumerate(episodes.lengths):
        frame_labels = labels[row, :length]
        parses.append(Segmentation(boundaries_from_labels(frame_labels), frame_labels))
    return score_segmentations(episodes, parses)


def label_episodes(episodes: Any, maps: np.ndarray, action_stats: tuple[np.ndarray, np.ndarray],
                   switch_penalty: float, episodes_per_pass: int = 1000) -> np.ndarray:
    """Each frame's map [E, T] (-1 on padding) on the best paths through fitted `maps`, a pass of at most
    about `episodes_per_pass` episodes at a time so that the error table stays small."""
    parts = np.array_split(np.arange(len(episodes.lengths)), max(1, len(episodes.lengths) // episodes_per_pass))
    return np.concatenate([
        best_paths(squared_errors(episode_frames(episodes.state[part], episodes.action[part], episodes.mask[part],
                                                 action_stats), maps), episodes.mask[part], switch_penalty)[0]
        for part in parts
    ])


def segment_dataset(args: argparse.Namespace) -> dict[str, Any]:
    """Fit on the first training episodes, label every training episode, report against the truth."""
    from ocn_data.episodes_table import load_episodes, split_episodes
    from ocn_data.training_view import metadata_fingerprint

    started = time.perf_counter()
    train = load_episodes(args.root, split_episodes(args.root, "train"))
    if not np.issubdtype(train.action.dtype, np.floating):
        raise SystemExit(f"{args.root} has actions of dtype {train.action.dtype}; "
                         "the affine maps need continuous ones.")
    action_stats = action_standardisation(train.action, train.mask)
    fitted = min(args.fit_episodes, len(train.tasks))
    fit_part = episode_frames(train.state[:fitted], train.action[:fitted], train.mask[:fitted], action_stats)
    fit = fit_segmentation(fit_part, args.n_options, args.switch_penalty, args.starts, args.seed, args.chunk)
    labels = label_episodes(train, fit.maps, action_stats, args.switch_penalty)
    write_labels(args.out, train, labels)
    val = load_episodes(args.root, split_episodes(args.root, "val"))
    val_labels = label_episodes(val, fit.maps, action_stats, args.switch_penalty)
    return {"root": str(args.root), "source_meta_sha256": metadata_fingerprint(args.root), "labels": str(args.out),
            "n_options": args.n_options,
            "switch_penalty": args.switch_penalty, "starts": args.starts, "seed": args.seed, "chunk": args.chunk,
            "fit_episodes": fitted, "cost": fit.cost, "start_costs": fit.start_costs,
            "split_and_merge_moves_kept": fit.moves_kept, "label_share": np.bincount(
                labels[train.mask], minlength=args.n_options).tolist(),
            "train_scores": ground_truth_scores(train, labels), "val_scores": ground_truth_scores(val, val_labels),
            "seconds": time.perf_counter() - started}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m tools.affine_segmentation", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a record_demos dataset with continuous actions")
    parser.add_argument("--out", type=Path, required=True, help="the training split's labels (.npz)")
    parser.add_argument("--report", type=Path, help="also write the fit's costs and its scores against the truth")
    parser.add_argument("--n-options", type=int, default=4)
    parser.add_argument("--switch-penalty", type=float, default=30.0,
                        help="cost of a change of map, in squared standardised action error")
    parser.add_argument("--starts", type=int, default=3, help="random starts before split-and-merge")
    parser.add_argument("--chunk", type=int, default=20, help="frames per randomly labelled run of a start")
    parser.add_argument("--fit-episodes", type=int, default=1200,
                        help="training episodes the maps are fitted on (the first ones); all are labelled")
    parser.add_argument("--seed", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    report = segment_dataset(args)
    print(json.dumps({key: report[key] for key in ("cost", "split_and_merge_moves_kept", "train_scores",
                                                   "val_scores")}, indent=1))
    if args.report is not None:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
