"""`ocn-reproduce gather`: a finetuning study from real `ocn-finetune` folders, and the runs it refuses."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from tools.ocn_finetune import main as ocn_finetune
from tools.reproduce import main as reproduce
from tools.reproduce.finetune import FINAL_ROWS

torch.set_num_threads(1)


def finetuned(out: Path, checkpoint: Path | None, seed: int, tasks: str = "ADC,CAD") -> Path:
    """A tiny sparse-reward `ocn-finetune` run over `checkpoint`'s options (None: flat PPO)."""
    source = ["--checkpoint", str(checkpoint)] if checkpoint else ["--flat", "--hidden-size", "16"]
    argv = [*source, "--tasks", tasks, "--frames", "300", "--envs", "4", "--max-steps", "20", "--seed", str(seed),
            "--batch-size", "32", "--out", str(out)]
    assert ocn_finetune(argv) == 0
    return out


@pytest.fixture(scope="module")
def runs(ocn_checkpoint, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("gather")
    return {"ocn1": finetuned(root / "ocn1", ocn_checkpoint, 1), "ocn2": finetuned(root / "ocn2", ocn_checkpoint, 2),
            "flat1": finetuned(root / "flat1", None, 1)}


def test_gather_writes_the_study_of_hand_made_runs(runs, tmp_path):
    assert reproduce(["gather", *map(str, runs.values()), "--name", "hand", "--results", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "finetune_hand.json").read_text())
    assert result["labels"] == ["ADC", "CAD"] and result["methods"] == ["OCN", "flat PPO"]
    assert result["command"].startswith("ocn-reproduce gather")
    assert set(result["summary"]) == {"OCN | sparse", "flat PPO | sparse"}
    assert result["summary"]["OCN | sparse"]["seeds"] == [1, 2]

    def last_rows(folder: Path, key: str) -> float:
        rows = list(csv.DictReader(open(folder / "curve.csv")))
        return float(np.mean([float(row[key]) for row in rows[-FINAL_ROWS:]]))

    ocn = result["summary"]["OCN | sparse"]["at_budget"]
    for key in ("success", "success[ADC]", "mean_return"):
        expected = np.mean([last_rows(runs["ocn1"], key), last_rows(runs["ocn2"], key)])
        assert ocn[key]["mean"] == pytest.approx(expected, abs=1e-4), key
    text = (tmp_path / "finetune_hand.md").read_text()
    assert "| OCN | sparse | 2 |" in text and "| flat PPO | sparse | 1 |" in text
    assert all(f"`{folder}`" in text for folder in runs.values())
    assert (tmp_path / "finetune_hand.png").stat().st_size > 10_000


def test_gather_refuses_unfinished_duplicated_and_unlike_runs(runs, ocn_checkpoint, tmp_path):
    def refused(*folders: Path) -> str:
        with pytest.raises(SystemExit) as raised:
            reproduce(["gather", *map(str, folders), "--name", "x", "--results", str(tmp_path / "results")])
        return str(raised.value)

    unfinished = tmp_path / "unfinished"
    shutil.copytree(runs["ocn1"], unfinished)
    (unfinished / "finetune.json").unlink()
    assert refused(runs["ocn2"], unfinished) == (f"ocn-reproduce gather: {unfinished} has no finetune.json; is it a "
                                                 "finished ocn-finetune --out?")
    copy = tmp_path / "copy"
    shutil.copytree(runs["ocn1"], copy)
    duplicated = f"{runs['ocn1']} and {copy} are both the OCN run with sparse reward and seed 1"
    assert duplicated in refused(runs["ocn1"], copy)
    other_tasks = finetuned(tmp_path / "adc", ocn_checkpoint, 3, tasks="ADC")
    assert "the runs differ in tasks" in refused(runs["ocn1"], other_tasks)
    assert not (tmp_path / "results").exists()
