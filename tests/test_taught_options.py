"""Options taught through `lerobot-train`: a packed view that holds option labels, the policy's
`taught_options` loss on it, and `ocn-reproduce dial --split affine`, which teaches clones the labels
of a switching affine policy, continues them on the paper's loss and keeps the continuation only where
it clones the validation demonstrations no worse."""

import json

import numpy as np
import pytest
import torch

from conftest import DIAL_REPO_ID
from lerobot.utils.constants import ACTION, OBS_STATE
from ocn_data.episodes_table import load_episodes, split_episodes
from ocn_data.option_labels import read_labels, write_labels
from ocn_data.packed_view import PACKED_OPTION, packed_view, packed_view_path
from ocn_data.training_view import MARKER
from policies.ocn import OCNConfig
from policies.sequence import training_windows
from test_packed_view import built, loaded, processed_batch

DIAL = {"obs_encoder": "identity", "action_type": "continuous", "hidden_size": 16, "mlp_hidden_size": 16,
        "n_options": 4}


def stepped_labels(root, path, period=7):
    """A label file for the training split of the dataset at `root`: option (t // period) % 4 at frame t."""
    train = load_episodes(root, split_episodes(root, "train"))
    labels = np.where(train.mask, (np.arange(train.mask.shape[1]) // period) % 4, -1)
    write_labels(path, train, labels)
    return path


def test_a_labelled_packed_view_holds_each_training_frame_s_label_and_none_elsewhere(dial_dataset, tmp_path):
    labels = stepped_labels(dial_dataset, tmp_path / "labels.npz")
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    width = int(np.median(episodes.lengths))  # some episodes are cut
    view = packed_view(dial_dataset, DIAL_REPO_ID, width, cut_long=True, option_labels=labels)
    assert view == packed_view_path(dial_dataset, width, True, labels) != packed_view_path(dial_dataset, width, True)
    assert len(json.loads((view / MARKER).read_text())["option_labels_sha256"]) == 64
    train = set(split_episodes(dial_dataset, "train"))
    rows = loaded(view, None, repo_id=DIAL_REPO_ID)
    for e, (index, length) in enumerate(zip(episodes.episode_index.tolist(), episodes.lengths.tolist(), strict=True)):
        option = rows[e][PACKED_OPTION].numpy()
        kept = min(length, width)
        if index in train:
            np.testing.assert_array_equal(option[:kept], (np.arange(kept) // 7) % 4)
        else:
            assert (option[:kept] == -1).all()  # the validation split is not labelled
        assert (option[kept:] == -1).all()
    assert train and len(train) < len(episodes.lengths)
    # Other labels are another view.
    other = stepped_labels(dial_dataset, tmp_path / "other.npz", period=5)
    assert packed_view_path(dial_dataset, width, True, other) != view


def test_taught_training_is_the_labelled_loss_on_the_packed_rows(dial_dataset, tmp_path):
    """Through LeRobot's loader and preprocessor, the taught loss of a labelled view's rows is
    `labelled_forward` on the same episodes and labels; without labels it is refused by name."""
    labels = stepped_labels(dial_dataset, tmp_path / "labels.npz")
    train = list(split_episodes(dial_dataset, "train"))
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "train"))
    width = int(load_episodes(dial_dataset, split_episodes(dial_dataset, "all")).lengths.max())
    view = packed_view(dial_dataset, DIAL_REPO_ID, width, option_labels=labels)
    config = OCNConfig(device="cpu", window_size=width, window_start="packed", taught_options=True,
                       taught_termination_weight=5.0, **DIAL)
    policy = built(config, view, train, DIAL_REPO_ID)
    rows = processed_batch(loaded(view, train, policy.config, DIAL_REPO_ID), policy)
    loss, stats = policy(rows)
    mask, state, action = training_windows(policy.config, rows)
    option = torch.from_numpy(read_labels(labels, episodes.episode_index, episodes.lengths, mask.shape[1]))
    expected, expected_stats = policy.labelled_forward({OBS_STATE: state, ACTION: action, "task": rows["task"]},
                                                       option, termination_weight=5.0)
    torch.testing.assert_close(loss, expected)
    assert stats == expected_stats and stats["frames_used"] == int(episodes.lengths.sum())
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.core.parameters() if p.requires_grad)

    with pytest.raises(ValueError, match="observation.packed.option"):
        policy({key: value for key, value in rows.items() if key != PACKED_OPTION})
    unlabelled = dict(rows)
    unlabelled[PACKED_OPTION] = torch.full_like(rows[PACKED_OPTION], -1)
    with pytest.raises(ValueError, match="frames without an option label"):
        policy(unlabelled)
    policy.config.n_options = 3
    with pytest.raises(ValueError, match="labelled option 3, but the policy has n_options = 3"):
        policy(rows)


def test_taught_options_name_their_misuses():
    with pytest.raises(ValueError, match="window_start=packed"):
        OCNConfig(taught_options=True)
    with pytest.raises(ValueError, match="MoE"):
        OCNConfig(hierarchy="moe", taught_termination_weight=5.0)
    with pytest.raises(ValueError, match="not hierarchy='hil'"):
        OCNConfig(hierarchy="hil", taught_options=True, window_start="packed")
    with pytest.raises(ValueError, match="taught_termination_weight must be >= 0"):
        OCNConfig(taught_termination_weight=-1.0)


def test_dial_affine_clones_are_taught_then_continued_and_keep_the_better_of_the_two(dial_dataset, tmp_path):
    from tools.episode_parsing import validation_nll
    from tools.reproduce import build_parser, dial, taught

    args = build_parser().parse_args([
        "dial", "--split", "affine", "--steps", "2", "--batch-size", "4", "--num-workers", "0",
        "--continue-steps", "2", "--restarts", "1", "--workdir", str(tmp_path), "--results", str(tmp_path / "results")])
    args.argv = None
    dial.use_taught_recipe(args)
    assert (args.usage_balance, args.window_start) == (0.0, "packed")
    ocn, moe = dial.METHODS
    trained, choice = dial.clone(args, dial_dataset, ocn, 1)
    labels = taught.labels_folder(args, dial_dataset) / taught.LABELS_FILE
    made = labels.stat().st_mtime_ns
    guard = choice["continuation"]
    assert choice["restarts"] is None and guard["continued_command"].startswith(guard["taught_command"] + " && ")
    assert trained.command == guard[f"{guard['kept']}_command"]
    words = guard["taught_command"].split()
    for flag in ("--policy.taught_options=true", "--policy.taught_termination_weight=5.0", "--policy.n_options=4",
                 "--policy.window_start=packed", "--policy.obs_encoder=dial_keys", "--policy.lr_schedule=constant",
                 f"--dataset.root={packed_view_path(dial_dataset, 120, True, labels)}"):
        assert flag in words, flag
    assert not any(word.startswith("--policy.usage_balance") for word in words)
    continued = guard["continued_command"].split(" && ")[1].split()
    assert "--policy.taught_options=false" in continued and f"--policy.optimizer_lr={taught.CONTINUE_LR}" in continued
    assert any(word.startswith("--policy.path=") for word in continued)
    folder = dial.clone_dir(args, ocn, 1)
    assert folder.parent.name == "ocn_taught_affine_packed"
    taught_model = folder / "train" / "checkpoints" / "last" / "pretrained_model"
    continued_model = folder / "continued" / "train" / "checkpoints" / "last" / "pretrained_model"
    assert OCNConfig.from_pretrained(taught_model).taught_options
    config = OCNConfig.from_pretrained(continued_model)
    assert not config.taught_options and config.taught_termination_weight == 5.0
    assert config.optimizer_lr == taught.CONTINUE_LR
    # The guard kept the model with the lower validation NLL (the continued one on a tie), scored afresh.
    nlls = {"taught": validation_nll(taught_model, dial_dataset, 600),
            "continued": validation_nll(continued_model, dial_dataset, 600)}
    assert guard["taught_val_nll"] == pytest.approx(nlls["taught"], rel=1e-6)
    assert guard["continued_val_nll"] == pytest.approx(nlls["continued"], rel=1e-6)
    assert guard["kept"] == ("continued" if nlls["continued"] <= nlls["taught"] else "taught")
    assert trained.checkpoint == {"taught": taught_model, "continued": continued_model}[guard["kept"]]
    assert json.loads((folder / "continuation.json").read_text()) == guard
    # Asked again, nothing is fitted or trained again.
    again, again_choice = dial.clone(args, dial_dataset, ocn, 1)
    assert not again.trained_now and again.checkpoint == trained.checkpoint and again_choice == choice
    assert labels.stat().st_mtime_ns == made
    made_by = json.loads((labels.parent / "made_by.json").read_text())
    assert made_by["fit"] == ["--n-options", "4", "--seed", "0"] and (labels.parent / taught.REPORT_FILE).exists()
    # With the two models the other way round, the guard keeps the other one.
    runs = {"taught": taught_model, "continued": continued_model}
    if nlls["taught"] != nlls["continued"]:
        from tools.reproduce.runs import TrainedRun

        swapped = taught.continuation_guard(tmp_path / "swapped.json", TrainedRun(runs["continued"], "b", None),
                                            TrainedRun(runs["taught"], "a", None), dial_dataset)
        assert swapped["kept"] != guard["kept"]
    # MoE is taught the same labels, with no terminations to weigh.
    _, moe_choice = dial.clone(args, dial_dataset, moe, 1)
    moe_words = moe_choice["continuation"]["taught_command"].split()
    assert "--policy.hierarchy=moe" in moe_words and "--policy.taught_options=true" in moe_words
    assert not any(word.startswith("--policy.taught_termination_weight") for word in moe_words)
    # The results files are dial_affine.*, which say how the clones were made.
    dial.write_results(args, dial_dataset, [], [], 0, 1.0)
    text = (tmp_path / "results" / "dial_affine.md").read_text()
    assert "taught the labels of a switching affine policy" in text and "fit seed 0" in text
    assert "`dial_affine.png`" in text and "The switching affine fit (seed 0) ended at cost" in text
    report = json.loads((tmp_path / "results" / "dial_affine.json").read_text())["option_labels"]
    assert report["cost"] <= min(report["start_costs"]) and 0 <= report["val_scores"]["nmi"] <= 1


def test_the_affine_split_refuses_the_induction_recipe_s_balance(tmp_path):
    from tools.reproduce import build_parser, dial

    args = build_parser().parse_args(["dial", "--split", "affine", "--usage-balance", "0.5", "--workdir",
                                      str(tmp_path)])
    with pytest.raises(SystemExit, match="--usage-balance 0.5 is the induction recipe's"):
        dial.use_taught_recipe(args)
