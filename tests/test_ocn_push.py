"""`ocn-push`: the dry-run folder is exactly the repository to upload, with cards that huggingface_hub
parses; without a token or a reachable Hub the upload is a one-line error (exit code 2), never a traceback."""

from __future__ import annotations

import http.server
import json
import socket
import subprocess
import threading
from pathlib import Path

import pytest
from huggingface_hub import DatasetCard, ModelCard
from lerobot.configs.default import DatasetConfig
from lerobot.configs.train import TrainPipelineConfig

from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.tools.eval.parsing import load_ocn
from lerobot_policy_ocn.tools.cli.ocn_eval import main as ocn_eval
from lerobot_policy_ocn.tools.cli.ocn_push import main as ocn_push

TRAIN_COMMAND = "lerobot-train --policy.type=ocn --dataset.repo_id=local/craft_small --steps=3000"


def tree(root: Path) -> dict[str, bytes]:
    return {"/".join(p.relative_to(root).parts): p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def eval_json(craft_dataset, ocn_checkpoint, tmp_path_factory) -> Path:
    """A real `ocn-eval` JSON (and its PNG) for the checkpoint, from a handful of rollouts."""
    out = tmp_path_factory.mktemp("eval") / "ocn_eval.json"
    assert ocn_eval(["--policy", str(ocn_checkpoint), "--root", str(craft_dataset), "--repo-id", "local/craft_small",
                     "--out", str(out), "--rollouts", "2"]) == 0
    return out


def test_dataset_dry_run_is_the_dataset_with_a_card_for_the_new_repo(craft_dataset, tmp_path):
    out = tmp_path / "dry"
    args = ["dataset", "--root", str(craft_dataset), "--repo-id", "me/craft_small", "--dry-run", str(out)]
    assert ocn_push(args) == 0
    staged, source = tree(out), tree(craft_dataset)
    assert set(staged) == set(source)
    assert {name: data for name, data in staged.items() if name != "README.md"} == {
        name: data for name, data in source.items() if name != "README.md"
    }
    card = DatasetCard.load(out / "README.md")
    assert card.data.license == "apache-2.0" and {"LeRobot", "robotics"} <= set(card.data.tags)
    assert card.data.task_categories == ["robotics"] and card.data.configs[0]["data_files"] == "data/*/*.parquet"
    # the rebuilt card is record_demos' card for the new repo id; the recording commands it quotes keep
    # the id they recorded with
    recorded = [line for line in source["README.md"].decode().splitlines() if line.startswith("record_demos ")]
    assert recorded and all("--repo-id local/craft_small" in line for line in recorded)
    expected = [
        line if line in recorded else line.replace("local/craft_small", "me/craft_small")
        for line in source["README.md"].decode().splitlines()
    ]
    assert staged["README.md"].decode().splitlines() == expected


def test_policy_dry_run_holds_the_checkpoint_eval_and_model_card(ocn_checkpoint, eval_json, tmp_path):
    out = tmp_path / "dry"
    args = ["policy", "--path", str(ocn_checkpoint), "--repo-id", "me/ocn-craft", "--eval-json", str(eval_json),
            "--train-command", TRAIN_COMMAND, "--dry-run", str(out)]
    assert ocn_push(args) == 0
    staged, checkpoint = tree(out), tree(ocn_checkpoint)
    assert set(staged) == set(checkpoint) | {"README.md", "eval/ocn_eval.json", "eval/ocn_eval.png"}
    assert all(staged[name] == data for name, data in checkpoint.items())
    assert staged["eval/ocn_eval.json"] == eval_json.read_bytes()
    load_ocn(out)  # what `--policy.path` downloads is a loadable checkpoint with its processors

    card = ModelCard.load(out / "README.md")
    data = card.data
    assert (data.library_name, data.pipeline_tag, data.license) == ("lerobot", "robotics", "apache-2.0")
    # The eval's dataset is a local recording (local/craft_small), which names no Hub dataset: none is listed.
    assert {"lerobot", "robotics", "ocn"} <= set(data.tags) and data.datasets is None
    result = json.loads(eval_json.read_text())
    metrics = {r.metric_name: r.metric_value for r in data.eval_results}
    assert data.model_name == "me/ocn-craft"
    assert metrics["boundary F1, tolerance 0"] == pytest.approx(result["f1_tol0"])
    assert metrics["NMI of options and subtasks"] == pytest.approx(result["nmi"])
    assert metrics["success rate: get wood, get iron"] == pytest.approx(result["success_rate"]["get wood, get iron"])
    text = card.text
    for expected in ("--policy.path=me/ocn-craft", "pip install ./lerobot_policy_ocn", TRAIN_COMMAND, "| options | 3 |",
                     "| hidden size (controller and option cells) | 16 |", "| controller temperature | 1.0 |",
                     "- `get iron, get grass`", "![option x subtask success](eval/ocn_eval.png)"):
        assert expected in text


def test_policy_card_reads_lerobot_train_config(ocn_checkpoint, tmp_path):
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    for path in ocn_checkpoint.iterdir():
        (checkpoint / path.name).write_bytes(path.read_bytes())
    policy, _, _ = load_ocn(ocn_checkpoint)
    TrainPipelineConfig(dataset=DatasetConfig(repo_id="me/craft_small"), policy=policy.config, steps=7,
                        batch_size=5, seed=11).save_pretrained(checkpoint)
    out = tmp_path / "dry"
    assert ocn_push(["policy", "--path", str(checkpoint), "--repo-id", "me/ocn", "--dry-run", str(out)]) == 0
    assert (out / "train_config.json").is_file()
    card = ModelCard.load(out / "README.md")
    assert card.data.datasets == ["me/craft_small"] and card.data.eval_results is None  # a Hub id is listed
    assert "dataset `me/craft_small`, 7 steps of batch size 5, seed 11" in card.text
    assert "The training command was not recorded." in card.text
    assert "No `ocn-eval` results were published" in card.text


def run_push(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([console_script("ocn-push"), *args], capture_output=True, text=True, timeout=120)


@pytest.fixture
def no_token(monkeypatch, tmp_path):
    """A Hugging Face home with no token, and no token in the environment."""
    monkeypatch.setenv("HF_TOKEN", "")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf_home"))
    for name in ("HUGGING_FACE_HUB_TOKEN", "HF_TOKEN_PATH", "HF_OIDC_RESOURCE"):
        monkeypatch.delenv(name, raising=False)


@pytest.mark.parametrize("what", ["dataset", "policy"])
def test_upload_without_a_token_is_a_one_line_error(what, no_token, craft_dataset, ocn_checkpoint):
    source = ["--root", str(craft_dataset)] if what == "dataset" else ["--path", str(ocn_checkpoint)]
    proc = run_push(what, *source, "--repo-id", "me/ocn_test")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "ocn-push: no Hugging Face token: run `hf auth login` or set HF_TOKEN to a write token."
    ]


def test_unreachable_hub_is_a_one_line_error(monkeypatch, craft_dataset):
    with socket.socket() as sock:  # a local port that nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    monkeypatch.setenv("HF_TOKEN", "hf_not_a_real_token")
    monkeypatch.setenv("HF_ENDPOINT", f"http://127.0.0.1:{port}")
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    proc = run_push("dataset", "--root", str(craft_dataset), "--repo-id", "me/ocn_test")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"ocn-push: cannot reach the Hugging Face Hub at http://127.0.0.1:{port}: ")


class RefusingHub(http.server.BaseHTTPRequestHandler):
    """A local stand-in for the Hub that answers every request as the Hub answers a bad token."""

    def do_GET(self):
        body = json.dumps({"error": "Invalid credentials in Authorization header"}).encode()
        self.send_response(401)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def test_refused_token_is_a_one_line_error(monkeypatch, ocn_checkpoint):
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), RefusingHub)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        monkeypatch.setenv("HF_TOKEN", "hf_not_a_real_token")
        monkeypatch.setenv("HF_ENDPOINT", f"http://127.0.0.1:{server.server_address[1]}")
        monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
        proc = run_push("policy", "--path", str(ocn_checkpoint), "--repo-id", "me/ocn_test")
    finally:
        server.shutdown()
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ocn-push: the Hub refused: ") and "token" in lines[0]


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing checkpoint", "holds no config.json"),
        ("not a dataset", "is not a LeRobot dataset"),
        ("bad repo id", "must be ORG/NAME"),
        ("not an eval JSON", "is not an ocn-eval JSON"),
        ("dry-run folder not empty", "is not an empty folder"),
    ],
)
def test_bad_input_is_a_clear_error(case, message, craft_dataset, ocn_checkpoint, tmp_path, capsys):
    out = tmp_path / "dry"
    args = ["policy", "--path", str(ocn_checkpoint), "--repo-id", "me/ocn"]
    if case == "missing checkpoint":
        args[2] = str(tmp_path / "nothing")
    elif case == "not a dataset":
        args = ["dataset", "--root", str(tmp_path), "--repo-id", "me/ds"]
    elif case == "bad repo id":
        args[4] = "ocn"
    elif case == "not an eval JSON":
        (tmp_path / "eval.json").write_text('{"f1_tol0": 0.5}')
        args += ["--eval-json", str(tmp_path / "eval.json")]
    else:
        out.mkdir()
        (out / "stale.txt").write_text("left over")
    assert ocn_push([*args, "--dry-run", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ocn-push: ") and message in err and len(err.strip().splitlines()) == 1
    assert case == "dry-run folder not empty" or not out.exists()


def test_help_lists_both_commands(capsys):
    with pytest.raises(SystemExit) as exit_info:
        ocn_push(["--help"])
    assert exit_info.value.code == 0
    assert "{dataset,policy}" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        ocn_push(["policy", "--help"])
    assert "--eval-json" in capsys.readouterr().out
