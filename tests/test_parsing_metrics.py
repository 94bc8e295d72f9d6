"""The shared parsing metrics against hand-computed cases."""

import math

import numpy as np
import pytest

from lerobot_policy_ocn.tools.eval.metrics import (
    boundaries_from_labels,
    f1_with_tolerance,
    normalized_mutual_info,
    option_table_summary,
    parsing_scores,
    task_alignment_accuracy,
)


def test_boundaries_are_segment_ends_including_the_last_step():
    assert boundaries_from_labels([0, 0, 0, 1, 1, 2]).tolist() == [2, 4, 5]
    assert boundaries_from_labels([3, 3, 3]).tolist() == [2]
    assert boundaries_from_labels([]).tolist() == []


def test_f1_exact_and_with_tolerance():
    true = [np.array([2, 5])]
    off_by_one = [np.array([3, 5])]
    # tol 0: precision 1/2, recall 1/2 -> F1 1/2; tol 1: both boundaries matched.
    assert f1_with_tolerance(true, off_by_one, 0) == pytest.approx(0.5)
    assert f1_with_tolerance(true, off_by_one, 1) == pytest.approx(1.0)
    assert f1_with_tolerance(true, true, 0) == pytest.approx(1.0)


def test_f1_counts_are_summed_over_episodes():
    true = [np.array([2, 5]), np.array([1, 3, 7])]
    predicted = [np.array([5]), np.array([0, 3, 6, 7])]
    # precise: 1 + 2 = 3 of 5 predicted; recalled: 1 + 2 = 3 of 5 true.
    assert f1_with_tolerance(true, predicted, 0) == pytest.approx(2 * 0.6 * 0.6 / 1.2)
    # tol 1: precise 1 + 4 = 5/5, recalled 1 + 3 = 4/5.
    assert f1_with_tolerance(true, predicted, 1) == pytest.approx(2 * 1.0 * 0.8 / 1.8)
    assert f1_with_tolerance(true, [np.array([], dtype=int), np.array([], dtype=int)], 1) == 0.0
    with pytest.raises(ValueError, match="episodes"):
        f1_with_tolerance(true, predicted[:1], 0)


def test_task_alignment_matches_segments_in_order():
    segments = [np.array([0, 0, 0, 1, 1, 1])]
    assert task_alignment_accuracy(segments, [np.array([2, 5])]) == 1.0
    # Boundary one step late: step 3 is labelled with subtask 0 -> 5/6.
    assert task_alignment_accuracy(segments, [np.array([3, 5])]) == pytest.approx(5 / 6)
    # A third predicted segment has no true subtask to match: steps 4, 5 count as wrong.
    assert task_alignment_accuracy(segments, [np.array([1, 3, 5])]) == pytest.approx(3 / 6)
    # One segment for the whole episode: only subtask 0's steps are right.
    assert task_alignment_accuracy(segments + [np.array([0, 1])], [np.array([5]), np.array([0, 1])]) == (
        pytest.approx((3 + 2) / 8)
    )


def test_nmi_hand_cases():
    assert normalized_mutual_info([0, 0, 1, 1], [5, 5, 7, 7]) == pytest.approx(1.0)
    assert normalized_mutual_info([0, 1, 0, 1], [0, 0, 1, 1]) == pytest.approx(0.0)
    assert normalized_mutual_info([2, 2, 2], [1, 1, 1]) == 1.0
    # a = [0,0,1,1], b = [0,0,0,1]: H(a) = ln 2, H(b) = H(3/4, 1/4), MI = H(a) + H(b) - H(a, b).
    h_b = -(0.75 * math.log(0.75) + 0.25 * math.log(0.25))
    h_ab = -(0.5 * math.log(0.5) + 2 * 0.25 * math.log(0.25))
    expected = (math.log(2) + h_b - h_ab) / ((math.log(2) + h_b) / 2)
    assert normalized_mutual_info([0, 0, 1, 1], [0, 0, 0, 1]) == pytest.approx(expected)
    with pytest.raises(ValueError, match="shape"):
        normalized_mutual_info([0, 1], [0])


def test_parsing_scores_of_a_perfect_option_parse():
    segments = [np.array([0, 0, 1, 1, 1]), np.array([0, 1, 1])]
    subtasks = [np.array([0, 0, 2, 2, 2]), np.array([2, 3, 3])]
    options = [np.array([1, 1, 0, 0, 0]), np.array([0, 2, 2])]
    scores = parsing_scores(segments, subtasks, [boundaries_from_labels(o) for o in options], options)
    assert scores == pytest.approx({"f1_tol0": 1.0, "f1_tol1": 1.0, "align_acc": 1.0, "nmi": 1.0})
    shuffled = [np.array([1, 0, 1, 0, 1]), np.array([0, 2, 0])]
    worse = parsing_scores(segments, subtasks, [boundaries_from_labels(o) for o in shuffled], shuffled)
    assert worse["f1_tol0"] < 1.0 and worse["nmi"] < 0.5


def test_option_table_matches_options_to_subtasks():
    table = np.array([[0.1, 0.97, 0.0], [0.0, 0.05, 0.99], [0.96, 0.08, 0.02]])
    summary = option_table_summary(table)
    assert summary["option_of_subtask"] == {0: 2, 1: 0, 2: 1}
    assert summary["diagonal"] == [0.96, 0.97, 0.99]
    assert summary["off_diagonal_max"] == pytest.approx(0.1)
    # Two options for three subtasks: the third subtask has no option of its own.
    two = option_table_summary(table[[0, 2]])
    assert two["option_of_subtask"] == {0: 1, 1: 0} and two["diagonal_min"] == pytest.approx(0.96)
    # Six options: the three best-matched ones are read, the spare ones ignored.
    six = option_table_summary(np.vstack([table, np.full((3, 3), 0.5)]))
    assert six["diagonal_mean"] == pytest.approx((0.96 + 0.97 + 0.99) / 3)


def test_parse_statistics_shows_a_pair_of_options_sharing_two_subtasks():
    from lerobot_policy_ocn.ocn_data.episodes_table import EpisodeArrays
    from lerobot_policy_ocn.tools.eval.parsing import Segmentation, parse_statistics

    # Two episodes: subtask ids 0 then 3 (4 + 2 frames, then padding), and 0 then 2 (3 + 3 frames).
    subtask_id = np.array([[0, 0, 0, 0, 3, 3, -1], [0, 0, 0, 2, 2, 2, 2]])
    lengths = np.array([6, 7])
    # Option 2 does subtask 2 alone; options 0 and 1 share subtasks 0 (3 and 4 of its 7 frames) and 3.
    labels = [np.array([0, 0, 1, 1, 0, 1]), np.array([1, 0, 1, 2, 2, 2, 2])]
    episodes = EpisodeArrays(state=np.zeros((2, 7, 1)), action=np.zeros((2, 7, 1)), subtask_index=subtask_id,
                             subtask_id=subtask_id, mask=subtask_id >= 0, lengths=lengths, tasks=["AD", "AC"],
                             episode_index=np.arange(2))
    parses = [Segmentation(np.array([1, 3, 4, 5]), labels[0]), Segmentation(np.array([0, 1, 2, 6]), labels[1])]
    stats = parse_statistics(episodes, parses)
    assert stats["label_by_subtask"] == {"0": [0.4286, 0.5714, 0.0], "2": [0.0, 0.0, 1.0], "3": [0.5, 0.5, 0.0]}
    assert stats["label_share"] == [0.3077, 0.3846, 0.3077]
    # By thirds of each true segment (frame j of L in third 3j // L): subtask 0's segments are
    # labelled 0 0 | 1 | 1 (4 frames) and 1 | 0 | 1 (3 frames); subtask 3's two frames fill two thirds.
    assert stats["label_by_subtask_third"] == {
        "0": [[0.6667, 0.3333, 0.0], [0.5, 0.5, 0.0], [0.0, 1.0, 0.0]],
        "2": [[0.0, 0.0, 1.0]] * 3,
        "3": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], None],
    }
    # By the move into each segment: subtask 0 starts both episodes; 3 follows 0 in the first, 2 in the second.
    assert stats["label_by_transition"] == {"start>0": [0.4286, 0.5714, 0.0], "0>2": [0.0, 0.0, 1.0],
                                            "0>3": [0.5, 0.5, 0.0]}
    assert stats["segments_per_episode"] == 4.0 and stats["true_segments_per_episode"] == 2.0


def test_boundary_offsets_place_each_true_boundary_and_split_them_by_the_move_before_it():
    from lerobot_policy_ocn.ocn_data.episodes_table import EpisodeArrays
    from lerobot_policy_ocn.tools.eval.parsing import Segmentation, parse_statistics

    # Inner true boundaries (last step of a subtask that is not the episode's last): episode 0 at
    # step 2, episode 1 at steps 1 and 3, episode 2 at step 0.
    index = np.array([[0, 0, 0, 1, 1, 1], [0, 0, 1, 1, 2, 2], [0, 1, 1, -1, -1, -1]])
    action = np.array([[4, 0, 4, 1, 1, 4], [3, 4, 0, 4, 2, 4], [4, 2, 4, 0, 0, 0]])[..., None]
    episodes = EpisodeArrays(state=np.zeros((3, 6, 1)), action=action, subtask_index=index, subtask_id=index,
                             mask=index >= 0, lengths=np.array([6, 6, 3]), tasks=["AC"] * 3, episode_index=np.arange(3))
    # Episode 0 switches one step early (1 for 2); episode 1 on time at 1, and 3's nearest is that same
    # switch, two steps early; episode 2 never switches.
    parses = [Segmentation(np.array([1, 5]), None), Segmentation(np.array([1, 5]), None),
              Segmentation(np.array([2]), None)]
    stats = parse_statistics(episodes, parses)
    assert stats["boundary_offsets"] == {"boundaries": 4, "-2": 0.25, "-1": 0.25, "0": 0.25, "1": 0.0, "2": 0.0,
                                         "farther": 0.25}
    by_action = stats["boundary_offsets_by_previous_action"]
    assert set(by_action) == {"-1", "0", "3"}  # step 0 has no action before it
    assert by_action["0"]["boundaries"] == 2 and by_action["0"]["-1"] == by_action["0"]["-2"] == 0.5
    assert by_action["3"]["0"] == 1.0 and by_action["-1"]["farther"] == 1.0
    # Continuous actions (several dimensions) get no breakdown by action.
    continuous = EpisodeArrays(**{**episodes.__dict__, "action": np.zeros((3, 6, 9))})
    assert "boundary_offsets_by_previous_action" not in parse_statistics(continuous, parses)


def test_parse_statistics_tells_options_that_follow_the_moves_from_options_that_follow_the_subtasks():
    from lerobot_policy_ocn.ocn_data.episodes_table import EpisodeArrays
    from lerobot_policy_ocn.tools.eval.parsing import Segmentation, parse_statistics

    # Subtask 1 comes after 0 in the first episode and after 2 in the second (2 + 2 frames each).
    subtask_id = np.array([[0, 0, 1, 1], [2, 2, 1, 1]])
    episodes = EpisodeArrays(state=np.zeros((2, 4, 1)), action=np.zeros((2, 4, 1)),
                             subtask_index=np.array([[0, 0, 1, 1]] * 2), subtask_id=subtask_id, mask=subtask_id >= 0,
                             lengths=np.array([4, 4]), tasks=["AB", "CB"], episode_index=np.arange(2))
    # Option 0 takes subtask 0 and the move 2 > 1; option 1 takes subtask 2 and the move 0 > 1.
    parses = [Segmentation(np.array([1, 3]), np.array([0, 0, 1, 1])),
              Segmentation(np.array([1, 3]), np.array([1, 1, 0, 0]))]
    stats = parse_statistics(episodes, parses)
    assert stats["label_by_subtask"]["1"] == [0.5, 0.5]
    assert stats["label_by_transition"] == {"start>0": [1.0, 0.0], "start>2": [0.0, 1.0], "0>1": [0.0, 1.0],
                                            "2>1": [1.0, 0.0]}
