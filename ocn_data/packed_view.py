"""A copy of a recorded dataset with each episode packed into one row, for fast `lerobot-train` runs.

A recurrent policy trained on whole episodes needs every frame of the sampled episode, and LeRobot's
windowed `__getitem__` assembles a window frame by frame, formatting every column of each: about
5 ms per window on S1's training view (`results/bench_train.md`), more than the model's update for a
batch of 128 on 2 cores. In the packed view each episode is one frame whose extra columns hold the
whole episode, padded to a fixed width: `observation.packed.state` [width * S],
`observation.packed.action` [width * A] and `observation.packed.length` (the real frames), each in the
smallest dtype that holds the data exactly. `lerobot-train` then loads one row per sample and the policy unpacks it
(`--policy.window_start=packed`, `policies.sequence.training_windows`).

The row keeps the episode's first `observation.state` and `action` (and the source's statistics of
both), and the policy drops the packed columns from its features, so that its features, and hence its
checkpoints, are those of the recorded dataset. LeRobot's default normaliser passes the packed columns on
as they are; the OCN processors add a step that normalises them frame by frame with the source's statistics
(`policies.ocn.processor_ocn.PackedEpisodeNormalizerStep`), so the view serves rescaled states and actions
(Dial) as well as Craft's stored ids.

Episodes, their indices, tasks and splits are the source's, so `--dataset.episodes` names the same
train split. LeRobot's sampler then draws episodes uniformly instead of in proportion to their length
(one row each): the loss is the mean NLL over the batch's real frames (`policies.sequence.batch_mean`),
the same per-frame mean in expectation.

A dataset whose longest episodes exceed the width (Dial's rare long DART episodes) packs with
`cut_long`: those episodes keep their first `width` frames, the frames `--policy.skip_long_episodes`
trains them on under windows, in a view of its own.

A labelled view (`option_labels`, a file of `ocn_data.option_labels`) adds `observation.packed.option`,
each frame's option label, which `--policy.taught_options=true` teaches (`OCNPolicy.labelled_forward`);
it lives in a folder named after the file's content.

`python -m ocn_data.packed_view --root DATASET --width W [--cut-long-episodes] [--option-labels F]` makes
(or checks) the view.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from lerobot.datasets.io_utils import load_stats, write_info, write_stats
from lerobot.utils.constants import ACTION, OBS_STATE

from ocn_data.episodes import EpisodeChunk
from ocn_data.episodes_table import load_episodes, read_info, split_episodes
from ocn_data.option_labels import labels_fingerprint, read_labels
from ocn_data.lerobot_writer import ColumnarDatasetWriter
from ocn_data.training_view import derived_dataset

# Named as observations so that LeRobot's processors pass them to the policy, which drops them from its
# features (`policies.sequence.prepare_config`): they are data layout, not inputs.
PACKED_STATE = "observation.packed.state"
PACKED_ACTION = "observation.packed.action"
PACKED_LENGTH = "observation.packed.length"
# Only in a labelled view (`--option-labels`): each frame's taught option, -1 past the end and on
# episodes the label file leaves out (the validation split).
PACKED_OPTION = "observation.packed.option"
PACKED_KEYS = (PACKED_STATE, PACKED_ACTION, PACKED_LENGTH, PACKED_OPTION)
# Episodes per data file of the view.
CHUNK_EPISODES = 5000


def packed_view_path(root: Path, width: int, cut_long: bool = False, option_labels: Path | None = None) -> Path:
    """Where the view of the dataset at `root` packed to `width` frames lives: a sibling folder
    (`_cut` when its longer episodes are cut to their first `width` frames, `_options<hash>` when it
    holds the option labels of a file, named by the file's content)."""
    root = Path(root)
    labelled = "" if option_labels is None else f"_options{labels_fingerprint(option_labels)[:12]}"
    return root.parent / f"{root.name}_packed{width}{'_cut' if cut_long else ''}{labelled}"


def compact_dtype(values: np.ndarray) -> np.dtype:
    """The smallest dtype that holds `values` exactly: unsigned or signed integers of 8 to 64 bits
    for integer and boolean data, float32 for floats (LeRobot stores float features as float32)."""
    if values.dtype.kind == "f":
        return np.dtype(np.float32)
    if values.size == 0:
        return np.dtype(np.uint8)
    low, high = int(values.min()), int(values.max())
    for dtype in (np.uint8, np.int16, np.int32, np.int64):
        info = np.iinfo(dtype)
        if info.min <= low and high <= info.max:
            return np.dtype(dtype)
    raise ValueError(f"integer values from {low} to {high} do not fit in int64")


def pad_to_width(values: np.ndarray, mask: np.ndarray, width: int) -> np.ndarray:
    """Episodes [E, T, ...] with real frames `mask` [E, T] as [E, width, ...] in `compact_dtype`, zeros after
    each end."""
    real = mask.reshape(*mask.shape, *[1] * (values.ndim - 2))
    padded = np.zeros((values.shape[0], width, *values.shape[2:]), compact_dtype(values[mask]))
    padded[:, : values.shape[1]] = np.where(real, values, 0)
    return padded


def packed_features(source: dict, width: int, state: np.dtype, action: np.dtype,
                    option: np.dtype | None = None) -> dict[str, dict]:
    """The view's features: the source's state and action (one frame), and the packed columns (the
    taught options' too when `option` gives their dtype)."""
    state_size = int(np.prod(source[OBS_STATE]["shape"]))
    action_size = int(np.prod(source[ACTION]["shape"]))
    features = {
        OBS_STATE: source[OBS_STATE],
        ACTION: source[ACTION],
        PACKED_STATE: {"dtype": state.name, "shape": [width * state_size], "names": None},
        PACKED_ACTION: {"dtype": action.name, "shape": [width * action_size], "names": None},
        PACKED_LENGTH: {"dtype": "int64", "shape": [1], "names": None},
    }
    if option is not None:
        features[PACKED_OPTION] = {"dtype": option.name, "shape": [width], "names": None}
    return features


def write_packed(root: Path, repo_id: str, view: Path, width: int, cut_long: bool = False,
                 option_labels: Path | None = None) -> None:
    """Write the packed view of the dataset at `root` into the new folder `view`; `cut_long` keeps the
    first `width` frames of longer episodes, as `--policy.skip_long_episodes` trains them on windows;
    `option_labels`: a label file (`ocn_data.option_labels`) whose labels the view adds."""
    info = read_info(root)
    episodes = load_episodes(root, split_episodes(root, "all"))
    longest = int(episodes.lengths.max())
    if longest > width and not cut_long:
        raise ValueError(f"{root} has episodes of up to {longest} frames; a packed view of width {width} cannot hold "
                         f"them. Pass --width {longest} or more (and train with --policy.window_size equal to it), "
                         f"or --cut-long-episodes to keep their first {width} frames.")
    count = len(episodes.lengths)
    mask = episodes.mask[:, :width]
    state, action = (pad_to_width(values[:, :width], mask, width) for values in (episodes.state, episodes.action))
    columns = {}
    if option_labels is not None:
        options = read_labels(option_labels, episodes.episode_index, episodes.lengths, width, unlabelled_ok=True)
        columns[PACKED_OPTION] = options.astype(compact_dtype(options))
    print(f"writing the packed view of {root} ({count} episodes, width {width}) to {view}", flush=True)
    features = packed_features(info["features"], width, state.dtype, action.dtype,
                               columns[PACKED_OPTION].dtype if columns else None)
    writer = ColumnarDatasetWriter(view, repo_id, info["fps"], features, robot_type=info.get("robot_type"))
    for start in range(0, count, CHUNK_EPISODES):
        rows = slice(start, min(count, start + CHUNK_EPISODES))
        n = rows.stop - rows.start
        writer.write(EpisodeChunk(
            lengths=np.ones(n, dtype=np.int64), tasks=episodes.tasks[rows], segments=[[] for _ in range(n)],
            columns={
                OBS_STATE: episodes.state[rows, 0],
                ACTION: episodes.action[rows, 0],
                PACKED_STATE: state[rows].reshape(n, -1),
                PACKED_ACTION: action[rows].reshape(n, -1),
                PACKED_LENGTH: np.minimum(episodes.lengths[rows, None], width).astype(np.int64),
                **{key: values[rows] for key, values in columns.items()},
            },
        ))
    # The source's statistics of state and action (the view's own cover first frames only) and its splits.
    stats, source_stats = load_stats(view), load_stats(root)
    stats.update({key: source_stats[key] for key in (OBS_STATE, ACTION)})
    write_stats(stats, view)
    view_info = writer.meta.info
    view_info.splits = dict(info.get("splits") or {})
    write_info(view_info, view)


def packed_view(root: Path, repo_id: str, width: int, cut_long: bool = False,
                option_labels: Path | None = None) -> Path:
    """The packed view of the dataset at `root`, made if missing or out of date; returns its root.
    `cut_long`: episodes longer than `width` keep their first `width` frames (else they are an error);
    `option_labels`: a label file whose labels the view holds as `PACKED_OPTION`."""
    root = Path(root)
    settings = {"packed_width": width, **({"cut_long_episodes": True} if cut_long else {}),
                **({"option_labels_sha256": labels_fingerprint(option_labels)} if option_labels else {})}
    return derived_dataset(root, packed_view_path(root, width, cut_long, option_labels), settings,
                           lambda view: write_packed(root, repo_id, view, width, cut_long, option_labels))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ocn_data.packed_view", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a LeRobot dataset written by record_demos")
    parser.add_argument("--repo-id", default="local/craft", help="the dataset's repo id")
    parser.add_argument("--width", type=int, required=True,
                        help="frames per packed episode: the --policy.window_size to train with (at least the "
                             "longest episode, unless --cut-long-episodes)")
    parser.add_argument("--cut-long-episodes", action="store_true",
                        help="keep the first --width frames of longer episodes (what --policy.skip_long_episodes "
                             "trains on windows), in a view of its own (`_cut`)")
    parser.add_argument("--option-labels", type=Path,
                        help="an option label file (tools.affine_segmentation --out) whose labels the view adds, "
                             "for lerobot-train --policy.taught_options=true")
    args = parser.parse_args(argv)
    print(packed_view(args.root, args.repo_id, args.width, args.cut_long_episodes, args.option_labels))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
