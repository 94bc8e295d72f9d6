"""OCN on datasets written by LeRobot's own API, as a new user's are (`LeRobotDataset.create`,
`add_frame`, `save_episode`, `finalize`; no robot type this project knows):

- `state_only`: one float `observation.state`, discrete actions, ground-truth subtask columns;
- `two_states_and_video`: `observation.state`, `observation.environment_state` and a video
  `observation.image`, continuous 2-d actions, ground truth (the issue's failing case);
- `unlabelled`: a float state and discrete actions, no ground-truth columns at all.

Each trains with plain `lerobot-train --policy.type=ocn` (no `--policy.*` flag) for a few steps, then
goes through `ocn-annotate`, `ocn-view --save` and `ocn-eval`. The episodes are synthetic: two
phases per episode, each with its own action rule, which is all the tools need to run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

import lerobot_policy_ocn  # noqa: F401  (registers `ocn` as LeRobot's CLIs do)
from lerobot_policy_ocn.episode_memory import fit_frames
from lerobot_policy_ocn.ocn import OCNConfig
from lerobot_policy_ocn.ocn.encoders import ConvEncoder, random_shift
from lerobot_policy_ocn.tools.cli.ocn_annotate import main as ocn_annotate
from lerobot_policy_ocn.tools.cli.ocn_eval import main as ocn_eval
from lerobot_policy_ocn.tools.cli.ocn_view import main as ocn_view

torch.set_num_threads(1)

EPISODES = 12
LENGTH = 10
IMAGE = (24, 32, 3)  # height, width, channels: not square, so that shrinking to 40 x 40 is exercised
TASKS = ("reach then push", "push then reach")


def make_dataset(root: Path, repo_id: str, *, states: dict[str, int], image: str | None, discrete: bool,
                 labelled: bool, episodes: int = EPISODES) -> Path:
    """`episodes` episodes of LENGTH frames written by LeRobot's own writer: random float states, an image
    (`image`: stored as "video" or as "image", or None) whose brightness encodes the phase and whose
    texture is random, an action that follows the phase, the tasks in turn."""
    rng = np.random.default_rng(0)
    features = {key: {"dtype": "float32", "shape": (width,), "names": None} for key, width in states.items()}
    if image:
        features["observation.image"] = {"dtype": image, "shape": IMAGE, "names": ["height", "width", "channels"]}
    features["action"] = {"dtype": "int64", "shape": (1,), "names": None} if discrete else \
        {"dtype": "float32", "shape": (2,), "names": None}
    if labelled:
        features |= {key: {"dtype": "int64", "shape": (1,), "names": None} for key in ("subtask.index", "subtask.id")}
    dataset = LeRobotDataset.create(repo_id, 10, features, root=root, use_videos=image == "video")
    for episode in range(episodes):
        switch = int(rng.integers(3, LENGTH - 3))
        for t in range(LENGTH):
            phase = int(t >= switch)
            frame = {key: rng.normal(size=width).astype(np.float32) + phase for key, width in states.items()}
            if image:
                frame["observation.image"] = (40 + 160 * phase + rng.integers(0, 50, IMAGE)).astype(np.uint8)
            frame["action"] = np.array([phase + int(rng.random() < 0.2)], dtype=np.int64) if discrete else \
                np.array([phase, 1 - phase], dtype=np.float32) + rng.normal(scale=0.1, size=2).astype(np.float32)
            if labelled:
                frame |= {"subtask.index": np.array([phase]), "subtask.id": np.array([(phase + episode) % 2])}
            dataset.add_frame({**frame, "task": TASKS[episode % 2]})
        dataset.save_episode()
    dataset.finalize()
    return root


@pytest.fixture(scope="module")
def state_only(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("state_only") / "ds", "local/state_only",
                        states={"observation.state": 5}, image=None, discrete=True, labelled=True)


@pytest.fixture(scope="module")
def two_states_and_video(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("video") / "ds", "local/two_states_and_video",
                        states={"observation.state": 4, "observation.environment_state": 3}, image="video",
                        discrete=False, labelled=True)


@pytest.fixture(scope="module")
def unlabelled(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("unlabelled") / "ds", "local/unlabelled",
                        states={"observation.state": 6}, image=None, discrete=True, labelled=False)


def lerobot_train(root: Path, out: Path, *flags: str) -> Path:
    """3 steps of plain `lerobot-train --policy.type=ocn` on `root`; the final pretrained_model folder."""
    command = [str(Path(sys.executable).parent / "lerobot-train"), "--policy.type=ocn", "--dataset.repo_id=local/x",
               f"--dataset.root={root}", "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false",
               "--steps=3", "--batch_size=4", "--num_workers=0", f"--output_dir={out}", *flags]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=out.parent,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    return out / "checkpoints" / "000003" / "pretrained_model"


def run_tools(checkpoint: Path, root: Path, tmp_path: Path, capsys) -> dict:
    """`ocn-annotate`, `ocn-view --save` and `ocn-eval` on the dataset; returns ocn-eval's JSON."""
    out = tmp_path / "annotated"
    assert ocn_annotate(["--policy", str(checkpoint), "--root", str(root), "--repo-id", "local/annotated",
                         "--out-root", str(out)]) == 0
    annotated = LeRobotDatasetMetadata("local/annotated", root=out)
    assert "language_persistent" in annotated.features and (out / "README.md").is_file()
    rrd = tmp_path / "view.rrd"
    assert ocn_view(["--root", str(root), "--repo-id", "local/x", "--policy", str(checkpoint), "--save", str(rrd),
                     "--episodes", "3"]) == 0
    assert rrd.stat().st_size > 0
    result = tmp_path / "eval.json"
    capsys.readouterr()
    assert ocn_eval(["--policy", str(checkpoint), "--root", str(root), "--repo-id", "local/x", "--out", str(result),
                     "--rollouts", "2"]) == 0
    assert "switches/frame" in capsys.readouterr().out
    return json.loads(result.read_text())


def test_state_only_dataset_trains_and_is_scored_without_a_world(state_only, tmp_path, capsys):
    checkpoint = lerobot_train(state_only, tmp_path / "train")
    config = json.loads((checkpoint / "config.json").read_text())
    assert list(config["input_features"]) == ["observation.state"]
    assert (config["obs_encoder"], config["action_type"], config["n_actions"]) == ("identity", "discrete", 3)
    result = run_tools(checkpoint, state_only, tmp_path, capsys)
    assert result["f1_tol1"] is not None and result["nmi"] is not None and result["world"] == "none"
    assert result["held_out"] is False and result["split"] == "val"  # LeRobot names no val split: the last fifth
    assert result["episodes_parsed"] == round(EPISODES * 0.2) and result["action_nll"] > 0
    assert result["success_rate"] is None and "no world" in result["not_applicable"]["success_rate"]
    free = result["label_free"]
    assert abs(sum(free["option_usage"]) - 1) < 1e-3 and free["segment_length"]["max"] <= LENGTH


def test_two_state_keys_and_a_video_are_all_read(two_states_and_video, tmp_path, capsys):
    checkpoint = lerobot_train(two_states_and_video, tmp_path / "train")
    config = json.loads((checkpoint / "config.json").read_text())
    assert set(config["input_features"]) == {"observation.state", "observation.environment_state",
                                             "observation.image"}
    assert config["input_features"]["observation.image"]["shape"] == [3, *IMAGE[:2]]
    assert (config["obs_encoder"], config["action_type"]) == ("identity", "continuous")
    result = run_tools(checkpoint, two_states_and_video, tmp_path, capsys)
    assert result["nmi"] is not None and result["label_free"]["switch_rate"] >= 0


def test_a_dataset_without_ground_truth_gets_the_label_free_figures(unlabelled, tmp_path, capsys):
    checkpoint = lerobot_train(unlabelled, tmp_path / "train")
    result = run_tools(checkpoint, unlabelled, tmp_path, capsys)
    assert all(result[key] is None for key in ("f1_tol0", "f1_tol1", "align_acc", "nmi"))
    assert "ground-truth subtask columns" in result["not_applicable"]["parsing_scores"]
    assert result["parse_statistics"] is None and result["action_nll"] > 0
    assert set(result["label_free"]) == {"segments_per_episode", "segment_length", "switch_rate", "option_usage"}
    annotation = json.loads((tmp_path / "annotated" / "meta" / "ocn_annotation.json").read_text())
    assert annotation["ground_truth"] is False and annotation["name_by"] == "option"
    assert "still hold the ground truth" not in (tmp_path / "annotated" / "README.md").read_text()
    assert ocn_annotate(["--policy", str(checkpoint), "--root", str(unlabelled), "--repo-id", "local/a",
                         "--out-root", str(tmp_path / "by_subtask"), "--name-by", "subtask"]) == 2
    error = capsys.readouterr().err.strip()
    assert "no subtask.index/subtask.id" in error and "\n" not in error
    assert ocn_view(["--root", str(unlabelled), "--repo-id", "local/x", "--png", str(tmp_path / "x.png")]) == 2
    assert "nothing to draw" in capsys.readouterr().err


def build(root: Path, **config) -> torch.nn.Module:
    """An OCN built in memory from the dataset at `root`, as lerobot-train builds it."""
    from lerobot.policies.factory import make_policy

    meta = LeRobotDatasetMetadata("local/x", root=root)
    return make_policy(OCNConfig(device="cpu", hidden_size=16, mlp_hidden_size=16, **config), ds_meta=meta)


@pytest.mark.parametrize("stored", ["video", "image"])
def test_images_are_decoded_once_as_lerobot_decodes_them(stored, two_states_and_video, tmp_path):
    root = two_states_and_video if stored == "video" else make_dataset(
        tmp_path / "ds", "local/image", states={}, image="image", discrete=True, labelled=False, episodes=3)
    policy = build(root, recipe="paper")
    frames = policy._episodes.frames["observation.image"]
    dataset = LeRobotDataset("local/x", root=root)
    assert frames.dtype == torch.uint8 and tuple(frames.shape) == (len(dataset), 3, 40, 40)
    for index in (0, 7, LENGTH + 4, len(dataset) - 1):
        item = dataset[index]
        start = int(policy._episodes.start[int(item["episode_index"])])
        expected = fit_frames(item["observation.image"], 40)
        assert torch.equal(frames[start + int(item["frame_index"])], expected)


def test_training_shifts_each_frame_and_evaluation_reads_it_as_it_is():
    frames = torch.rand(64, 3, 12, 12) * 255
    moved = random_shift(frames, 2)
    padded = torch.nn.functional.pad(frames, (2, 2, 2, 2), mode="replicate")
    offsets = set()
    for frame, original in zip(moved, padded, strict=True):
        matches = [(row, col) for row in range(5) for col in range(5)
                   if torch.equal(original[:, row : row + 12, col : col + 12], frame)]
        assert len(matches) == 1
        offsets.add(matches[0])
    assert len(offsets) > 10  # each frame draws its own offset

    encoder = ConvEncoder(3, 40)
    images = torch.rand(8, 3, 40, 40) * 255
    assert not torch.equal(encoder(images), encoder(images))  # training: shifted at random
    encoder.eval()
    assert torch.equal(encoder(images), encoder(images))


def test_features_can_be_dropped_and_bad_ones_are_named(two_states_and_video, state_only, tmp_path):
    policy = build(two_states_and_video, recipe="paper", drop_features=["observation.image"])
    assert policy.config.image_keys == [] and "observation.image" not in policy._episodes.frames
    images_alone = build(two_states_and_video, recipe="paper",
                         drop_features=["observation.state", "observation.environment_state"])
    assert images_alone.config.obs_encoder == "none" and images_alone.encoder.out_dim == 128
    with pytest.raises(ValueError, match=r"`observation.image` alone takes .*drop_features='\[observation.image\]'"
                                         r".*--policy.image_size"):
        build(two_states_and_video, recipe="paper", image_size=64, episode_memory_mb=1)
    with pytest.raises(ValueError, match="names \\['observation.depth'\\], which the dataset"):
        build(state_only, drop_features=["observation.depth"])
    with pytest.raises(ValueError, match="cannot drop `action`"):
        build(state_only, drop_features=["action"])
    grid = tmp_path / "grid"
    dataset = LeRobotDataset.create("local/grid", 10, {
        "observation.state": {"dtype": "float32", "shape": (2, 3), "names": None},
        "action": {"dtype": "int64", "shape": (1,), "names": None}}, root=grid, use_videos=False)
    for t in range(4):
        dataset.add_frame({"observation.state": np.zeros((2, 3), np.float32), "action": np.array([t % 2]),
                           "task": "t"})
    dataset.save_episode()
    dataset.finalize()
    with pytest.raises(ValueError, match=r"`observation.state` is float32 of shape \(2, 3\): drop it with "
                                         r"--policy.drop_features='\[observation.state\]'"):
        build(grid)


def test_tools_name_a_dataset_that_lacks_what_the_policy_reads(two_states_and_video, unlabelled, compile_checkpoint,
                                                                tmp_path, capsys):
    policy = build(two_states_and_video, recipe="paper")
    checkpoint = tmp_path / "pretrained_model"
    policy.save_pretrained(checkpoint)
    from lerobot.policies.factory import make_pre_post_processors

    for processor in make_pre_post_processors(policy.config, dataset_stats=LeRobotDatasetMetadata(
            "local/x", root=two_states_and_video).stats):
        processor.save_pretrained(checkpoint)
    cases = [
        (ocn_eval, ["--policy", str(checkpoint), "--root", str(unlabelled), "--repo-id", "local/x", "--out",
                    str(tmp_path / "e.json")], "has no `observation.environment_state`, `observation.image`"),
        (ocn_view, ["--root", str(unlabelled), "--repo-id", "local/x", "--policy", str(checkpoint), "--save",
                    str(tmp_path / "v.rrd")], "has no `observation.environment_state`, `observation.image`"),
        (ocn_annotate, ["--policy", str(compile_checkpoint), "--root", str(unlabelled), "--repo-id", "local/x",
                        "--out-root", str(tmp_path / "a")], "holds an `compile` checkpoint; this tool needs an `ocn`"),
        (ocn_eval, ["--policy", str(checkpoint), "--root", str(tmp_path), "--repo-id", "local/x", "--out",
                    str(tmp_path / "e.json")], "is not a LeRobot dataset"),
    ]
    for tool, args, needle in cases:
        capsys.readouterr()
        assert tool(args) == 2
        error = capsys.readouterr().err.strip()
        assert needle in error and "\n" not in error and "Traceback" not in error
