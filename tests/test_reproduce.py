"""ocn-reproduce reuses a finished run only when it was trained by the same settings."""

import json

import pytest

from tools.reproduce.runs import check_reusable

COMMAND = "/venv/bin/lerobot-train --policy.type=ocn --dataset.root={root} --steps={steps} --output_dir={root}/out"


def _write_record(run_dir, command):
    run_dir.mkdir(parents=True)
    (run_dir / "record.json").write_text(json.dumps({"train_command": command}))


def test_reuse_ignores_moved_paths(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/old/place", steps=5000))
    check_reusable(tmp_path / "run", COMMAND.format(root="/new/place", steps=5000))


def test_reuse_refuses_other_settings(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=250))
    with pytest.raises(SystemExit, match="trained with other settings"):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000))


def test_unfinished_run_is_checked_by_its_command_file(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "train_command.txt").write_text(COMMAND.format(root="/data", steps=250) + "\n")
    with pytest.raises(SystemExit, match="--steps=250"):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000))
    check_reusable(tmp_path / "empty", COMMAND.format(root="/data", steps=5000))


def test_reuse_ignores_how_often_a_run_logs_and_saves(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --save_freq=5000 --log_freq=50")
    check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --save_freq=1000 --log_freq=10")


def test_reuse_ignores_argument_order(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --policy.n_options=3 --seed=1")
    check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --seed=1 --policy.n_options=3")
    with pytest.raises(SystemExit):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --seed=2 --policy.n_options=3")
