"""The Dial recipe's first phase: option labels found without subtask labels, which the options are taught.

On Dial, gradient descent on the paper's loss rarely splits the digits
(results/archive/dial_induced_2026-12-06, `--split induced`), yet one affine map from the state to the
action per digit explains most of the expert's control. So the recipe fits that simpler model directly
and teaches its split to OCN: N affine maps, and per episode a path through them that pays
`SWITCH_PENALTY` per change, scored by the squared error of the standardised actions. The fit alternates
the best paths (a Viterbi pass over all episodes at once) with a least-squares refit of each map on its
frames. That descent stops in local optima, so the best of a few random starts is then improved by
split-and-merge moves (Ueda et al., 2000): two maps' frames are merged, a third map's frames are split
at random between it and the freed map, and the descent runs again; a move is kept when it lowers the
total cost. No subtask label is read.

The fit depends only on the training episodes' states and actions and the settings below, so it is
cached by their hash (`cached_split`): every clone of a recording shares one fit.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

RIDGE = 1e-3  # keeps each map's normal equations solvable when its frames span few states
# The fit's settings (results/archive/dial_affine_2026-12-06): a change of map costs 30 squared
# standardised action errors;
# the best of 3 random starts, each of runs of 20 frames with a random map, fitted on the first 1,200
# training episodes (all are labelled), fit seed 0.
SWITCH_PENALTY = 30.0
STARTS = 3
CHUNK = 20
FIT_EPISODES = 1200
FIT_SEED = 0


@dataclass
class Frames:
    """Episodes as the fit reads them: inputs [E, T, S + 1] (the state and a 1), standardised actions
    [E, T, A] and the mask of real frames [E, T]."""

    inputs: np.ndarray
    targets: np.ndarray
    mask: np.ndarray


def episode_frames(state: np.ndarray, action: np.ndarray, mask: np.ndarray,
                   action_stats: tuple[np.ndarray, np.ndarray]) -> Frames:
    """`Frames` of padded episodes, actions standardised by `action_stats` (mean, std)."""
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
    for _ in range(max_rounds):
        improved = False
        for merged, freed, split in moves:
            trial = np.where(labels == freed, merged, labels)
            halves = random_chunks(frames.mask, 2, chunk, rng) == 1
            trial[(labels == split) & halves] = freed
            trial, trial_cost = descend(frames, trial, n_maps, switch_penalty, rng)
            if trial_cost < cost * (1 - min_gain):
                labels, cost, improved, kept = trial, trial_cost, True, kept + 1
        if not improved:
            break
    return labels, cost, kept


@dataclass
class SegmentationFit:
    """The fitted maps [N, S + 1, A], the fitted episodes' labels [E, T] and the fit's history."""

    maps: np.ndarray
    labels: np.ndarray
    cost: float
    start_costs: list[float]
    moves_kept: int


def fit_segmentation(frames: Frames, n_maps: int, switch_penalty: float, starts: int, seed: int,
                     chunk: int = CHUNK) -> SegmentationFit:
    """The best of `starts` random descents, then improved by split-and-merge (which moves three maps
    at a time, so fewer than three are left as the descents leave them)."""
    if starts < 1:
        raise ValueError(f"starts must be at least 1, got {starts}.")
    rng = np.random.default_rng(seed)
    results = [descend(frames, random_chunks(frames.mask, n_maps, chunk, rng), n_maps, switch_penalty, rng)
               for _ in range(starts)]
    labels, cost = min(results, key=lambda result: result[1])
    labels, cost, kept = split_and_merge(frames, labels, cost, n_maps, switch_penalty, rng, chunk)
    return SegmentationFit(fit_maps(frames, labels, n_maps, rng), labels, cost,
                           [result[1] for result in results], kept)


def label_frames(frames: Frames, maps: np.ndarray, switch_penalty: float, episodes_per_pass: int = 1000) -> np.ndarray:
    """Each frame's map [E, T] (-1 on padding) on the best paths through fitted `maps`, a pass of at most
    about `episodes_per_pass` episodes at a time so that the error table stays small."""
    parts = np.array_split(np.arange(len(frames.mask)), max(1, len(frames.mask) // episodes_per_pass))
    return np.concatenate([
        best_paths(squared_errors(Frames(frames.inputs[part], frames.targets[part], frames.mask[part]), maps),
                   frames.mask[part], switch_penalty)[0]
        for part in parts
    ])


@dataclass
class SplitReport:
    """How a split was found: its cost, the random starts' costs, the split-and-merge moves kept, the
    share of frames per option and the fit's wall seconds (from the run that fitted it)."""

    cost: float
    start_costs: list[float]
    moves_kept: int
    label_share: list[int]
    seconds: float


def affine_split(state: np.ndarray, action: np.ndarray, mask: np.ndarray,
                 n_options: int) -> tuple[np.ndarray, SplitReport]:
    """The labels [E, T] (-1 on padding) of padded episodes (raw states [E, T, S], actions [E, T, A]): the
    maps are fitted on the first `FIT_EPISODES` and every episode is labelled on its best path."""
    started = time.perf_counter()
    real = action[mask]
    action_stats = (real.mean(0), real.std(0).clip(1e-8))
    frames = episode_frames(state, action, mask, action_stats)
    fitted = Frames(frames.inputs[:FIT_EPISODES], frames.targets[:FIT_EPISODES], frames.mask[:FIT_EPISODES])
    fit = fit_segmentation(fitted, n_options, SWITCH_PENALTY, STARTS, FIT_SEED)
    labels = label_frames(frames, fit.maps, SWITCH_PENALTY)
    share = np.bincount(labels[mask], minlength=n_options).tolist()
    return labels, SplitReport(fit.cost, fit.start_costs, fit.moves_kept, share, time.perf_counter() - started)


def split_cache_dir() -> Path:
    """Where fits are kept: beside LeRobot's own cache (`HF_LEROBOT_HOME`), in `ocn_affine_splits/`."""
    lerobot_home = os.environ.get("HF_LEROBOT_HOME")
    base = Path(lerobot_home) if lerobot_home else Path.home() / ".cache" / "huggingface" / "lerobot"
    return base / "ocn_affine_splits"


def cached_split(state: np.ndarray, action: np.ndarray, mask: np.ndarray,
                 n_options: int) -> tuple[np.ndarray, SplitReport]:
    """`affine_split`, read from the cache when the same episodes were split with the same settings
    before, else fitted and written there (atomically, so that runs side by side never read half a file)."""
    digest = hashlib.sha256()
    for array in (state, action, mask):
        digest.update(np.ascontiguousarray(array).tobytes())
    digest.update(json.dumps([n_options, SWITCH_PENALTY, STARTS, CHUNK, FIT_EPISODES, FIT_SEED, RIDGE]).encode())
    path = split_cache_dir() / f"{digest.hexdigest()[:24]}.npz"
    if path.exists():
        stored = np.load(path)
        return stored["labels"], SplitReport(**json.loads(str(stored["report"])))
    logging.info(f"Fitting the switching affine split of {int(mask.sum())} frames into {n_options} options "
                 f"(cached in {path})")
    labels, report = affine_split(state, action, mask, n_options)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(f".{os.getpid()}.partial.npz")
    np.savez_compressed(partial, labels=labels, report=json.dumps(asdict(report)))
    os.replace(partial, path)
    return labels, report
