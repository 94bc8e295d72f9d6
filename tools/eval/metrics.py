"""Parsing metrics (OMPN's definitions, paper appendix A.4), written once for every model.

A model's parse of an episode is given as per-step labels (OCN: the chosen option, argmax p^c) or
directly as boundary steps (OMPN, compILE); the ground truth is the per-step subtask. A boundary
is the last step of a segment ("a segment runs up to and including its boundary step"), so every
episode's final step is one: the last subtask completes there.
"""

from collections.abc import Sequence
from typing import Any

import numpy as np


def boundaries_from_labels(labels: Sequence[int] | np.ndarray) -> np.ndarray:
    """Steps t where a segment ends: labels[t + 1] != labels[t], and the final step."""
    labels = np.asarray(labels)
    if labels.size == 0:
        return np.zeros(0, dtype=np.int64)
    changes = np.flatnonzero(labels[1:] != labels[:-1])
    return np.append(changes, labels.size - 1).astype(np.int64)


def segment_starts(labels: Sequence[int] | np.ndarray) -> np.ndarray:
    """First step of each maximal run of equal labels: 0, then the step after each inner boundary."""
    return np.append(0, boundaries_from_labels(labels)[:-1] + 1).astype(np.int64)


def _hits(source: np.ndarray, target: np.ndarray, tolerance: int) -> int:
    """How many of `source` have some element of `target` within `tolerance` steps."""
    if source.size == 0 or target.size == 0:
        return 0
    return int((np.abs(source[:, None] - target[None, :]) <= tolerance).any(axis=1).sum())


def f1_with_tolerance(
    true_boundaries: Sequence[np.ndarray], predicted_boundaries: Sequence[np.ndarray], tolerance: int
) -> float:
    """F1 over all episodes: a true boundary is recalled, a predicted one is precise, when the other
    side has a boundary within `tolerance` steps; counts are summed over episodes first."""
    if len(true_boundaries) != len(predicted_boundaries):
        raise ValueError(f"{len(true_boundaries)} true episodes against {len(predicted_boundaries)} predicted.")
    recalled = precise = n_true = n_predicted = 0
    for true, predicted in zip(true_boundaries, predicted_boundaries, strict=True):
        true, predicted = np.asarray(true), np.asarray(predicted)
        recalled += _hits(true, predicted, tolerance)
        precise += _hits(predicted, true, tolerance)
        n_true += true.size
        n_predicted += predicted.size
    if recalled == 0 or precise == 0:
        return 0.0
    precision, recall = precise / n_predicted, recalled / n_true
    return 2 * precision * recall / (precision + recall)


def _segment_index(boundaries: np.ndarray, length: int) -> np.ndarray:
    """Per step, which segment (0, 1, ...) contains it, for segments ending at `boundaries`."""
    return np.searchsorted(np.sort(boundaries), np.arange(length), side="left")


def task_alignment_accuracy(
    true_labels: Sequence[np.ndarray], predicted_boundaries: Sequence[np.ndarray]
) -> float:
    """Fraction of steps whose predicted segment, matched in order to the episode's k-th true
    subtask, is that step's true subtask. Predicted segments beyond the true ones match nothing."""
    correct = total = 0
    for labels, predicted in zip(true_labels, predicted_boundaries, strict=True):
        labels = np.asarray(labels)
        subtasks = labels[segment_starts(labels)]
        segment = _segment_index(np.asarray(predicted), labels.size)
        in_range = segment < subtasks.size
        matched = np.where(in_range, subtasks[np.minimum(segment, subtasks.size - 1)], -1)
        correct += int((matched == labels).sum())
        total += labels.size
    return correct / total if total else 0.0


def _entropy(counts: np.ndarray) -> float:
    p = counts[counts > 0] / counts.sum()
    return float(-(p * np.log(p)).sum())


def normalized_mutual_info(a: Sequence[int] | np.ndarray, b: Sequence[int] | np.ndarray) -> float:
    """MI(a, b) / mean(H(a), H(b)) of two labelings of the same steps (scikit-learn's arithmetic NMI;
    1.0 when both are constant)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"Labelings differ in shape: {a.shape} and {b.shape}.")
    _, a_ids = np.unique(a, return_inverse=True)
    _, b_ids = np.unique(b, return_inverse=True)
    joint = np.zeros((a_ids.max() + 1, b_ids.max() + 1))
    np.add.at(joint, (a_ids, b_ids), 1)
    h_a, h_b = _entropy(joint.sum(1)), _entropy(joint.sum(0))
    if h_a == 0 and h_b == 0:
        return 1.0
    mi = h_a + h_b - _entropy(joint.ravel())
    return max(0.0, mi) / ((h_a + h_b) / 2)


def parsing_scores(
    true_segments: Sequence[np.ndarray],
    true_subtasks: Sequence[np.ndarray],
    predicted_boundaries: Sequence[np.ndarray],
    predicted_labels: Sequence[np.ndarray] | None = None,
) -> dict[str, float]:
    """f1_tol0, f1_tol1, align_acc, and nmi when per-step predicted labels exist.

    Per episode, `true_segments` numbers each step's subtask by its position in the task (0, 1, ...,
    so repeated subtasks stay apart) and `true_subtasks` names it (the subtask id, for NMI).
    """
    true_boundaries = [boundaries_from_labels(segments) for segments in true_segments]
    scores = {
        "f1_tol0": f1_with_tolerance(true_boundaries, predicted_boundaries, 0),
        "f1_tol1": f1_with_tolerance(true_boundaries, predicted_boundaries, 1),
        "align_acc": task_alignment_accuracy(true_segments, predicted_boundaries),
    }
    if predicted_labels is not None:
        scores["nmi"] = normalized_mutual_info(np.concatenate(predicted_labels), np.concatenate(true_subtasks))
    return scores


def option_table_summary(table: np.ndarray) -> dict[str, Any]:
    """Read an option x subtask success table [N options, K subtasks] (paper table 1).

    Options carry no names, so each subtask is matched to a distinct option by the assignment with
    the highest total success (`scipy.optimize.linear_sum_assignment`: polynomial, where trying every
    permutation took about 26 s at 10 x 10). `diagonal` is the matched cells, `off_diagonal_max` the
    best success of a matched option on any other subtask.
    """
    from scipy.optimize import linear_sum_assignment

    table = np.asarray(table, dtype=float)
    options, subtasks = linear_sum_assignment(table, maximize=True)
    matched = {int(subtask): int(option) for option, subtask in zip(options, subtasks, strict=True)}
    diagonal = [float(table[option, subtask]) for subtask, option in sorted(matched.items())]
    off = table[[option for _, option in sorted(matched.items())]].copy()  # row k: the option of subtask k's match
    for k, (subtask, _) in enumerate(sorted(matched.items())):
        off[k, subtask] = -np.inf
    off_max = float(off.max()) if np.isfinite(off).any() else 0.0
    return {
        "option_of_subtask": {int(s): int(o) for s, o in sorted(matched.items())},
        "diagonal": diagonal,
        "diagonal_mean": float(np.mean(diagonal)),
        "diagonal_min": float(np.min(diagonal)),
        "off_diagonal_max": off_max,
    }
