"""The in-memory training loop for trying recipes: it trains the real policy on a recorded dataset,
scores the parse with the shared metrics and draws curves."""

import json

import numpy as np
import pytest
import torch

from conftest import CRAFT_REPO_ID, DIAL_REPO_ID
from lerobot.utils.constants import ACTION, OBS_STATE
from ocn_data.episodes_table import load_episodes, split_episodes
from tools.episode_parsing import load_policy, score_segmentations, segment_episodes
from tools.fast_imitation import (
    episode_batch,
    episode_draws,
    main,
    frame_options,
    option_labels,
    parse_overrides,
    peak_table,
    restart_gain,
    restart_rows,
    restart_table,
    split_table,
)


def test_fast_imitation_trains_scores_and_plots(craft_dataset, tmp_path):
    out = tmp_path / "balanced.json"
    argv = ["train", "--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--out", str(out), "--steps", "4",
            "--batch-size", "8", "--eval-every", "2", "--window-size", "30", "--set", "usage_balance=1.0",
            "hidden_size=16", "mlp_hidden_size=16", "--save", str(tmp_path / "model")]
    assert main(argv) == 0
    result = json.loads(out.read_text())
    assert result["settings"]["usage_balance"] == 1.0 and result["settings"]["n_options"] == 3
    assert result["settings"]["temperature"] == 10.0 and result["settings"]["hidden_size"] == 16
    assert [point["step"] for point in result["curve"]] == [2, 4]
    for point in result["curve"]:
        assert point["nll"] > 0 and 0 <= point["usage_imbalance"] <= 1.0987
        assert point["lr"] == result["settings"]["optimizer_lr"]
        assert all(0 <= point[key] <= 1 for key in ("f1_tol0", "f1_tol1", "align_acc", "nmi"))
        assert sum(point["option_share"]) == pytest.approx(1.0, abs=1e-3)
        for thirds in point["option_by_subtask_third"].values():
            assert all(third is None or sum(third) == pytest.approx(1.0, abs=1e-3) for third in thirds)
        # Each move into a subtask ("start>ID" first), with its frames' option shares.
        moves = point["option_by_transition"]
        assert {move.split(">")[1] for move in moves} == set(point["option_by_subtask"])
        assert any(move.startswith("start>") for move in moves)
        assert all(sum(shares) == pytest.approx(1.0, abs=1e-3) for shares in moves.values())
        # Where the parse puts the true boundaries, overall and by the move before each (Craft's actions).
        offsets, by_move = point["boundary_offsets"], point["boundary_offsets_by_previous_action"]
        assert offsets["boundaries"] == sum(entry["boundaries"] for entry in by_move.values()) > 0
    policy, preprocessor, _ = load_policy(tmp_path / "model")
    assert policy.config.usage_balance == 1.0 and policy.config.hidden_size == 16
    val = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    reloaded = score_segmentations(val, segment_episodes(policy, preprocessor, val))
    assert reloaded == {key: result["curve"][-1][key] for key in reloaded}
    # --init continues that model: its config (hidden size 16, not the default), then --set on top. The
    # config of a checkpoint from a resumed lerobot-train run names where it resumed from.
    saved_config = tmp_path / "model" / "config.json"
    saved_config.write_text(json.dumps({**json.loads(saved_config.read_text()), "pretrained_path": str(tmp_path)}))
    more = tmp_path / "continued.json"
    assert main(["train", "--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--out", str(more), "--steps", "2",
                 "--batch-size", "8", "--eval-every", "2", "--init", str(tmp_path / "model"),
                 "--set", "termination_cost=0.1", "termination_penalty=log", "lr_schedule=cosine"]) == 0
    continued = json.loads(more.read_text())
    assert continued["curve"][-1]["lr"] == 0.0  # the cosine schedule has annealed to zero by the last step
    assert continued["settings"]["hidden_size"] == 16 and continued["settings"]["usage_balance"] == 1.0
    assert continued["settings"]["pretrained_path"] == str(tmp_path)
    assert continued["settings"]["termination_penalty"] == "log" and continued["settings"]["termination_cost"] == 0.1
    png = tmp_path / "curves.png"
    assert main(["plot", str(out), "--png", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_supervised_options_train_on_the_labelled_split_and_are_scored_as_usual(craft_dataset, tmp_path, monkeypatch):
    """--supervise-options trains the split given by the subtask labels (OCNPolicy.labelled_forward),
    each subtask id its own option, and scores the model like any other run."""
    from policies.ocn import OCNPolicy

    split = load_episodes(craft_dataset, split_episodes(craft_dataset, "train"))
    ids = np.unique(split.subtask_id[split.mask])
    rows = np.array([0, 3])
    labels = option_labels(frame_options(split, ids), rows, split.lengths, width=12)
    assert labels.shape == (2, min(12, int(split.lengths[rows].max())))
    for row, episode in enumerate(rows):
        n = min(12, int(split.lengths[episode]))
        expected = [int(np.flatnonzero(ids == i)[0]) for i in split.subtask_id[episode, :n]]
        assert labels[row, :n].tolist() == expected and (labels[row, n:] == -1).all()

    seen = []
    labelled = OCNPolicy.labelled_forward

    def recording(self, batch, option, termination_weight):
        seen.append((batch[OBS_STATE].shape[:2], option.clone(), termination_weight))
        return labelled(self, batch, option, termination_weight)

    monkeypatch.setattr(OCNPolicy, "labelled_forward", recording)
    out = tmp_path / "supervised.json"
    argv = ["train", "--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--out", str(out), "--steps", "2",
            "--batch-size", "4", "--eval-every", "2", "--window-size", "30", "--supervise-options",
            "--termination-weight", "5", "--set", "hidden_size=16", "mlp_hidden_size=16"]
    assert main(argv) == 0
    assert len(seen) == 2
    for shape, option, weight in seen:
        assert option.shape == shape and set(option.unique().tolist()) <= {-1, *range(len(ids))} and weight == 5.0
    result = json.loads(out.read_text())
    assert result["settings"]["supervise_options"] is True and result["settings"]["termination_weight"] == 5.0
    point = result["curve"][-1]
    assert point["choice_ce"] > 0 and point["termination_bce"] > 0 and point["val_nll"] > 0
    assert 0 < point["mean_end_at_switch"] < 1 and 0 < point["mean_end_elsewhere"] < 1
    assert "usage_imbalance" not in point and 0 <= point["nmi"] <= 1
    with pytest.raises(SystemExit, match="its own option; n_options is 1"):
        main([*argv[:-3], "--set", "n_options=1"])
    with pytest.raises(SystemExit, match="needs --supervise-options"):
        main([arg for arg in argv if arg != "--supervise-options"])


def test_fast_imitation_overrides_are_typed_config_fields():
    assert parse_overrides(["usage_balance=0.5", "n_options=6", "option_memory=false", "lr_schedule=cosine"]) == {
        "usage_balance": 0.5, "n_options": 6, "option_memory": False, "lr_schedule": "cosine"}
    with pytest.raises(SystemExit, match="OCNConfig field"):
        parse_overrides(["no_such_field=1"])
    with pytest.raises(SystemExit, match="takes true or false"):
        parse_overrides(["option_memory=maybe"])


def test_split_table_names_the_first_step_at_the_nmi_threshold_and_the_episodes_drawn_by_then(tmp_path):
    def curve(name, nmis, batch_size=128):
        path = tmp_path / f"{name}.json"
        points = [{"step": 500 * (k + 1), "nmi": nmi, "f1_tol1": 0.5, "align_acc": 0.25} for k, nmi in enumerate(nmis)]
        path.write_text(json.dumps({"settings": {"batch_size": batch_size}, "curve": points}))
        return path

    curves = [curve("late", [0.1, 0.89, 0.9, 0.95]), curve("never", [0.1, 0.2]), curve("small", [0.95], batch_size=32)]
    rows = split_table(curves, 0.9).splitlines()
    assert rows[0].startswith("| run | batch | first step with NMI >= 0.9 | episodes drawn by then | last step |")
    assert rows[2] == "| late | 128 | 1500 | 192,000 | 2000 | 0.950 | 0.500 | 0.250 |"
    assert rows[3] == "| never | 128 | not within the run | - | 1000 | 0.200 | 0.500 | 0.250 |"
    assert rows[4] == "| small | 32 | 500 | 16,000 | 500 | 0.950 | 0.500 | 0.250 |"
    assert main(["plot", *map(str, curves), "--png", str(tmp_path / "episodes.png"), "--x", "episodes"]) == 0
    assert (tmp_path / "episodes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_in_memory_batches_train_what_lerobot_train_windows_train(craft_dataset):
    # The same episodes, once as LeRobot's loader windows them for `lerobot-train` (one window per
    # sampled frame, clamped at the episode's ends) and once as this loop takes them from memory:
    # the same loss, so the recipe found here is the one `lerobot-train` trains.
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.utils.collate import lerobot_collate_fn

    from policies.ocn import OCNConfig

    meta = LeRobotDatasetMetadata(CRAFT_REPO_ID, root=craft_dataset)
    config = OCNConfig(device="cpu", window_size=30, hidden_size=16, mlp_hidden_size=16, usage_balance=1.0)
    torch.manual_seed(0)
    policy = make_policy(config, ds_meta=meta).eval()
    preprocessor, _ = make_pre_post_processors(config, dataset_stats=meta.stats)
    train = list(split_episodes(craft_dataset, "train"))
    windows = LeRobotDataset(CRAFT_REPO_ID, root=craft_dataset, episodes=train,
                             delta_timestamps=resolve_delta_timestamps(config, meta))
    frames = [0, 5, len(windows) // 2, len(windows) - 1]  # the first and last frames of episodes among them
    items = [windows[k] for k in frames]
    # As lerobot-train collates (this dataset has subtask annotations, LeRobot's language columns).
    collate = lerobot_collate_fn if meta.has_language_columns else torch.utils.data.default_collate
    loaded = preprocessor(collate(items))
    split = load_episodes(craft_dataset, split_episodes(craft_dataset, "train"))
    rows = np.array([train.index(int(item["episode_index"])) for item in items])
    with torch.no_grad():
        from_loader, loader_stats = policy.forward(loaded)
        from_memory, memory_stats = policy.forward(episode_batch(split, rows))
    assert loader_stats["frames_used"] == memory_stats["frames_used"] == int(split.lengths[rows].sum())
    assert from_loader.item() == pytest.approx(from_memory.item(), rel=1e-6)


def test_epoch_draws_take_every_frame_once_per_pass_and_replacement_draws_follow_lengths():
    lengths = np.array([1, 2, 3, 6])  # 12 frames: 3 batches of 4 per pass
    rng = np.random.default_rng(0)
    epoch = episode_draws(lengths, 4, "epoch", rng)
    for _ in range(2):
        one_pass = np.concatenate([next(epoch) for _ in range(3)])
        assert np.bincount(one_pass, minlength=4).tolist() == lengths.tolist()
    replacement = episode_draws(lengths, 4, "replacement", rng)
    drawn = np.concatenate([next(replacement) for _ in range(3000)])
    assert np.bincount(drawn, minlength=4) / drawn.size == pytest.approx(lengths / lengths.sum(), abs=0.01)


def test_fast_imitation_trains_dial_on_standardised_episodes_and_scores_free_runs(dial_dataset, tmp_path, monkeypatch):
    """On Dial the loop takes the world's settings from the dataset, standardises every training batch
    with the dataset's statistics (as lerobot-train's preprocessor does), cuts long episodes at
    --window-size, and reports free-run success per PIN."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from policies.ocn import OCNPolicy
    from tools.worlds import dial

    seen = []
    forward = OCNPolicy.forward

    def recording_forward(self, batch, *args, **kwargs):
        seen.append({key: batch[key].clone() for key in (OBS_STATE, ACTION, f"{ACTION}_is_pad")})
        return forward(self, batch, *args, **kwargs)

    monkeypatch.setattr(OCNPolicy, "forward", recording_forward)
    out, width = tmp_path / "dial.json", 30
    argv = ["train", "--root", str(dial_dataset), "--repo-id", DIAL_REPO_ID, "--out", str(out), "--steps", "2",
            "--batch-size", "4", "--eval-every", "2", "--window-size", str(width), "--rollouts", "1",
            "--set", "hidden_size=16", "mlp_hidden_size=16", "--save", str(tmp_path / "model")]
    assert main(argv) == 0
    result = json.loads(out.read_text())
    settings = result["settings"]
    assert result["world"] == "dial" and settings["n_options"] == 4 and settings["temperature"] == 10.0
    assert settings["obs_encoder"] == "identity" and settings["action_type"] == "continuous"
    point = result["curve"][-1]
    val_tasks = load_episodes(dial_dataset, split_episodes(dial_dataset, "val")).tasks
    assert set(point["success_rate"]) == {dial().task_key(task) for task in val_tasks}
    assert 0 <= point["mean_success_rate"] <= 1
    assert all(0 <= point[key] <= 1 for key in ("f1_tol0", "f1_tol1", "nmi"))

    stats = LeRobotDatasetMetadata(DIAL_REPO_ID, root=dial_dataset).stats
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "train"))
    assert episodes.lengths.max() > width  # the fixture's episodes are longer than the cut
    assert len(seen) == 2
    for batch in seen:
        assert batch[OBS_STATE].shape[1] == width
        # Each row, unstandardised with the dataset's statistics, is the first frames of a recorded episode.
        raw = batch[OBS_STATE].numpy() * stats[OBS_STATE]["std"] + stats[OBS_STATE]["mean"]
        raw_action = batch[ACTION].numpy() * stats[ACTION]["std"] + stats[ACTION]["mean"]
        for state, action in zip(raw, raw_action, strict=True):
            match = [e for e in range(len(episodes.lengths))
                     if np.allclose(state, episodes.state[e, :width], atol=1e-4)]
            assert len(match) == 1
            np.testing.assert_allclose(action, episodes.action[match[0], :width], atol=1e-4)


def test_plot_draws_the_chosen_metrics_and_names_a_missing_one(tmp_path, capsys):
    path = tmp_path / "run.json"
    points = [{"step": 250 * (k + 1), "nmi": 1.0, "f1_tol1": 1.0, "align_acc": 1.0, "nll": 2.0 - k,
               "mean_success_rate": 0.5 * k} for k in range(3)]
    path.write_text(json.dumps({"settings": {"batch_size": 32}, "curve": points}))
    png = tmp_path / "success.png"
    assert main(["plot", str(path), "--png", str(png), "--metrics", "mean_success_rate,nll",
                 "--peak", "mean_success_rate"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert capsys.readouterr().out.rstrip().endswith("| run | 750 | 1.000 | 0.000 |")
    assert split_table([path], 0.9, ("mean_success_rate", "nll")).splitlines()[2].endswith("| 750 | 1.000 | 0.000 |")
    assert peak_table([path], "nll", ("nll", "mean_success_rate")).splitlines()[2] == "| run | 250 | 2.000 | 0.000 |"
    assert peak_table([path], "mean_success_rate").splitlines()[2] == "| run | 750 | 1.000 | 1.000 | 1.000 |"
    without = tmp_path / "no_rollouts.json"
    without.write_text(json.dumps({"settings": {"batch_size": 32}, "curve": [{k: v for k, v in points[0].items()
                                                                            if k != "mean_success_rate"}]}))
    with pytest.raises(SystemExit, match="no mean_success_rate"):
        main(["plot", str(without), "--png", str(tmp_path / "x.png"), "--metrics", "mean_success_rate"])
    with pytest.raises(SystemExit, match="no mean_success_rate"):
        main(["plot", str(without), "--png", str(tmp_path / "x.png"), "--peak", "mean_success_rate"])


def test_restart_table_orders_runs_by_validation_nll_at_the_choice(tmp_path, capsys):
    paths = []
    for name, nlls, nmi in (("likely", (9.0, 8.5), 0.6), ("unlikely", (8.9, 8.7), 0.2), ("middle", (9.1, 8.6), 0.7)):
        path = tmp_path / f"{name}.json"
        curve = [{"step": 1000 * (k + 1), "val_nll": nll, "nmi": nmi, "f1_tol1": 0.9, "align_acc": 0.8}
                 for k, nll in enumerate(nlls)]
        path.write_text(json.dumps({"settings": {"batch_size": 32}, "curve": curve}))
        paths.append(path)
    # Ordered by the NLL at the chosen step, not at the first one, with the scores of each run's last point
    # or of the step asked for.
    assert restart_table(restart_rows(paths[::-1], 2000, None), 2000, ("nmi",)).splitlines()[2:] == [
        "| likely | 8.500 | 2000 | 0.600 |", "| middle | 8.600 | 2000 | 0.700 |", "| unlikely | 8.700 | 2000 | 0.200 |"]
    assert restart_table(restart_rows(paths, 1000, None), 1000, ("nmi",)).splitlines()[2].startswith(
        "| unlikely | 8.900 |")
    assert restart_table(restart_rows(paths, 2000, 1000), 2000, ("nmi",)).splitlines()[2] == \
        "| likely | 8.500 | 1000 | 0.600 |"
    # Pairs {likely, unlikely}, {likely, middle}, {middle, unlikely}: the likeliest of each scores 0.6, 0.6, 0.7.
    rows = restart_rows(paths, 2000, None)
    gain = restart_gain(rows, "nmi", 2)
    assert gain == pytest.approx({"sets": 3, "one": 0.5, "likeliest": 1.9 / 3, "best": 2.0 / 3})
    assert restart_gain(rows, "val_nll", 2)["best"] == pytest.approx((8.5 + 8.5 + 8.6) / 3)  # the least
    assert main(["plot", *map(str, paths), "--png", str(tmp_path / "r.png"), "--select-step", "2000",
                 "--restarts", "2", "--metrics", "nmi"]) == 0
    assert capsys.readouterr().out.rstrip().endswith(
        "nmi over all 3 sets of 2: one restart 0.500, the likeliest at step 2000 0.633, the best 0.667")
    with pytest.raises(SystemExit, match="likely.json has no evaluation at step 1500"):
        restart_rows(paths, 1500, None)
    with pytest.raises(SystemExit, match="--restarts 4: choose among 1..3 curve files"):
        restart_gain(rows, "nmi", 4)
