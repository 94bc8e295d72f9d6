import json

import numpy as np

from tools.option_linearity import affine_r2, main


def test_affine_maps_per_group_explain_what_one_map_for_all_cannot():
    rng = np.random.default_rng(0)
    state = rng.normal(size=(400, 3))
    groups = np.repeat([0, 1], 200)
    # Each group's action is its own exact affine map of the state.
    maps = rng.normal(size=(2, 3, 2))
    action = np.einsum("fs,fsa->fa", state, maps[groups]) + np.array([[1.0, -2.0], [-3.0, 0.5]])[groups]
    assert affine_r2(state, action, groups) > 0.999
    assert affine_r2(state, action, np.zeros(400, int)) < 0.9
    # Groups that cut across the true ones explain no more than one map for all.
    shuffled = rng.permutation(groups)
    assert affine_r2(state, action, shuffled) < affine_r2(state, action, groups) - 0.1


def test_the_cli_scores_the_label_groupings_and_a_checkpoints_options(craft_dataset, ocn_checkpoint, tmp_path):
    out = tmp_path / "linearity.json"
    assert main(["--root", str(craft_dataset), "--policy", str(ocn_checkpoint), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    scores = result["affine_r2"]
    assert set(scores) == {"one group", "subtask", "move into the subtask", f"options of {ocn_checkpoint}"}
    assert all(score <= 1.0 for score in scores.values())
    # More groups can only fit better: a subtask's maps nest in the moves'.
    assert scores["one group"] <= scores["subtask"] <= scores["move into the subtask"] + 1e-9
    assert result["frames"] > 0 and result["groups"]["one group"] == 1
