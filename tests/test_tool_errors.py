"""Bad inputs and outputs of ocn-eval, ocn-view, ocn-annotate and ocn-finetune: each is refused in
one line that names the file (or id) and the fix, before anything is written; damaged checkpoints,
checkpoints of another policy type, unwritable outputs, bad repo ids, and an existing ocn-eval result; and
loading a checkpoint leaves no temporary file behind.
Real checkpoint folders (conftest's untrained OCN, LeRobot's own ACT config), real tool entry points."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from lerobot.policies.act.configuration_act import ACTConfig

from conftest import CRAFT_REPO_ID
from lerobot_policy_ocn.tools.cli import ocn_annotate, ocn_eval, ocn_finetune, ocn_view
from unwritable import read_only_folder

TOOLS: dict[str, Callable[[list[str]], int]] = {
    "ocn-eval": ocn_eval.main, "ocn-view": ocn_view.main, "ocn-annotate": ocn_annotate.main,
    "ocn-finetune": ocn_finetune.main,
}


def tool_args(tool: str, policy: Path, root: Path, out: Path, repo_id: str = CRAFT_REPO_ID) -> list[str]:
    """The smallest run of `tool` with checkpoint `policy` on the dataset `root`, writing under `out`."""
    return {
        "ocn-eval": ["--policy", str(policy), "--root", str(root), "--repo-id", repo_id, "--out", str(out / "e.json"),
                     "--rollouts", "1", "--max-episodes", "2"],
        "ocn-view": ["--policy", str(policy), "--root", str(root), "--repo-id", repo_id, "--save", str(out / "v.rrd"),
                     "--episodes", "2"],
        "ocn-annotate": ["--policy", str(policy), "--root", str(root), "--repo-id", repo_id,
                         "--out-root", str(out / "annotated")],
        "ocn-finetune": ["--checkpoint", str(policy), "--tasks", "ADC", "--frames", "10", "--envs", "2",
                         "--out", str(out / "run")],
    }[tool]


def refused(tool: str, args: list[str], capsys: pytest.CaptureFixture) -> str:
    """Run the tool, which must refuse with exit code 2 and one line of stderr; returns that line."""
    capsys.readouterr()
    assert TOOLS[tool](args) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and error.startswith(f"{tool}: "), error
    return error


@pytest.fixture
def damaged_checkpoints(ocn_checkpoint, tmp_path) -> dict[str, tuple[Path, str]]:
    """Copies of the checkpoint with one file cut short, and the file each error must name."""
    damaged = {}
    for name in ("model.safetensors", "config.json", "policy_preprocessor.json"):
        copy = tmp_path / name / "pretrained_model"
        shutil.copytree(ocn_checkpoint, copy)
        data = (copy / name).read_bytes()
        (copy / name).write_bytes(data[: len(data) // 2])
        damaged[name] = (copy, str(copy / name))
    return damaged


@pytest.mark.parametrize("tool", list(TOOLS))
def test_a_truncated_checkpoint_file_is_named(tool, damaged_checkpoints, craft_dataset, tmp_path, capsys):
    for checkpoint, file in damaged_checkpoints.values():
        error = refused(tool, tool_args(tool, checkpoint, craft_dataset, tmp_path / "out"), capsys)
        assert file in error and ("truncated or corrupt" in error or "not a valid config" in error), error
        assert "copy" in error
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("tool", "wanted"),
    [("ocn-eval", "`ocn`, `ompn` or `compile`"), ("ocn-view", "`ocn`"), ("ocn-annotate", "`ocn`"),
     ("ocn-finetune", "`ocn`, `compile` or `ompn`")],
)
def test_a_checkpoint_of_another_policy_type_says_which_type_is_needed(tool, wanted, craft_dataset, tmp_path, capsys):
    act = tmp_path / "act" / "pretrained_model"
    act.mkdir(parents=True)
    ACTConfig()._save_pretrained(act)
    error = refused(tool, tool_args(tool, act, craft_dataset, tmp_path / "out"), capsys)
    assert f"{act} holds an `act` checkpoint; this tool needs an {wanted} one." in error
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("tool", list(TOOLS))
def test_an_unwritable_output_is_refused_before_the_work(tool, ocn_checkpoint, craft_dataset, tmp_path, capsys):
    blocked = tmp_path / "blocked"
    with read_only_folder(blocked):
        error = refused(tool, tool_args(tool, ocn_checkpoint, craft_dataset, blocked), capsys)
        assert f"cannot write in {blocked}" in error and "choose a folder you can write to" in error
        assert list(blocked.iterdir()) == []


@pytest.mark.parametrize("tool", ["ocn-eval", "ocn-view", "ocn-annotate"])
def test_a_repo_id_needs_exactly_one_slash(tool, ocn_checkpoint, craft_dataset, tmp_path, capsys):
    for repo_id in ("no slash here", "a/b/c", "/name"):
        error = refused(tool, tool_args(tool, ocn_checkpoint, craft_dataset, tmp_path, repo_id), capsys)
        assert f"--repo-id {repo_id!r} must be ORG/NAME with exactly one slash" in error


def test_ocn_eval_keeps_an_earlier_result_unless_forced(ocn_checkpoint, craft_dataset, tmp_path, capsys):
    args = tool_args("ocn-eval", ocn_checkpoint, craft_dataset, tmp_path)
    out, png = tmp_path / "e.json", tmp_path / "e.png"
    assert ocn_eval.main(args) == 0
    assert json.loads(out.read_text())["episodes_parsed"] == 2 and png.is_file()
    out.write_text("an earlier result")
    png.write_bytes(b"an earlier table")
    error = refused("ocn-eval", args, capsys)
    assert f"--out: {out} already exists" in error and "--force" in error
    assert out.read_text() == "an earlier result"
    out.unlink()
    assert f"--out: {png} already exists" in refused("ocn-eval", args, capsys)
    assert png.read_bytes() == b"an earlier table"
    assert ocn_eval.main([*args, "--force"]) == 0
    assert json.loads(out.read_text())["episodes_parsed"] == 2
    assert png.read_bytes().startswith(b"\x89PNG")


def test_loading_a_checkpoint_leaves_no_temporary_file(ocn_checkpoint):
    """LeRobot's config loader writes a temporary JSON that it never deletes; `load_policy` points the temporary
    folder at one of its own while it loads, removes it, and puts the temporary folder back."""
    import tempfile

    from lerobot_policy_ocn.tools.eval.parsing import load_policy

    folder = tempfile.gettempdir()
    before = set(Path(folder).iterdir())
    load_policy(ocn_checkpoint)
    assert tempfile.gettempdir() == folder and set(Path(folder).iterdir()) == before
