"""`ocn-annotate`: an OCN's parse as native LeRobot subtask rows in a new dataset that LeRobot loads and trains on."""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from huggingface_hub import DatasetCard
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.collate import lerobot_collate_fn

from lerobot_policy_ocn.envs.craft.world import SUBTASK_NAMES
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from lerobot_policy_ocn.ocn_data.record_demos import main as record_demos
from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.ocn import OCNConfig
from lerobot_policy_ocn.tools.eval.parsing import load_ocn, parse_episodes
from lerobot_policy_ocn.tools.cli.ocn_annotate import main as ocn_annotate

torch.set_num_threads(1)

ANNOTATED_ID = "local/craft_small_ocn"


def tree_digest(root: Path) -> dict[str, str]:
    files = (p for p in root.rglob("*") if p.is_file())
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def run_annotate(policy: Path, root: Path, out: Path, *extra: str) -> int:
    args = ["--policy", str(policy), "--root", str(root), "--repo-id", ANNOTATED_ID, "--out-root", str(out)]
    return ocn_annotate([*args, *extra])


@pytest.fixture(scope="module")
def parses(craft_dataset, ocn_checkpoint):
    """The checkpoint's own parse of every episode, and the episodes, for comparison."""
    policy, preprocessor, _ = load_ocn(ocn_checkpoint)
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "all"))
    return parse_episodes(policy, preprocessor, episodes), episodes


@pytest.fixture(scope="module")
def annotated(craft_dataset, ocn_checkpoint, tmp_path_factory) -> tuple[Path, dict, dict]:
    """(annotated root, input digest before, input digest after) of one `--name-by option` run."""
    before = tree_digest(craft_dataset)
    out = tmp_path_factory.mktemp("annotate") / "ds"
    assert run_annotate(ocn_checkpoint, craft_dataset, out) == 0
    return out, before, tree_digest(craft_dataset)


def segments(option: np.ndarray, name) -> list[tuple[int, str]]:
    starts = [0, *np.flatnonzero(option[1:] != option[:-1]) + 1]
    return [(int(s), name(int(option[s]))) for s in starts]


def frame_rows(ds: LeRobotDataset, index: int) -> list[tuple[int, str]]:
    item = ds[index]
    rows = item["language_persistent"]
    assert all(r["role"] == "assistant" and r["style"] == "subtask" and r["camera"] is None for r in rows)
    assert item["language_events"] == []
    return [(round(r["timestamp"] * ds.fps), r["content"]) for r in rows]


def test_rows_are_the_parse_segments_on_every_frame(annotated, parses):
    root, _, _ = annotated
    parsed, episodes = parses
    ds = LeRobotDataset(ANNOTATED_ID, root=root)
    assert ds.meta.has_language_columns and ds.num_episodes == len(parsed)
    for e, parse in zip(episodes.episode_index, parsed, strict=True):
        expected = segments(parse.option, lambda k: f"option {k}")
        first, last = ds.meta.episodes[int(e)]["dataset_from_index"], ds.meta.episodes[int(e)]["dataset_to_index"] - 1
        assert frame_rows(ds, first) == expected == frame_rows(ds, last)
    assert any(parse.switches.size for parse in parsed)  # the checkpoint's options do switch within episodes


def test_input_is_untouched_and_the_copy_is_complete(annotated, craft_dataset):
    root, before, after = annotated
    assert before == after
    copied = tree_digest(root)
    changed = {name for name in before if copied.get(name) != before[name]}
    assert changed == {"README.md", "data/chunk-000/file-000.parquet"}  # it already had language columns
    assert set(copied) - set(before) == {"meta/ocn_annotation.json"}
    assert not [p for p in root.parent.iterdir() if p.name != root.name]  # no scratch folder left behind


def test_adds_the_language_columns_to_a_dataset_without_them(ocn_checkpoint, tmp_path):
    root, out = tmp_path / "plain", tmp_path / "annotated"
    assert record_demos(["--tasks", "CD", "--episodes-per-task", "3", "--root", str(root), "--repo-id", "local/plain",
                         "--seed", "5"]) == 0
    assert not LeRobotDataset("local/plain", root=root).meta.has_language_columns
    assert run_annotate(ocn_checkpoint, root, out) == 0
    features = json.loads((out / "meta" / "info.json").read_text())["features"]
    assert features["language_persistent"]["dtype"] == features["language_events"]["dtype"] == "language"
    ds = LeRobotDataset(ANNOTATED_ID, root=out)
    assert ds.meta.has_language_columns and all(frame_rows(ds, i) for i in range(ds.num_frames))


def test_a_batch_of_the_annotated_dataset_trains_a_policy_built_from_it(annotated):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    root, _, _ = annotated
    meta = LeRobotDatasetMetadata(ANNOTATED_ID, root=root)
    policy = make_policy(OCNConfig(device="cpu", recipe="paper", hidden_size=8, mlp_hidden_size=8), ds_meta=meta)
    preprocessor, _ = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    frames = LeRobotDataset(ANNOTATED_ID, root=root)
    assert "language_persistent" in frames[5]
    loader = torch.utils.data.DataLoader(frames, batch_size=4, collate_fn=lerobot_collate_fn)  # lerobot-train's
    batch = next(iter(loader))
    policy.train()
    loss, stats = policy(preprocessor(batch))
    assert torch.isfinite(loss) and stats["frames_used"] > 0
    loss.backward()


def test_lerobot_train_runs_on_the_annotated_dataset(annotated, tmp_path):
    root, _, _ = annotated
    proc = subprocess.run(
        [console_script("lerobot-train"), "--policy.type=ocn", f"--dataset.repo_id={ANNOTATED_ID}",
         f"--dataset.root={root}", "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false",
         "--env_eval_freq=0", "--steps=2", "--batch_size=2", "--num_workers=0", "--policy.hidden_size=8",
         "--policy.mlp_hidden_size=8", f"--output_dir={tmp_path / 'train'}"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "train" / "checkpoints" / "000002" / "pretrained_model" / "model.safetensors").is_file()


def test_names_by_the_most_overlapping_subtask(craft_dataset, ocn_checkpoint, parses, tmp_path):
    parsed, episodes = parses
    out = tmp_path / "by_subtask"
    assert run_annotate(ocn_checkpoint, craft_dataset, out, "--name-by", "subtask") == 0
    option = np.concatenate([p.option for p in parsed])
    subtask = np.concatenate([episodes.subtask_id[i, :n] for i, n in enumerate(episodes.lengths)])
    overlap = {k: np.bincount(subtask[option == k], minlength=len(SUBTASK_NAMES)) for k in np.unique(option)}
    name = {int(k): SUBTASK_NAMES[int(counts.argmax())] for k, counts in overlap.items()}
    annotation = json.loads((out / "meta" / "ocn_annotation.json").read_text())
    assert {o["option"]: o["name"] for o in annotation["options"]} == name
    assert sum(o["frames"] for o in annotation["options"]) == int(episodes.lengths.sum())
    ds = LeRobotDataset(ANNOTATED_ID, root=out)
    for e, parse in zip(episodes.episode_index, parsed, strict=True):
        assert frame_rows(ds, ds.meta.episodes[int(e)]["dataset_from_index"]) == segments(parse.option, name.get)


def test_card_describes_the_annotation(annotated):
    root, _, _ = annotated
    card = DatasetCard.load(root / "README.md")
    assert card.data.license == "apache-2.0" and {"LeRobot", "robotics"} <= set(card.data.tags)
    assert f"# {ANNOTATED_ID}: Craft demonstrations" in card.text
    assert "## OCN subtask annotations" in card.text and "named by its option number" in card.text
    assert "| get wood, get iron | `AC` | 10 |" in card.text


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing checkpoint", "holds no config.json"),
        ("existing out-root", "already exists"),
        ("out-root inside root", "lies inside the dataset"),
        ("not a dataset", "is not a LeRobot dataset"),
    ],
)
def test_bad_input_is_a_clear_error(case, message, craft_dataset, ocn_checkpoint, tmp_path, capsys):
    policy, root, out = ocn_checkpoint, craft_dataset, tmp_path / "out"
    if case == "missing checkpoint":
        policy = tmp_path / "no_checkpoint"
    elif case == "existing out-root":
        out.mkdir()
    elif case == "out-root inside root":
        out = craft_dataset / "annotated"
    else:
        root = tmp_path / "empty"
        root.mkdir()
    assert run_annotate(policy, root, out) == 2
    err = capsys.readouterr().err
    assert err.startswith("ocn-annotate: ") and message in err and len(err.strip().splitlines()) == 1
    assert not (craft_dataset / "annotated").exists()
    assert case == "existing out-root" or not out.exists()
