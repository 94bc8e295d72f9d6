"""Policy runs logged to MCAP by `ocn-eval --mcap`, read back with the `mcap` reader."""

import json

import numpy as np
from mcap.reader import make_reader

from conftest import CRAFT_REPO_ID
from lerobot_policy_ocn.ocn_data.mcap_log import read_mcap_messages
from lerobot_policy_ocn.tools.cli.ocn_eval import main as ocn_eval

ROLLOUTS = 3


def run_eval(dataset, checkpoint, out, mcap):
    return ocn_eval(["--policy", str(checkpoint), "--root", str(dataset), "--repo-id", CRAFT_REPO_ID, "--split", "all",
                     "--out", str(out), "--rollouts", str(ROLLOUTS), "--mcap", str(mcap)])


def test_free_run_steps_reach_the_mcap(craft_dataset, ocn_checkpoint, tmp_path):
    mcap = tmp_path / "runs.mcap"
    assert run_eval(craft_dataset, ocn_checkpoint, tmp_path / "eval.json", mcap) == 0
    result = json.loads((tmp_path / "eval.json").read_text())
    topics = read_mcap_messages(mcap)
    assert set(topics) == {"/observation", "/action", "/option", "/reward"}
    counts = {len(messages) for messages in topics.values()}
    assert len(counts) == 1  # one message per topic per step

    options, rewards = topics["/option"], topics["/reward"]
    episodes = sorted({m["episode_index"] for m in options})
    assert episodes == list(range(ROLLOUTS * len(result["success_rate"])))
    for message in options:
        assert abs(sum(message["p_c"]) - 1.0) < 1e-5
        assert message["option"] == int(np.argmax(message["p_c"]))
        if message["frame_index"] == 0:
            assert message["termination"] == 1.0  # the controller always chooses at t = 1
    finals = [m for m in rewards if m["success"] is not None]
    assert len(finals) == len(episodes) and all(m["done"] for m in finals)
    for task, rate in result["success_rate"].items():
        mine = [m["success"] for m in finals if m["task"] == task]
        assert len(mine) == ROLLOUTS and np.mean(mine) == rate
        returns = [sum(m["reward"] for m in rewards if m["task"] == task and m["episode_index"] == e) for e in episodes]
        assert sum(r > 0 for r in returns) == sum(mine)  # sparse reward: paid exactly on success

    with mcap.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}


def test_an_existing_mcap_is_never_overwritten(craft_dataset, ocn_checkpoint, tmp_path, capsys):
    mcap = tmp_path / "runs.mcap"
    mcap.write_bytes(b"earlier log")
    assert run_eval(craft_dataset, ocn_checkpoint, tmp_path / "eval.json", mcap) == 2
    assert "already exists" in capsys.readouterr().err
    assert mcap.read_bytes() == b"earlier log"
