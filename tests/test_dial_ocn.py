"""Continuous-action OCN on Dial: the Gaussian-mixture NLL on recorded Dial windows, unnormalised
torques out of the postprocessor, `lerobot-train --policy.type=ocn` and `lerobot-eval
--env.type=dial` as real subprocesses, the Dial rollouts of `tools.rl.dial_rollouts`, and `ocn-eval` and
`ocn-view` on a Dial dataset (ground-truth boundaries at the key presses, the JSON, the MCAP log of
the free runs, the .rrd read back), and `ocn-annotate`'s copy of it read back by LeRobot.

One tiny recorded dataset (PINs 12 and 21, conftest's `dial_dataset`) and one tiny training run are
shared by the module.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.configs import NormalizationMode
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch.distributions import Categorical, Independent, MixtureSameFamily, Normal

from lerobot_policy_ocn.envs.dial import PRESS_L1, DialBatch, dial_poses, key_positions, parse_pin
from lerobot_policy_ocn.envs.dial.scene import N_JOINTS
from lerobot_policy_ocn.ocn_data.dial_recorder import dial_state_names
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.ocn_data.mcap_log import read_mcap_messages
from lerobot_policy_ocn.ocn import OCNConfig, OCNPolicy
from lerobot_policy_ocn.ocn.encoders import DialKeyEncoder
from lerobot_policy_ocn.ocn.processor_ocn import make_ocn_pre_post_processors
from lerobot_policy_ocn.tools.rl.dial_rollouts import DIAL_WORLD
from lerobot_policy_ocn.tools.rl.rollouts import free_run_success, option_subtask_success
from rrd_reading import forward_fill, read_rrd, values
from lerobot_policy_ocn.tools.cli import ocn_annotate, ocn_eval, ocn_view
from lerobot_policy_ocn.tools.eval.parsing import load_ocn, parse_episodes
from lerobot_policy_ocn.tools.eval.metrics import boundaries_from_labels
from lerobot_policy_ocn.tools.viz.scenes import DialScene
from conftest import DIAL_REPO_ID, run_cli

REPO_ID = DIAL_REPO_ID
STEPS = 5
SMALL = {"hidden_size": 16, "mlp_hidden_size": 16}


@pytest.fixture(scope="module")
def trained(dial_dataset) -> Path:
    """The `pretrained_model` folder of a few steps of plain `lerobot-train --policy.type=ocn` on
    `dial_dataset`: the policy takes Dial's recipe from the continuous actions, by itself."""
    base = dial_dataset.parent
    proc = run_cli(
        "lerobot-train", "--policy.type=ocn", f"--dataset.repo_id={REPO_ID}", f"--dataset.root={dial_dataset}",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false", "--env_eval_freq=0",
        f"--steps={STEPS}", "--batch_size=4", "--num_workers=0", "--log_freq=1",
        *[f"--policy.{key}={value}" for key, value in SMALL.items()], f"--output_dir={base / 'train'}",
        cwd=base,
    )
    (base / "train.log").write_text(proc.stdout + proc.stderr)
    return base / "train" / "checkpoints" / f"{STEPS:06d}" / "pretrained_model"


def _policy(root: Path, **overrides) -> tuple[OCNPolicy, LeRobotDatasetMetadata]:
    """A small Dial OCN built from the dataset's metadata, as `lerobot-train` builds it (the paper's
    loss unless `overrides` say otherwise, so that no affine fit runs)."""
    torch.manual_seed(0)
    meta = LeRobotDatasetMetadata(REPO_ID, root=root)
    config = OCNConfig(device="cpu", **{"recipe": "paper", "n_options": 3, **SMALL, **overrides})
    return make_policy(config, ds_meta=meta), meta


def one_frame_per_episode(root: Path) -> dict:
    """A LeRobot batch of one sampled frame of every episode (the policy reads their whole episodes)."""
    meta = LeRobotDatasetMetadata(REPO_ID, root=root)
    frames = LeRobotDataset(REPO_ID, root=root)
    firsts = [int(index) + 1 for index in meta.episodes["dataset_from_index"]]
    return torch.utils.data.default_collate([frames[index] for index in firsts])


def test_gaussian_mixture_nll_on_whole_dial_episodes(dial_dataset):
    policy, meta = _policy(dial_dataset, obs_encoder="identity")
    policy.eval()  # every episode, both splits
    mask, state, action, tasks, _ = policy.training_windows(one_frame_per_episode(dial_dataset))
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    stats = meta.stats[ACTION]
    mean, std = torch.as_tensor(stats["mean"]), torch.as_tensor(stats["std"])
    expected_action = (torch.from_numpy(episodes.action) - mean) / std
    torch.testing.assert_close(action[mask], expected_action[torch.from_numpy(episodes.mask)].float(),
                               rtol=1e-5, atol=1e-5)
    policy.train()
    loss, info = policy.forward(one_frame_per_episode(dial_dataset))
    train_lengths = episodes.lengths[list(split_episodes(dial_dataset, "train"))]
    assert info["frames_used"] == int(train_lengths.sum())  # the train split's whole episodes

    # The same NLL from torch.distributions, over the core's per-step mixture of 2N Gaussians.
    mask, state, action, tasks, _ = policy.training_windows(one_frame_per_episode(dial_dataset))
    out = policy._unroll(state, tasks)
    mean, log_std = out.params.chunk(2, dim=-1)
    log_std = log_std.clamp(policy.config.log_std_min, policy.config.log_std_max)
    components = Independent(Normal(mean.permute(2, 0, 1, 3), log_std.exp().permute(2, 0, 1, 3)), 1)
    mixture = MixtureSameFamily(Categorical(probs=out.weights.transpose(0, 1)), components)
    nll = -mixture.log_prob(action) * mask
    reference = (nll.sum(1) / mask.sum(1)).mean()
    torch.testing.assert_close(loss, reference, rtol=1e-4, atol=1e-4)
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in policy.parameters())


def test_plain_defaults_on_dial_data_take_the_dial_recipe(dial_dataset):
    meta = LeRobotDatasetMetadata(REPO_ID, root=dial_dataset)
    config = OCNConfig(device="cpu", **SMALL)
    config.input_features, config.output_features = {}, {}
    config.resolve_from_dataset(meta)
    assert (config.recipe, config.obs_encoder, config.action_type, config.n_options) == (
        "dial", "dial_keys", "continuous", 4)
    identity = NormalizationMode.IDENTITY
    assert config.normalization_mapping == {"STATE": identity, "ENV": identity, "VISUAL": identity,
                                            "ACTION": NormalizationMode.MEAN_STD}
    paper = OCNConfig(device="cpu", recipe="paper")
    paper.resolve_from_dataset(meta)
    assert (paper.recipe, paper.obs_encoder, paper.n_options) == ("paper", "identity", 3)


def test_select_action_returns_unnormalised_torques(dial_dataset):
    policy, meta = _policy(dial_dataset, inference_mode="greedy")
    preprocessor, postprocessor = make_ocn_pre_post_processors(policy.config, meta.stats)
    obs = DialBatch(2).reset(seeds=[0, 1], tasks=["12", "21"])
    batch = preprocessor({OBS_STATE: torch.from_numpy(obs), "task": ["press 1, press 2", "press 2, press 1"]})
    action = postprocessor(policy.select_action(batch))
    report = policy.last_step
    assert action.shape == (2, 9) and report.p_c.shape == (2, 3)
    # Greedy: the mean of the heaviest component (at t = 1 the restarted options, the last N).
    _, params = policy.core.step(policy.core.initial_state(policy.task_index(batch["task"], 2)),
                                 policy.core.project(batch[OBS_STATE]), torch.ones(2, dtype=torch.bool))[1][:2]
    chosen = params[3 + report.option, torch.arange(2), :9]
    stats = meta.stats[ACTION]
    torch.testing.assert_close(action,
                               chosen * torch.as_tensor(stats["std"]).float() + torch.as_tensor(stats["mean"]).float())


def test_lerobot_train_checkpoint_reloads_and_runs_in_lerobot_eval(trained):
    policy = OCNPolicy.from_pretrained(trained)
    assert sorted(policy.config.tasks) == ["press 1, press 2", "press 2, press 1"]
    assert (policy.config.recipe, policy.config.obs_encoder, policy.config.action_type,
            policy.config.n_options) == ("dial", "dial_keys", "continuous", 4)
    assert policy.config.normalization_mapping == {"STATE": "IDENTITY", "ENV": "IDENTITY", "VISUAL": "IDENTITY",
                                                   "ACTION": "MEAN_STD"}
    # lerobot-train built the phase clock from the preset and saved it where a resumed run reads it; the
    # taught phase ran first, then the final fifth (1 of 5 steps) trained the paper's loss at a 0.03x lr.
    assert json.loads((trained / "train_config.json").read_text())["scheduler"]["type"] == "ocn_phases"
    scheduler = json.loads((trained.parent / "training_state" / "scheduler_state.json").read_text())
    assert scheduler["last_epoch"] == STEPS and scheduler["_last_lr"] == pytest.approx([3e-5])
    log = (trained.parents[3] / "train.log").read_text()
    steps = re.findall(r"step:\d+ .*", log)
    assert len(steps) == STEPS and "final_phase:1.000" in steps[-1] and "final_phase" not in "".join(steps[:-1])
    assert all(float(re.search(r"choice_ce:([0-9.]+)", line).group(1)) > 0 for line in steps[:-1])
    out = trained.parents[3] / "eval"
    # --eval.recording writes the rollout as a dataset instead of rendering videos, so no OpenGL is needed.
    run_cli(
        "lerobot-eval", f"--policy.path={trained}", "--env.type=dial", "--env.task=12", "--eval.n_episodes=1",
        "--eval.batch_size=1", "--env.max_steps=50", "--eval.recording=true", "--policy.device=cpu",
        f"--output_dir={out}",
        cwd=trained.parents[3],
    )
    info = json.loads((out / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1 and info["overall"]["pc_success"] in (0.0, 100.0)
    assert 0.0 <= info["overall"]["avg_sum_reward"] <= 2.0


def test_dial_rollouts_of_the_trained_policy(trained):
    policy, preprocessor, postprocessor = load_ocn(trained)
    rates = free_run_success(
        policy, preprocessor, postprocessor, DIAL_WORLD, ["12", "press 2, press 1"], episodes=1, seed=5
    )
    assert list(rates) == ["12", "press 2, press 1"] and all(0.0 <= r <= 1.0 for r in rates.values())
    table = option_subtask_success(
        policy, preprocessor, postprocessor, DIAL_WORLD, ["1", "press 2"], episodes=1, seed=5
    )
    assert table.success.shape == (4, 2) and np.isin(table.success, [0.0, 1.0]).all()
    with torch.no_grad():  # options that terminate at once get one step: too short to reach a key
        policy.core.options.b_out[..., -1] = 50.0
        policy.core.options.w_out[..., -1] = 0.0
    table = option_subtask_success(policy, preprocessor, postprocessor, DIAL_WORLD, ["1", "2"], episodes=2, seed=5)
    assert np.array_equal(table.success, np.zeros((4, 2))) and np.array_equal(table.stopped, np.ones((4, 2)))
    with pytest.raises(ValueError, match="Unknown task"):
        free_run_success(policy, preprocessor, postprocessor, DIAL_WORLD, ["48"], episodes=1)


def _key_presses(state: np.ndarray, pin: tuple[int, ...]) -> np.ndarray:
    """The steps whose action pressed each digit of the PIN, judged from the recorded states alone:
    the step before the first later state with the fingertip within PRESS_L1 (L1) of that digit's
    key. The last press ends the episode, so no state follows it: it is the last step."""
    distance = np.abs(state[:, N_JOINTS:].reshape(len(state), -1, 3)).sum(axis=2)
    presses, start = [], 1
    for digit in pin[:-1]:
        at_key = start + int(np.flatnonzero(distance[start:, digit] < PRESS_L1)[0])
        presses.append(at_key - 1)
        start = at_key + 1
    return np.array([*presses, len(state) - 1])


def test_ground_truth_boundaries_are_the_key_presses(dial_dataset):
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    for i, n in enumerate(episodes.lengths):
        pin = parse_pin(episodes.tasks[i])
        truth = boundaries_from_labels(episodes.subtask_index[i, :n])  # what the parsing metrics score against
        np.testing.assert_array_equal(truth, _key_presses(episodes.state[i, :n], pin))
        assert tuple(episodes.subtask_id[i, truth]) == pin  # each segment is its digit's


def test_dial_keys_encoder_sees_each_press_as_its_log_distance_crossing_zero(dial_dataset):
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    encoder = DialKeyEncoder()
    for i, n in enumerate(episodes.lengths):
        pin = parse_pin(episodes.tasks[i])
        features = encoder(torch.as_tensor(episodes.state[i, :n]))
        assert features.shape == (n, 49) and torch.isfinite(features).all()
        log_distance = features[:, -10:]
        for press, digit in zip(boundaries_from_labels(episodes.subtask_index[i, :n])[:-1], pin, strict=False):
            # The press step's own frame is still outside PRESS_L1; the next frame is the first inside.
            assert log_distance[press, digit] >= 0 > log_distance[press + 1, digit]
    home = torch.as_tensor(np.concatenate([dial_poses().home, np.zeros(30)]), dtype=torch.float32)
    torch.testing.assert_close(encoder(home)[:N_JOINTS], torch.zeros(N_JOINTS))


def test_ocn_with_the_dial_keys_encoder_trains_on_the_raw_state(dial_dataset):
    policy, meta = _policy(dial_dataset, obs_encoder="dial_keys")
    assert policy.config.normalization_mapping["STATE"] is NormalizationMode.IDENTITY
    policy.eval()
    mask, state, *_ = policy.training_windows(one_frame_per_episode(dial_dataset))
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    torch.testing.assert_close(state[mask], torch.from_numpy(episodes.state[episodes.mask]).float())
    policy.train()
    loss, _ = policy.forward(one_frame_per_episode(dial_dataset))
    loss.backward()
    assert torch.isfinite(loss) and all(p.grad is not None and torch.isfinite(p.grad).all()
                                        for p in policy.parameters())
    craft_state = {OBS_STATE: PolicyFeature(FeatureType.STATE, (81,))}
    with pytest.raises(ValueError, match=r"dial_keys encoder expects Dial's state of shape \(39,\)"):
        OCNConfig(device="cpu", obs_encoder="dial_keys", action_type="continuous", input_features=craft_state,
                  output_features={ACTION: PolicyFeature(FeatureType.ACTION, (9,))}).validate_features()


def test_ocn_eval_on_dial(trained, dial_dataset, tmp_path):
    out, mcap = tmp_path / "eval.json", tmp_path / "runs.mcap"
    args = ["--policy", str(trained), "--root", str(dial_dataset), "--repo-id", REPO_ID, "--split", "all",
            "--max-episodes", "5", "--rollouts", "2", "--out", str(out), "--mcap", str(mcap)]
    assert ocn_eval.main(args) == 0
    result = json.loads(out.read_text())
    assert result["world"] == "dial" and result["episodes_parsed"] == 5 and "not_applicable" not in result
    shape = result["parse_statistics"]
    assert shape["true_segments_per_episode"] == 2.0 and shape["segments_per_episode"] >= 1.0  # 2-digit PINs
    assert len(shape["label_share"]) <= 4 and sum(shape["label_share"]) == pytest.approx(1.0, abs=1e-3)
    assert shape["boundary_offsets"]["boundaries"] == 5  # one inner boundary per 2-digit PIN
    assert "boundary_offsets_by_previous_action" not in shape  # 9 torques: no action to split by
    for key in ("f1_tol0", "f1_tol1", "align_acc", "nmi"):
        assert 0.0 <= result[key] <= 1.0, key
    table = result["option_subtask_success"]
    assert sorted(table["subtasks"]) == ["1", "2"] and np.array(table["table"]).shape == (4, 2)  # digit columns
    assert sorted(result["success_rate"]) == ["12", "21"]
    assert all(rate in (0.0, 0.5, 1.0) for rate in result["success_rate"].values())
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"

    topics = read_mcap_messages(mcap)
    finals = [m for m in topics["/reward"] if m["success"] is not None]
    assert len(finals) == 2 * 2 and {m["task"] for m in finals} == {"press 1, press 2", "press 2, press 1"}
    assert {len(m["state"]) for m in topics["/observation"]} == {len(dial_state_names())}
    assert {len(m["action"]) for m in topics["/action"]} == {N_JOINTS}
    for pin, task in (("12", "press 1, press 2"), ("21", "press 2, press 1")):
        assert np.mean([m["success"] for m in finals if m["task"] == task]) == result["success_rate"][pin]
    from mcap.reader import make_reader

    with mcap.open("rb") as f:
        metadata = {record.name: record.metadata for record in make_reader(f).iter_metadata()}
    assert json.loads(metadata["observation.state"]["names"]) == dial_state_names()


def test_ocn_view_on_dial(trained, dial_dataset, tmp_path):
    path, png = tmp_path / "dial.rrd", tmp_path / "dial.png"
    args = ["--root", str(dial_dataset), "--repo-id", REPO_ID, "--split", "all", "--episodes", "3",
            "--policy", str(trained), "--save", str(path), "--png", str(png)]
    assert ocn_view.main(args) == 0
    temporal, static = read_rrd(path)
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"), 3)
    policy, preprocessor, _ = load_ocn(trained)
    parses = parse_episodes(policy, preprocessor, episodes)
    total = int(episodes.lengths.sum())
    steps = [(i, t) for i, n in enumerate(episodes.lengths) for t in range(n)]
    state = np.stack([episodes.state[i, t] for i, t in steps])

    keys = static["/scene/keys"]
    np.testing.assert_allclose(keys["Points3D:positions"][0], key_positions(), atol=1e-6)
    assert keys["Points3D:labels"][0] == [str(d) for d in range(10)]
    tip = temporal["/scene/fingertip"]
    assert tip["frame"] == list(range(total))
    offsets = state[:, N_JOINTS:].reshape(total, 10, 3)
    np.testing.assert_allclose(values(tip["Points3D:positions"]), offsets[:, 3] + key_positions()[3], atol=1e-5)
    np.testing.assert_allclose(temporal["/joints"]["Scalars:scalars"], state[:, :N_JOINTS], atol=1e-6)
    np.testing.assert_allclose(temporal["/key_distance"]["Scalars:scalars"], np.abs(offsets).sum(2), atol=1e-5)
    actions = np.stack([episodes.action[i, t] for i, t in steps])
    np.testing.assert_allclose(temporal["/action"]["Scalars:scalars"], actions, atol=1e-6)

    lane = temporal["/segments/subtask"]
    digits = [f"press {episodes.subtask_id[i, t]}" for i, t in steps]
    assert forward_fill(lane["frame"], values(lane["StateChange:state"]), total) == digits
    lane = temporal["/segments/option"]
    chosen = [f"option {o}" for parse in parses for o in parse.option]
    assert forward_fill(lane["frame"], values(lane["StateChange:state"]), total) == chosen
    p_c = np.concatenate([parse.p_c for parse in parses])
    for k in range(p_c.shape[1]):
        np.testing.assert_allclose(values(temporal[f"/p_c/option_{k}"]["Scalars:scalars"]), p_c[:, k], atol=1e-6)
    end = np.concatenate([parse.end for parse in parses])
    np.testing.assert_allclose(values(temporal["/termination/e_t"]["Scalars:scalars"]), end, atol=1e-6)
    assert {f"/summary/usage/{d}" for d in "12"} <= set(static)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_ocn_annotate_on_dial(trained, dial_dataset, tmp_path):
    out, annotated_id = tmp_path / "annotated", f"{REPO_ID}_ocn"
    args = ["--policy", str(trained), "--root", str(dial_dataset), "--repo-id", annotated_id, "--out-root", str(out),
            "--name-by", "subtask"]
    assert ocn_annotate.main(args) == 0
    episodes = load_episodes(dial_dataset, split_episodes(dial_dataset, "all"))
    policy, preprocessor, _ = load_ocn(trained)
    parses = parse_episodes(policy, preprocessor, episodes)
    option = np.concatenate([parse.option for parse in parses])
    subtask = np.concatenate([episodes.subtask_id[i, :n] for i, n in enumerate(episodes.lengths)])
    name = {int(k): f"press {np.bincount(subtask[option == k]).argmax()}" for k in np.unique(option)}
    annotation = json.loads((out / "meta" / "ocn_annotation.json").read_text())
    assert {o["option"]: o["name"] for o in annotation["options"]} == name  # named by the digit it overlaps most

    ds = LeRobotDataset(annotated_id, root=out)
    assert ds.meta.has_language_columns and ds.num_episodes == len(parses)
    for e, parse in zip(episodes.episode_index, parses, strict=True):
        starts = [0, *np.flatnonzero(parse.option[1:] != parse.option[:-1]) + 1]
        expected = [(int(s), name[int(parse.option[s])]) for s in starts]
        span = ds.meta.episodes[int(e)]
        for index in (span["dataset_from_index"], span["dataset_to_index"] - 1):
            item = ds[index]
            assert item["language_events"] == []
            rows = item["language_persistent"]
            assert all(r["role"] == "assistant" and r["style"] == "subtask" for r in rows)
            assert [(round(r["timestamp"] * ds.fps), r["content"]) for r in rows] == expected
    card = (out / "README.md").read_text()
    assert f"# {annotated_id}: Dial demonstrations" in card and "## OCN subtask annotations" in card


def test_the_dial_scene_places_the_fingertip_where_the_env_has_it():
    batch = DialBatch(3)
    obs = batch.reset(seeds=[0, 1, 2], tasks=["12", "48", "81"])
    obs, *_ = batch.step(np.random.default_rng(0).uniform(-1, 1, (3, N_JOINTS)))
    np.testing.assert_allclose(DialScene().fingertip(obs), batch.tip, atol=1e-6)


def test_a_dataset_of_another_world_is_parsed_without_acting_in_it(trained, dial_dataset, tmp_path, capsys):
    root = tmp_path / "other"
    shutil.copytree(dial_dataset, root)
    info_path = root / "meta" / "info.json"
    info_path.write_text(json.dumps({**json.loads(info_path.read_text()), "robot_type": "koch"}))
    eval_args = ["--policy", str(trained), "--root", str(root), "--repo-id", REPO_ID, "--out", str(tmp_path / "x.json")]
    assert ocn_eval.main(eval_args) == 0
    result = json.loads((tmp_path / "x.json").read_text())
    assert result["world"] == "koch" and result["nmi"] is not None and result["success_rate"] is None
    assert "robot_type 'koch'" in result["not_applicable"]["success_rate"]
    assert ocn_view.main(["--root", str(root), "--repo-id", REPO_ID, "--save", str(tmp_path / "x.rrd")]) == 0
    annotate_args = ["--policy", str(trained), "--root", str(root), "--repo-id", REPO_ID,
                     "--out-root", str(tmp_path / "annotated")]
    assert ocn_annotate.main(annotate_args) == 0
    card = (tmp_path / "annotated" / "README.md").read_text()
    assert card.startswith((root / "README.md").read_text().rstrip("\n"))  # its own card, the section added
    assert card.count("## OCN subtask annotations") == 1
    assert ocn_eval.main([*eval_args[:-1], str(tmp_path / "y.json"), "--mcap", str(tmp_path / "x.mcap")]) == 2
    assert "robot_type 'koch'" in capsys.readouterr().err
