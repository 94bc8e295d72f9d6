"""`ocn-view` end to end on the session's recorded Craft dataset and untrained checkpoint.

The .rrd is read back with rerun's own reader and checked against the dataset (load_episodes) and
against the model's parse (parse_episodes), both computed here independently of ocn-view.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lerobot_policy_ocn.envs.craft.world import SUBTASK_LETTERS, SUBTASK_NAMES
from lerobot_policy_ocn.ocn_data.episodes_table import load_episodes, split_episodes
from rrd_reading import forward_fill, read_rrd, values
from lerobot_policy_ocn.tools.cli.ocn_view import main
from lerobot_policy_ocn.tools.viz.scenes import craft_scene_images

CRAFT_REPO_ID = "local/craft_small"


@pytest.fixture(scope="module")
def expected(craft_dataset, ocn_checkpoint):
    """The val episodes and the checkpoint's parse of them, computed without ocn-view."""
    from lerobot_policy_ocn.tools.eval.parsing import load_ocn, parse_episodes

    episodes = load_episodes(craft_dataset, split_episodes(craft_dataset, "val"))
    policy, preprocessor, _ = load_ocn(ocn_checkpoint)
    parses = parse_episodes(policy, preprocessor, episodes)
    offsets = np.concatenate([[0], np.cumsum(episodes.lengths)[:-1]])
    return episodes, parses, offsets


@pytest.fixture(scope="module")
def with_policy(craft_dataset, ocn_checkpoint, tmp_path_factory):
    """One run with a policy: the .rrd read back, and the PNG's path."""
    out = tmp_path_factory.mktemp("view")
    args = ["--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--split", "val",
            "--policy", str(ocn_checkpoint), "--save", str(out / "view.rrd"), "--png", str(out / "view.png")]
    assert main(args) == 0
    return (*read_rrd(out / "view.rrd"), out)


def test_switches_are_logged_where_the_model_switched(with_policy, expected):
    temporal, _, _ = with_policy
    episodes, parses, offsets = expected
    changed = [np.flatnonzero(parse.option[1:] != parse.option[:-1]) + 1 for parse in parses]  # not ocn-view's helper
    switches = np.concatenate([offset + steps for offset, steps in zip(offsets, changed, strict=True)])
    assert switches.size > 0, "the fixture's checkpoint should switch options inside episodes"
    assert temporal["/log/switch"]["frame"] == switches.tolist()
    assert temporal["/termination/switch"]["frame"] == switches.tolist()
    for frame, text in zip(switches, values(temporal["/log/switch"]["TextLog:text"]), strict=True):
        e = int(np.searchsorted(offsets, frame, side="right") - 1)
        option = parses[e].option
        step = frame - offsets[e]
        switch = f"option {option[step - 1]} -> {option[step]}"
        assert text.startswith(f"episode {episodes.episode_index[e]} step {step}: {switch}")


def test_option_distribution_and_termination_match_the_parse(with_policy, expected):
    temporal, _, _ = with_policy
    _, parses, _ = expected
    total = sum(parse.option.size for parse in parses)
    p_c = np.concatenate([parse.p_c for parse in parses])
    for k in range(p_c.shape[1]):
        series = temporal[f"/p_c/option_{k}"]
        assert series["frame"] == list(range(total))
        np.testing.assert_allclose(values(series["Scalars:scalars"]), p_c[:, k], atol=1e-6)
    end = np.concatenate([parse.end for parse in parses])
    np.testing.assert_allclose(values(temporal["/termination/e_t"]["Scalars:scalars"]), end, atol=1e-6)
    lane = temporal["/segments/option"]
    chosen = forward_fill(lane["frame"], values(lane["StateChange:state"]), total)
    assert chosen == [f"option {o}" for parse in parses for o in parse.option]


def test_true_segments_match_the_dataset(with_policy, expected):
    temporal, _, _ = with_policy
    episodes, _, offsets = expected
    total = int(episodes.lengths.sum())
    lane = temporal["/segments/subtask"]
    states = values(lane["StateChange:state"])
    assert lane["frame"][-1] == total and states[-1] == ""  # the lane ends after the last step
    truth = [f"{SUBTASK_LETTERS[s]} {SUBTASK_NAMES[s]}" for i, n in enumerate(episodes.lengths)
             for s in episodes.subtask_id[i, :n]]
    assert forward_fill(lane["frame"], states, total) == truth
    starts = [offset + t for i, (offset, n) in enumerate(zip(offsets, episodes.lengths, strict=True))
              for t in range(n) if t == 0 or episodes.subtask_index[i, t] != episodes.subtask_index[i, t - 1]]
    assert lane["frame"][:-1] == starts
    assert temporal["/segments/episode"]["frame"][:-1] == offsets.tolist()
    assert len(temporal["/scene"]["frame"]) == len(temporal["/action"]["frame"]) == total
    actions = np.concatenate([episodes.action[i, :n, 0] for i, n in enumerate(episodes.lengths)])
    np.testing.assert_array_equal(values(temporal["/action"]["Scalars:scalars"]), actions)


def test_option_usage_summary_and_blueprint(with_policy, expected):
    from rerun.experimental import RrdReader

    _, static, out = with_policy
    episodes, parses, _ = expected
    subtask = np.concatenate([episodes.subtask_id[i, :n] for i, n in enumerate(episodes.lengths)])
    option = np.concatenate([parse.option for parse in parses])
    for s in np.unique(subtask):
        bars = values(static[f"/summary/usage/{SUBTASK_LETTERS[s]}"]["BarChart:values"])[0]["buffer"]
        share = np.bincount(option[subtask == s], minlength=parses[0].p_c.shape[1]) / (subtask == s).sum()
        np.testing.assert_allclose(bars, share)
    assert "option 0" in static["/summary/table"]["TextDocument:text"][0][0]
    assert len(RrdReader(out / "view.rrd").blueprints()) == 1


def test_png_is_a_real_image(with_policy):
    import matplotlib.image

    _, _, out = with_policy
    image = matplotlib.image.imread(out / "view.png")
    assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 600
    assert image[..., :3].std() > 0.05  # drawn, not blank


def test_ground_truth_only_without_policy(craft_dataset, tmp_path):
    path = tmp_path / "truth.rrd"
    args = ["--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--episodes", "2,5", "--save", str(path)]
    assert main(args) == 0
    temporal, static = read_rrd(path)
    model_only = ("/p_c", "/termination", "/summary/usage")
    assert not [entity for entity in {**temporal, **static} if entity.startswith(model_only)]
    assert "/segments/option" not in temporal and "/log/switch" not in temporal
    episodes = load_episodes(craft_dataset, range(20))
    lane = values(temporal["/segments/episode"]["StateChange:state"])
    assert lane == [f"episode 2: {episodes.tasks[2]}", f"episode 5: {episodes.tasks[5]}", ""]
    assert len(temporal["/scene"]["frame"]) == episodes.lengths[2] + episodes.lengths[5]


def test_scene_is_the_env_frame():
    from lerobot_policy_ocn.envs.craft.env import CraftEnv

    env = CraftEnv(task="AC", render_mode="rgb_array")
    observation, _ = env.reset(seed=7)
    for action in (0, 3, 4):
        observation, *_ = env.step(action)
    np.testing.assert_array_equal(craft_scene_images(observation[None])[0], env.render())


@pytest.fixture
def unknown_task_dataset(tmp_path) -> Path:
    """A dataset of task DA, which the fixture checkpoint (tasks AC and CD) was not trained on."""
    from lerobot_policy_ocn.ocn_data.record_demos import main as record_demos

    root = tmp_path / "da"
    assert record_demos(["--tasks", "DA", "--episodes-per-task", "2", "--root", str(root),
                         "--repo-id", "local/da", "--seed", "1", "--subtask-annotations"]) == 0
    return root


@pytest.mark.parametrize("case", ["missing dataset", "no config.json", "unknown task"])
def test_bad_input_is_a_one_line_error(case, craft_dataset, ocn_checkpoint, tmp_path, capsys, request):
    root, policy, needle = craft_dataset, ocn_checkpoint, None
    if case == "missing dataset":
        root, needle = tmp_path / "nowhere", "no meta/info.json"
    elif case == "no config.json":
        policy, needle = tmp_path, "no config.json"
    else:
        root, needle = request.getfixturevalue("unknown_task_dataset"), "not trained on"
    save = tmp_path / "out.rrd"
    capsys.readouterr()  # only what ocn-view writes
    args = ["--root", str(root), "--repo-id", "x/y", "--split", "all", "--policy", str(policy), "--save", str(save)]
    assert main(args) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("ocn-view: ") and "\n" not in error and needle in error
    assert not save.exists()  # nothing is opened before the input is checked


def test_help_and_nothing_to_do(craft_dataset, capsys):
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0 and "--save" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        main(["--root", str(craft_dataset), "--repo-id", CRAFT_REPO_ID])
    assert done.value.code == 2 and "nothing to do" in capsys.readouterr().err
