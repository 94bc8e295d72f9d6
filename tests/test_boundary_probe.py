"""`tools.boundary_probe` on a real recorded Craft dataset and an `ocn` checkpoint."""

import json

import numpy as np
import pytest

from ocn_data.episodes_table import load_episodes, split_episodes
from tools.boundary_probe import COLUMNS, main
from tools.parsing_metrics import boundaries_from_labels


def test_the_probe_reads_every_inner_boundary_step_once_and_groups_it_by_the_move_before(
        ocn_checkpoint, craft_dataset, tmp_path, capsys):
    out = tmp_path / "probe.json"
    result = main(["--policy", str(ocn_checkpoint), "--root", str(craft_dataset), "--out", str(out)])
    assert json.loads(out.read_text()) == result
    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    assert result["episodes"] == len(episodes.tasks)
    expected: dict[str, int] = {}
    for i, n in enumerate(episodes.lengths):
        for t in boundaries_from_labels(episodes.subtask_index[i, :n])[:-1]:
            if t > 0:
                key = str(int(episodes.action[i, t - 1, 0]))
                expected[key] = expected.get(key, 0) + 1
    groups = result["by_previous_action"]
    assert {key: row["boundaries"] for key, row in groups.items() if key != "all"} == expected
    assert groups["all"]["boundaries"] == sum(expected.values()) > 0
    for row in groups.values():
        assert all(0.0 <= row[column] <= 1.0 for column in COLUMNS[1:])
    # "all" is the boundary-weighted mean of the groups.
    weights = np.array([row["boundaries"] for key, row in groups.items() if key != "all"])
    for column in COLUMNS[1:]:
        values = np.array([row[column] for key, row in groups.items() if key != "all"])
        assert groups["all"][column] == pytest.approx((weights * values).sum() / weights.sum(), abs=1e-3)
    printed = capsys.readouterr().out
    assert "| previous action | boundaries | handed_over" in printed and ("| left |" in printed or "| up |" in printed)


def test_the_probe_refuses_continuous_actions(ocn_checkpoint, dial_dataset):
    with pytest.raises(ValueError, match="has continuous actions"):
        main(["--policy", str(ocn_checkpoint), "--root", str(dial_dataset), "--split", "all"])
