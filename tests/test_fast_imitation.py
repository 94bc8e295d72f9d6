"""The in-memory training loop for trying recipes: it trains the real policy on a recorded dataset,
scores the parse with the shared metrics and draws curves."""

import json

import pytest

from conftest import CRAFT_REPO_ID
from ocn_data.episodes_table import load_episodes, split_episodes
from tools.episode_parsing import load_policy, score_segmentations, segment_episodes
from tools.fast_imitation import main, parse_overrides


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
        assert all(0 <= point[key] <= 1 for key in ("f1_tol0", "f1_tol1", "align_acc", "nmi"))
        assert sum(point["option_share"]) == pytest.approx(1.0, abs=1e-3)
    policy, preprocessor, _ = load_policy(tmp_path / "model")
    assert policy.config.usage_balance == 1.0 and policy.config.hidden_size == 16
    val = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    reloaded = score_segmentations(val, segment_episodes(policy, preprocessor, val))
    assert reloaded == {key: result["curve"][-1][key] for key in reloaded}
    # --init continues that model: its config (hidden size 16, not the default), then --set on top.
    more = tmp_path / "continued.json"
    assert main(["train", "--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--out", str(more), "--steps", "2",
                 "--batch-size", "8", "--eval-every", "2", "--init", str(tmp_path / "model"),
                 "--set", "termination_cost=0.1", "termination_penalty=log"]) == 0
    continued = json.loads(more.read_text())
    assert continued["settings"]["hidden_size"] == 16 and continued["settings"]["usage_balance"] == 1.0
    assert continued["settings"]["termination_penalty"] == "log" and continued["settings"]["termination_cost"] == 0.1
    png = tmp_path / "curves.png"
    assert main(["plot", str(out), "--png", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fast_imitation_overrides_are_typed_config_fields():
    assert parse_overrides(["usage_balance=0.5", "n_options=6", "option_memory=false", "lr_schedule=cosine"]) == {
        "usage_balance": 0.5, "n_options": 6, "option_memory": False, "lr_schedule": "cosine"}
    with pytest.raises(SystemExit, match="OCNConfig field"):
        parse_overrides(["no_such_field=1"])
    with pytest.raises(SystemExit, match="takes true or false"):
        parse_overrides(["option_memory=maybe"])
