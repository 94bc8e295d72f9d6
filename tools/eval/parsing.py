"""A trained policy read back over recorded episodes: one place for loading a checkpoint and parsing.

`ocn-eval` scores the parse, `ocn-view` draws it and `ocn-annotate` writes it into a dataset.
Checkpoints load with `load_policy` (any registered type) or `load_ocn` (tools that need OCN's
options). `parse_episodes` gives OCN's per-step hierarchy of whole episodes; `segment_episodes`
gives every model type's parse in the one form the shared parsing metrics read (a `Segmentation`
per episode), through that type's entry in `PARSERS`: a new model type adds an entry there.
`choose_boundary_threshold` tunes OMPN's count-free read-out on training episodes;
`validation_nll` scores a checkpoint's fit to held-out demonstrations, labels unread.
`policy_episodes` reads a dataset's episodes with every input feature a policy reads (after checking
that the dataset has them, as the policy saw them in training); `label_free_figures` describes a
parse without any ground truth (option usage, segment lengths, switch rate).
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION
from lerobot_policy_ocn.ocn_data.episodes_table import EpisodeArrays
from lerobot_policy_ocn.ocn import OCNPolicy
from lerobot_policy_ocn.ompn.modeling_ompn import expansion_boundaries, threshold_boundaries
from lerobot_policy_ocn.tools.eval.metrics import boundaries_from_labels, parsing_scores, segment_starts

Processor = Callable[[Any], Any]


@dataclass
class EpisodeParse:
    """One episode's hierarchy, per real step: p_c [T, N], option = argmax p^c [T], end = e_t [T]
    (1 at t = 1, where the controller always chooses)."""

    p_c: np.ndarray
    option: np.ndarray
    end: np.ndarray

    @property
    def switches(self) -> np.ndarray:
        """Steps t >= 1 (0-based) where the chosen option differs from the step before."""
        return segment_starts(self.option)[1:]


@dataclass
class Segmentation:
    """One episode's parse as the shared metrics read it: `boundaries`, the last step of each
    predicted segment (sorted); `labels` [T], a per-step option label, or None for a model
    without discrete options (NMI needs labels); and `action_log_prob` [T], the log-likelihood of
    each demonstrated action under the same parse, or None for a model that has no per-step one."""

    boundaries: np.ndarray
    labels: np.ndarray | None
    action_log_prob: np.ndarray | None = None


class Segmenter(Protocol):
    """How one model type parses whole episodes for the metrics (one Segmentation per episode)."""

    def __call__(
        self, policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int
    ) -> list[Segmentation]: ...


@dataclass(frozen=True)
class Parser:
    """A model type's entry: its `segment` function; for a model whose parses may come without
    per-step labels, `no_labels`: why they have none (reported in place of NMI when they do); and for
    a model whose parse gives no per-step action likelihood, `no_action_nll`: why (in place of
    `action_nll`)."""

    segment: Segmenter
    no_labels: str | None = None
    no_action_nll: str | None = None


def checkpoint_type(path: Path) -> str:
    """The policy type a checkpoint's config.json names, read before anything is loaded."""
    config = Path(path) / "config.json"
    if not config.exists():
        raise FileNotFoundError(f"{path} holds no config.json: pass a checkpoint's pretrained_model folder.")
    try:
        policy_type = json.loads(config.read_text()).get("type")
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError) as error:
        raise ValueError(f"{config} is not a valid config ({error}): the checkpoint is damaged; copy it again.") \
            from None
    if not isinstance(policy_type, str):
        raise ValueError(f"{config} names no policy type: pass a checkpoint's pretrained_model folder.")
    return policy_type


def check_checkpoint_files(path: Path) -> None:
    """Every JSON file of a checkpoint parses and every safetensors file is whole (its header and the
    tensors it announces fit in the file): a truncated copy is named here, not deep in LeRobot."""
    from safetensors import SafetensorError, safe_open

    for file in sorted(Path(path).glob("*.json")):
        try:
            json.loads(file.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as error:
            raise ValueError(f"{file} is truncated or corrupt ({error}): copy the checkpoint again.") from None
    for file in sorted(Path(path).glob("*.safetensors")):
        try:
            with safe_open(file, "pt"):
                pass
        except SafetensorError as error:
            raise ValueError(f"{file} is truncated or corrupt ({error}): copy the checkpoint again.") from None


@contextmanager
def scratch_tempdir() -> Iterator[None]:
    """Temporary files go to a folder removed on exit: LeRobot's `PreTrainedConfig.from_pretrained` writes
    the config it parses to a temporary JSON that it never deletes (one more in /tmp at every load)."""
    previous = tempfile.tempdir
    with tempfile.TemporaryDirectory(prefix="ocn_load_") as folder:
        tempfile.tempdir = folder
        try:
            yield
        finally:
            tempfile.tempdir = previous


def load_policy(
    path: Path, device: str = "cpu", types: Sequence[str] | None = None
) -> tuple[PreTrainedPolicy, Processor, Processor]:
    """A checkpoint (a `pretrained_model` folder) of any registered policy type, or of one of `types`
    (what the calling tool takes), in eval mode, with its pre/post-processors. The project's types are
    registered first, as LeRobot's CLIs do, so that every policy type it ships (`ocn`, `ompn`,
    `compile`) loads in any process. A checkpoint of another type, or with a damaged file, is a
    one-line ValueError naming it, before any weight is read."""
    import draccus
    from lerobot.configs import PreTrainedConfig

    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    from lerobot_policy_ocn import register

    register()
    path = Path(path)
    policy_type = checkpoint_type(path)
    if types is not None and policy_type not in types:
        wanted = " or ".join(", ".join(f"`{t}`" for t in types).rsplit(", ", 1))
        raise ValueError(f"{path} holds an `{policy_type}` checkpoint; this tool needs an {wanted} one.")
    check_checkpoint_files(path)
    try:
        with scratch_tempdir():
            config = PreTrainedConfig.from_pretrained(path)
    except draccus.utils.DraccusException as error:
        raise ValueError(f"{path / 'config.json'} does not describe a `{policy_type}` policy: {error}") from None
    try:
        policy = get_policy_class(config.type).from_pretrained(path, config=config)
    except RuntimeError as error:
        first_line = str(error).strip().splitlines()[0]
        raise ValueError(f"{path / 'model.safetensors'} does not fit {path / 'config.json'}: {first_line}") from None
    policy.config.device = device
    policy.to(device).eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy.config, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}}
    )
    return policy, preprocessor, postprocessor


def load_ocn(path: Path, device: str = "cpu") -> tuple[OCNPolicy, Processor, Processor]:
    """`load_policy` for tools that need OCN's options: another policy type is a ValueError."""
    return load_policy(path, device, types=("ocn",))


def check_tasks(policy: PreTrainedPolicy, episodes: EpisodeArrays) -> None:
    """Every task of the episodes must be one the policy was trained on."""
    unknown = sorted(set(episodes.tasks) - set(policy.config.tasks))
    if unknown:
        raise ValueError(f"The dataset has tasks {unknown} that the policy was not trained on ({policy.config.tasks}).")


def input_keys(policy: PreTrainedPolicy) -> list[str]:
    """The dataset features a policy reads: its state features, then its image features."""
    return [*policy.config.state_keys, *policy.config.image_keys]


def check_dataset(policy: PreTrainedPolicy, root: Path) -> None:
    """The dataset at `root` must hold every feature the policy reads, in the shape it was trained on, and
    an action of its width: anything else is a one-line ValueError naming the feature."""
    from lerobot.utils.feature_utils import dataset_to_policy_features

    from lerobot_policy_ocn.ocn_data.episodes_table import read_info

    stored = read_info(root)["features"]
    found = dataset_to_policy_features({key: ft for key, ft in stored.items() if key in (*input_keys(policy), ACTION)})
    wanted = {**policy.config.input_features, **policy.config.output_features}
    missing = ", ".join(f"`{key}`" for key in wanted if key not in found)
    if missing:
        raise ValueError(f"{root} has no {missing}, which this {policy.name} policy reads: pass the dataset it was "
                         f"trained on, or one with the same features (it has {sorted(stored)}).")
    for key, feature in wanted.items():
        if tuple(found[key].shape) != tuple(feature.shape):
            raise ValueError(f"`{key}` has shape {tuple(found[key].shape)} in {root}, but this {policy.name} policy "
                             f"was trained on shape {tuple(feature.shape)}: pass the dataset it was trained on.")


def policy_episodes(policy: PreTrainedPolicy, root: Path, episodes: range,
                    max_episodes: int | None = None) -> EpisodeArrays:
    """The selected episodes of the dataset at `root` (`load_episodes`) with every input the policy reads,
    images at its `image_size`, after `check_dataset`."""
    from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes

    check_dataset(policy, root)
    return load_episodes(root, episodes, max_episodes, input_keys(policy), policy.config.image_size)


def parsed_episodes(
    policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int, keys: Sequence[str]
) -> Iterator[dict[str, np.ndarray]]:
    """`policy.parse`'s outputs `keys` for each whole episode, cut to its real steps, in episode order.
    The episodes must hold the policy's inputs (`policy_episodes`)."""
    check_tasks(policy, episodes)
    missing = [key for key in input_keys(policy) if key not in episodes.inputs]
    if missing:
        raise ValueError(f"The episodes were read without {missing}, which the policy reads: read them with "
                         "lerobot_policy_ocn.tools.eval.parsing.policy_episodes.")
    for start in range(0, len(episodes.tasks), batch_size):
        rows = slice(start, start + batch_size)
        inputs = {key: torch.from_numpy(episodes.inputs[key][rows]) for key in input_keys(policy)}
        batch = {
            **{key: value if value.dtype == torch.uint8 else value.float() for key, value in inputs.items()},
            ACTION: torch.from_numpy(episodes.action[rows]).float(),
            f"{ACTION}_is_pad": torch.from_numpy(~episodes.mask[rows]),
            "task": episodes.tasks[rows],
        }
        with torch.no_grad():
            parsed = policy.parse(preprocessor(batch))
        parsed = {key: parsed[key].cpu().numpy() for key in keys}
        for i, length in enumerate(episodes.lengths[rows]):
            yield {key: value[i, :length] for key, value in parsed.items()}


def parse_episodes(
    policy: OCNPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int = 1024
) -> list[EpisodeParse]:
    """The OCN's hierarchy over each whole episode, cut to the episode's real steps."""
    parsed = parsed_episodes(policy, preprocessor, episodes, batch_size, ("p_c", "option", "end"))
    return [EpisodeParse(**episode) for episode in parsed]


def _ocn_segmentations(
    policy: OCNPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int
) -> list[Segmentation]:
    """OCN: the chosen option argmax p^c labels each step; a segment ends where it changes."""
    parsed = parsed_episodes(policy, preprocessor, episodes, batch_size, ("option", "action_log_prob"))
    return [
        Segmentation(boundaries_from_labels(episode["option"]), episode["option"], episode["action_log_prob"])
        for episode in parsed
    ]


def _ompn_segmentations(
    policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int
) -> list[Segmentation]:
    """OMPN: per episode, `expansion_boundaries` (its top-k read-out in the shared boundary
    convention), k = the episode's number of ground-truth boundaries (OMPN is told how many, as in
    its own evaluation); or, when the config sets `boundary_threshold`, the count-free
    `threshold_boundaries`."""
    parsed = _ompn_parse(policy, preprocessor, episodes, batch_size)
    return _ompn_read_out(episodes, parsed, policy.config.boundary_threshold)


def _ompn_parse(
    policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int
) -> list[dict[str, np.ndarray]]:
    """OMPN's per-step expected expansion height (`depth`) and action log-likelihood of each episode."""
    return list(parsed_episodes(policy, preprocessor, episodes, batch_size, ("depth", "action_log_prob")))


def _ompn_read_out(
    episodes: EpisodeArrays, parsed: Sequence[dict[str, np.ndarray]], threshold: float | None
) -> list[Segmentation]:
    """The Segmentations of an OMPN parse (`_ompn_parse`) under one read-out: top-k told each
    episode's count (`threshold` None) or count-free at `threshold`. Episodes without ground truth have
    no count to tell: they need the count-free read-out."""
    if threshold is None and not episodes.labelled:
        raise ValueError("OMPN's top-k read-out is told each episode's number of subtasks, which a dataset without "
                         "ground truth does not have: pass --boundary-threshold (e.g. 0.5) for its count-free one.")
    counts = [boundaries_from_labels(episodes.subtask_index[i, :n]).size if threshold is None else 0
              for i, n in enumerate(episodes.lengths)]
    return [
        Segmentation(
            expansion_boundaries(episode["depth"], k) if threshold is None
            else threshold_boundaries(episode["depth"], threshold),
            None,
            episode["action_log_prob"],
        )
        for episode, k in zip(parsed, counts, strict=True)
    ]


def _compile_segmentations(
    policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int
) -> list[Segmentation]:
    """compILE: the hard parse (argmax boundaries, as in its evaluation); a segment ends at the step
    before the argmax position of its boundary distribution (the next segment's first step), the
    last at the episode's last step, and positions that start no new segment (one at or before an
    earlier boundary) add none. Labels: each step's segment's concrete latent category (argmax);
    Gaussian latents give none."""
    concrete = policy.config.latent_type == "concrete"
    parsed = parsed_episodes(policy, preprocessor, episodes, batch_size, ("segment", "label"))
    return [
        Segmentation(boundaries_from_labels(episode["segment"]), episode["label"] if concrete else None)
        for episode in parsed
    ]


PARSERS: dict[str, Parser] = {
    "ocn": Parser(_ocn_segmentations),
    "ompn": Parser(
        _ompn_segmentations,
        no_labels=(
            "OMPN has no discrete per-step choice to label steps with: its memory is continuous and only "
            "its boundaries are read out. A segment index derived from them would restate the boundaries "
            "(already scored by F1 and alignment), and, numbering segments within an episode, would not "
            "be an identity that recurs across tasks, which is what NMI measures for OCN's options."
        ),
    ),
    "compile": Parser(
        _compile_segmentations,
        no_labels=(
            "compILE with Gaussian latents has no discrete latent to label steps with (NMI needs "
            "categories); train it with --policy.latent_type=concrete for per-step labels."
        ),
        no_action_nll=(
            "compILE's likelihood of an action depends on the segment it falls in, a sum over soft "
            "segmentations rather than one per-step prediction."
        ),
    ),
}


def parser_of(policy: PreTrainedPolicy) -> Parser:
    """The `PARSERS` entry of the policy's type; a type without one is a ValueError."""
    if policy.name not in PARSERS:
        raise ValueError(f"No parse is defined for `{policy.name}` policies; the parsed types are {sorted(PARSERS)}.")
    return PARSERS[policy.name]


def action_nll(parses: Sequence[Segmentation]) -> float:
    """Mean NLL of the demonstrated actions per real frame, from parses of whole episodes (each run
    through the policy from its first frame): the behaviour-cloning fit, to compare between splits
    (a train NLL far below the validation one is memorised demonstrations)."""
    missing = sum(parse.action_log_prob is None for parse in parses)
    if missing:
        raise ValueError(f"{missing} of {len(parses)} parses carry no per-step action log-likelihood.")
    return -float(np.concatenate([parse.action_log_prob for parse in parses]).mean())


def validation_nll(checkpoint: Path, root: Path, max_episodes: int | None = None) -> float:
    """`action_nll` of a checkpoint on the validation split of the dataset at `root` (its first
    `max_episodes` episodes): how well it clones held-out demonstrations, read without their subtask
    labels, so that it may choose between runs without looking at the scores it is judged on."""
    from lerobot_policy_ocn.ocn_data.episodes_table import split_episodes

    policy, preprocessor, _ = load_policy(checkpoint)
    episodes = policy_episodes(policy, root, split_episodes(root, "val"), max_episodes)
    return action_nll(segment_episodes(policy, preprocessor, episodes))


def segment_episodes(
    policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays, batch_size: int = 1024
) -> list[Segmentation]:
    """Any parsed model type's Segmentation of each whole episode."""
    return parser_of(policy).segment(policy, preprocessor, episodes, batch_size)


def label_free_figures(episodes: EpisodeArrays, parses: Sequence[Segmentation]) -> dict[str, Any]:
    """What a parse says without any ground truth: `segments_per_episode`; `segment_length` (frames per
    predicted segment: mean, median, min, max); `switch_rate`, the switches (segment starts after an
    episode's first frame) per frame; and for labelled parses `option_usage`, each label's share of
    the frames ([label 0, 1, ... up to the highest used]: an unused option shows as 0)."""
    lengths = np.concatenate([np.diff(np.r_[-1, parse.boundaries]) for parse in parses])
    switches = sum(len(parse.boundaries) - 1 for parse in parses)
    figures: dict[str, Any] = {
        "segments_per_episode": float(np.mean([len(parse.boundaries) for parse in parses])),
        "segment_length": {"mean": float(lengths.mean()), "median": float(np.median(lengths)),
                           "min": int(lengths.min()), "max": int(lengths.max())},
        "switch_rate": switches / int(episodes.lengths.sum()),
    }
    if all(parse.labels is not None for parse in parses):
        labels = np.concatenate([parse.labels for parse in parses]).astype(np.int64)
        figures["option_usage"] = _shares(labels, labels.max() + 1)
    return figures


def parse_statistics(episodes: EpisodeArrays, parses: Sequence[Segmentation]) -> dict[str, Any]:
    """How a parse cuts the episodes against their ground truth, which the scores alone hide: predicted
    and true segments per episode, and, for labelled parses, each label's share of the frames ([share
    of label 0, 1, ..., up to the highest label used]), where an unused option shows as a share of 0
    (or is past the list's end) and a parse that never switches as one segment; and `label_by_subtask`: for each true
    subtask id, the share of its frames under each label (a pair of options that split two subtasks
    half and half between them, which NMI only summarises, shows here as two rows of halves); and
    `label_by_subtask_third`: the same shares in the first, middle and last third of each true
    segment (None for a third without frames), which tell a pair that splits subtasks by target
    from one that splits them by phase, one option starting every subtask and the other finishing it;
    `label_by_transition`: the same shares per pair of the previous true subtask and this one, keyed
    "PREVIOUS>SUBTASK" ("start>SUBTASK" for each episode's first), which tell options that follow the
    subtasks from options that follow the moves between them (a Dial option that takes key 4 to 1 and
    key 1 to 2 serves two digits, one from each key);
    `boundary_offsets`: where the parse puts each true boundary, one step early, on time, late...
    (`_boundary_offsets`), and for discrete actions the same by the action before the boundary step."""
    true_segments = [len(boundaries_from_labels(episodes.subtask_index[i, :n])) for i, n in enumerate(episodes.lengths)]
    stats: dict[str, Any] = {
        "segments_per_episode": float(np.mean([len(parse.boundaries) for parse in parses])),
        "true_segments_per_episode": float(np.mean(true_segments)),
    }
    if all(parse.labels is not None for parse in parses):
        labels = np.concatenate([parse.labels for parse in parses]).astype(np.int64)
        stats["label_share"] = _shares(labels, labels.max() + 1)
        subtasks, previous = frame_moves(episodes)
        stats["label_by_subtask"] = {
            str(subtask): _shares(labels[subtasks == subtask], labels.max() + 1) for subtask in np.unique(subtasks)
        }
        thirds = np.concatenate(
            [_segment_thirds(episodes.subtask_index[i, :n]) for i, n in enumerate(episodes.lengths)]
        )
        stats["label_by_subtask_third"] = {
            str(subtask): [
                _shares(labels[(subtasks == subtask) & (thirds == third)], labels.max() + 1) for third in range(3)
            ]
            for subtask in np.unique(subtasks)
        }
        stats["label_by_transition"] = {
            f"{'start' if before < 0 else before}>{subtask}": _shares(
                labels[(previous == before) & (subtasks == subtask)], labels.max() + 1)
            for before, subtask in sorted(set(zip(previous.tolist(), subtasks.tolist(), strict=True)))
        }
    offsets = _boundary_offsets(episodes, parses)
    stats["boundary_offsets"] = _offset_shares(offsets)
    if episodes.action.shape[-1] == 1:  # discrete actions: which move led to the boundary step
        stats["boundary_offsets_by_previous_action"] = {
            str(action): _offset_shares([o for o in offsets if o[0] == action])
            for action in sorted({action for action, _ in offsets})
        }
    return stats


OFFSET_BINS = ("-2", "-1", "0", "1", "2", "farther")


def _boundary_offsets(episodes: EpisodeArrays, parses: Sequence[Segmentation]) -> list[tuple[int, str]]:
    """Per inner true boundary (the last step of a subtask that is not the episode's last): the
    demonstrated action one step before it (-1 at step 0; the first action dimension) and the offset
    of the nearest inner predicted boundary (predicted - true, as a bin of OFFSET_BINS; 'farther':
    none within 2 steps). -1 is a switch one step early: the next subtask's option takes its last step."""
    offsets = []
    for i, n in enumerate(episodes.lengths):
        predicted = parses[i].boundaries[parses[i].boundaries < n - 1]
        for t in boundaries_from_labels(episodes.subtask_index[i, :n])[:-1]:
            nearest = int(predicted[np.argmin(np.abs(predicted - t))] - t) if predicted.size else None
            action = int(episodes.action[i, t - 1, 0]) if t > 0 else -1
            offsets.append((action, str(nearest) if nearest is not None and abs(nearest) <= 2 else "farther"))
    return offsets


def _offset_shares(offsets: Sequence[tuple[int, str]]) -> dict[str, Any]:
    """How many inner true boundaries `offsets` holds and the share of each offset bin."""
    bins = [offset for _, offset in offsets]
    return {"boundaries": len(bins), **{b: round(bins.count(b) / len(bins), 4) if bins else None for b in OFFSET_BINS}}


def _segment_thirds(segment_index: np.ndarray) -> np.ndarray:
    """Per frame of one episode's segment index [T], the third (0, 1, 2) of its segment it lies in:
    frame j of a segment of L frames is in third floor(3 j / L)."""
    starts = segment_starts(segment_index)
    lengths = np.diff(np.r_[starts, segment_index.size])
    offset = np.arange(segment_index.size) - np.repeat(starts, lengths)
    return 3 * offset // np.repeat(lengths, lengths)


def frame_moves(episodes: EpisodeArrays) -> tuple[np.ndarray, np.ndarray]:
    """Per real frame of the episodes, in order: its true subtask id, and the id of the true segment
    before its own (-1 in an episode's first segment); the two make the move into the subtask."""
    subtasks, previous = [], []
    for i, n in enumerate(episodes.lengths):
        subtask_id = episodes.subtask_id[i, :n]
        starts = segment_starts(episodes.subtask_index[i, :n])
        before = np.r_[-1, subtask_id[starts[:-1]]]
        subtasks.append(subtask_id)
        previous.append(np.repeat(before, np.diff(np.r_[starts, n])))
    return np.concatenate(subtasks), np.concatenate(previous)


def _shares(labels: np.ndarray, n_labels: int) -> list[float] | None:
    """Each label's share of `labels`, rounded; None when there are none."""
    return (np.bincount(labels, minlength=n_labels) / labels.size).round(4).tolist() if labels.size else None


SCORES = ("f1_tol0", "f1_tol1", "align_acc", "nmi")


def score_segmentations(episodes: EpisodeArrays, parses: Sequence[Segmentation]) -> dict[str, float | None]:
    """The shared parsing metrics of one Segmentation per episode against the episodes' ground truth:
    f1_tol0, f1_tol1 and align_acc from the boundaries, nmi from the labels (None without labels).
    Only the predictions count, never which model made them. Episodes without ground truth have no
    scores: every one is None."""
    if not episodes.labelled:
        return dict.fromkeys(SCORES)
    segments = [episodes.subtask_index[i, :n] for i, n in enumerate(episodes.lengths)]
    subtasks = [episodes.subtask_id[i, :n] for i, n in enumerate(episodes.lengths)]
    labelled = all(parse.labels is not None for parse in parses)
    labels = [parse.labels for parse in parses] if labelled else None
    scores: dict[str, float | None] = parsing_scores(segments, subtasks, [parse.boundaries for parse in parses], labels)
    scores.setdefault("nmi", None)
    return scores


# Thresholds of OMPN's count-free read-out tried by `choose_boundary_threshold`: OMPN's own code uses
# 0.4-0.6 on the same scaled height; the lower ones find the shallow expansions of later subtasks.
BOUNDARY_THRESHOLDS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)


def choose_boundary_threshold(
    policy: PreTrainedPolicy, preprocessor: Processor, episodes: EpisodeArrays,
    thresholds: Sequence[float] = BOUNDARY_THRESHOLDS, batch_size: int = 1024,
) -> tuple[float, dict[float, float]]:
    """The threshold of OMPN's count-free read-out (`threshold_boundaries`) whose parse of `episodes`
    has the best F1@1 (ties to the lower), and each threshold's F1@1. Pass training episodes: the
    threshold is a setting of the read-out, so it is chosen on episodes the reported scores do not
    use. The episodes are parsed once and every threshold reads that parse; the policy's own
    read-out is not touched."""
    if not hasattr(policy.config, "boundary_threshold"):
        raise ValueError(f"`{policy.name}` has no count-free boundary read-out to tune.")
    parsed = _ompn_parse(policy, preprocessor, episodes, batch_size)
    f1 = {threshold: score_segmentations(episodes, _ompn_read_out(episodes, parsed, threshold))["f1_tol1"]
          for threshold in thresholds}
    return max(thresholds, key=lambda threshold: (f1[threshold], -threshold)), f1
