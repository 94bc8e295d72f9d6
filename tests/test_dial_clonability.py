"""`ocn-bench clonability`: the explained-variance fit and the Dial expert's frames it is fitted to."""

from __future__ import annotations

import json

import numpy as np

from tools.dial_clonability import explained_variance, expert_frames, feature_sets


def test_explained_variance_is_high_for_a_function_of_the_input_and_low_for_noise():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, 3)).astype(np.float32)
    y = np.stack([np.sin(2 * x[:, 0]) + x[:, 1] * x[:, 2], rng.normal(size=2000)], axis=1)
    held_out = np.arange(2000) % 5 == 0
    r2 = explained_variance(x, y, held_out, steps=800)
    assert r2[0] > 0.9
    assert r2[1] < 0.1  # fitted noise explains nothing held out (or less than nothing)


def test_expert_frames_are_whole_episodes_and_the_expert_needs_no_velocity():
    frames = expert_frames(episodes=3, num_envs=2)
    n = len(frames["t"])
    assert frames["obs"].shape == (n, 39) and frames["action"].shape == (n, 9) and frames["qvel"].shape == (n, 9)
    assert sorted(set(frames["episode"].tolist())) == [0, 1, 2]
    for episode in range(3):
        t = frames["t"][frames["episode"] == episode]
        np.testing.assert_array_equal(t, np.arange(len(t)))
    assert set(frames["digit"].tolist()) <= {1, 2, 4, 8}
    inputs = feature_sets(frames)
    assert [x.shape[1] for x in inputs.values()] == [39, 43, 82, 52]
    change = inputs["observation + digit + last change"][:, 43:]
    assert not change[frames["t"] == 0].any() and change[frames["t"] > 0].any()
    # The expert's control is a function of the observation and the digit: two frames of one digit
    # with the same observation get the same control, whatever the velocities.
    from envs.dial import DialBatch, DialExpert

    batch = DialBatch(2)
    batch.reset(seeds=[0, 0], tasks=["12", "12"])
    expert = DialExpert(batch, (0.0,))
    batch.data[1].qvel[:] = 0.5
    batch.qvel[1] = 0.5
    np.testing.assert_allclose(expert.act()[0], expert.act()[1])


def test_ocn_bench_clonability_writes_every_input_row(tmp_path):
    from tools.bench import main

    out = tmp_path / "clonability.json"
    main(["clonability", "--episodes", "4", "--fit-steps", "10", "--out", str(out), "--note", "test"])
    result = json.loads(out.read_text())["clonability"]
    assert result["episodes"] == 4 and result["frames"] > 0 < result["held_out_frames"] < result["frames"]
    assert list(result["r2"]) == ["observation", "observation + digit", "observation + digit + last change",
                                  "observation + digit + joint velocities"]
    report = out.with_suffix(".md").read_text()
    assert "Conditions: test" in report and "| observation + digit |" in report
