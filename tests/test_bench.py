"""`ocn-bench train`'s report: every measured row, and the ratios computed from the same runs."""

import pytest

from tools.bench import _train_markdown


def _train_run(workers: int, threads: int, step_s: float) -> dict:
    return {"steps": 150, "batch_size": 128, "num_workers": workers, "threads": threads, "window_size": 24,
            "step_s": step_s, "update_s": step_s - 0.01, "data_wait_s": 0.01, "real_frames_per_step": 1100.0,
            "real_frames_per_s": 1100.0 / step_s}


def test_train_report_gives_the_packed_views_thread_setting_and_its_ratio():
    result = {
        "machine": {"cpu": "AMD EPYC", "cores": 2, "python": "3.12.1"}, "device": {"type": "cpu"}, "note": "",
        "train_rounds": 2, "lerobot_train": _train_run(2, 1, 0.5), "lerobot_train_view": _train_run(2, 1, 0.4),
        "lerobot_train_packed": _train_run(2, 1, 0.2), "lerobot_train_packed_threads": _train_run(1, 2, 0.125),
        "getitem_s_per_window": 0.007, "getitem_view_s_per_window": 0.005, "getitem_packed_s_per_row": 0.0005,
        "update_only": [{"threads": 1, "real_frames_per_s": 12000.0, "padded_frames_per_s": 40000.0,
                         "running_vs_every_row": {"running_rows_per_s": 40000.0, "every_row_per_s": 25000.0,
                                                  "speedup": 1.6},
                         "restarts_ahead_vs_each_step": {"restarts_ahead_per_s": 39000.0,
                                                         "restarts_each_step_per_s": 30000.0, "speedup": 1.3}}],
        "stacked_vs_loop": {"stacked_frames_per_s": 26000.0, "loop_frames_per_s": 24000.0, "speedup": 26 / 24},
        "select_action_s": {"batch_1": 0.0004, "batch_64": 0.002},
    }
    report = _train_markdown(result)
    assert "on the packed view, batch 128, 1 worker, 2 math threads, window 24 | 8,800 real frames/s" in report
    assert "on S1, batch 128, 2 workers, 1 math thread, window 24 | 2,200 real frames/s" in report
    assert "| one worker and two math threads against 2 workers and one (same runs) | 1.60x |" in report
    assert "(stacked is 1.08x)" in report and "| 0.40 ms per step |" in report
    assert ("padding included (as before `OCNCore.unroll_frames`; alternated, best of 3) | stepping only the rows "
            "still in their episode is 1.60x faster") in report
    assert ("computed in each step (as before `OCNCore.restarts_ahead`; alternated, best of 3) | computing it for "
            "the whole window in one call is 1.30x faster") in report


def test_stepping_every_row_keeps_the_loss_and_is_undone():
    """The baseline of the running-rows speed-up: the same loss, every row stepped, only inside."""
    import torch

    from lerobot.utils.constants import ACTION
    from policies.ocn.benchmark import make_bench_policy, random_batch, stepping_every_row

    policy = make_bench_policy(hidden_size=16, obs_dim=20, window=6)
    batch = random_batch(policy, 4, 6)
    batch[f"{ACTION}_is_pad"][0, 2:] = batch[f"{ACTION}_is_pad"][3, 4:] = True
    running, _ = policy.forward(batch)
    calls = []
    core_step = policy.core.step
    policy.core.step = lambda state, x, start, restarted: calls.append(start.shape[0]) or core_step(
        state, x, start, restarted)
    with stepping_every_row(policy):
        every, _ = policy.forward(batch)
    assert calls == [4] * 6  # every row at every step of the window
    calls.clear()
    policy.forward(batch)
    assert calls == [4, 4, 3, 3, 2, 2]  # outside, only the rows still in their episode
    torch.testing.assert_close(every, running)


@pytest.mark.parametrize("only_real_frames", [True, False])
def test_restarting_in_each_step_keeps_the_loss_and_gradients_and_is_undone(only_real_frames):
    """The baseline of the restarts-ahead speed-up: the options' restarted branch computed in each step
    gives the same loss and gradients as one call for the whole window, over the real frames alone
    (`unroll_frames`) and over every frame (`unroll_projected`); only inside the context."""
    import torch

    from lerobot.utils.constants import ACTION
    from policies.ocn.benchmark import make_bench_policy, random_batch, restarting_in_each_step
    from policies.sequence import training_windows

    policy = make_bench_policy(hidden_size=16, obs_dim=20, window=6)
    batch = random_batch(policy, 4, 6)
    batch[f"{ACTION}_is_pad"][0, 2:] = batch[f"{ACTION}_is_pad"][3, 4:] = True
    mask, state, _ = training_windows(policy.config, batch)
    calls = []
    restarts = policy.core.restarts
    policy.core.restarts = lambda x_options: calls.append(x_options.shape[1]) or restarts(x_options)

    def loss_and_gradients() -> tuple:
        policy.zero_grad(set_to_none=True)
        out = policy._unroll(state, batch["task"], mask if only_real_frames else None)
        loss = (out.weights.square().sum() + out.params.square().sum() + out.end.sum())
        loss.backward()
        return loss, [parameter.grad.clone() for parameter in policy.parameters()]

    ahead, ahead_grads = loss_and_gradients()
    assert calls == ([mask.sum().item()] if only_real_frames else [4 * 6])  # one call for the window
    calls.clear()
    with restarting_in_each_step(policy):
        each, each_grads = loss_and_gradients()
    assert calls == ([4, 4, 3, 3, 2, 2] if only_real_frames else [4] * 6)  # one call per step
    calls.clear()
    loss_and_gradients()
    assert len(calls) == 1
    torch.testing.assert_close(ahead, each)
    for got, expected in zip(ahead_grads, each_grads, strict=True):
        torch.testing.assert_close(got, expected)


def test_critic_per_step_gives_the_same_replay_and_gradients_and_is_undone():
    """The baseline of the replay speed-up: the critic one decision step at a time, only inside."""
    import torch

    import tools.ppo as ppo
    from tools.ppo_speed import bench_pool, critic_per_step

    policy = bench_pool("flat", ["get wood", "get grass"])
    critic = ppo.ValueHead(policy.config.hidden_size, 8)
    state = torch.rand(3, 5, 81)
    task_index = torch.tensor([0, 1, 0])

    def replayed() -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
        policy.zero_grad(set_to_none=True)
        critic.zero_grad(set_to_none=True)
        logits, values = ppo.replay_controller(policy, critic, state, task_index)
        (logits.square().sum() + values.sum()).backward()
        grads = [p.grad.clone() for p in (*policy.core.controller.parameters(), *critic.parameters())]
        return logits.detach(), values.detach(), grads

    at_once = critic.net
    logits, values, grads = replayed()
    with critic_per_step(critic):
        assert critic.net is not at_once
        per_step_logits, per_step_values, per_step_grads = replayed()
    assert critic.net is at_once
    assert logits.shape == (3, 5, 5) and values.shape == (3, 5)
    torch.testing.assert_close(per_step_logits, logits)
    torch.testing.assert_close(per_step_values, values)
    for per_step, now in zip(per_step_grads, grads, strict=True):
        torch.testing.assert_close(per_step, now)


def test_ocn_bench_ppo_writes_both_pools_rates_and_the_replay_ratio(tmp_path):
    import json

    from tools.bench import main

    out = tmp_path / "bench_ppo.json"
    main(["ppo", "--envs", "3", "--iterations", "1", "--out", str(out), "--note", "test"])
    result = json.loads(out.read_text())
    pools = {p["pool"]: p for p in result["pools"]}
    assert set(pools) == {"flat", "ocn"}
    assert pools["flat"]["decisions_per_frame"] == 1.0  # a decision at every step
    assert 0 < pools["ocn"]["decisions_per_frame"] < 1.0
    for p in pools.values():
        assert p["frames"] > 0 and p["frames_per_s"] > 0 and p["replay"]["speedup"] > 0
    report = out.with_suffix(".md").read_text()
    assert "Conditions: test" in report and "| flat pool (a decision every step" in report


def test_ocn_bench_stacked_writes_one_row_per_setting_and_refuses_bad_lists(tmp_path, capsys):
    import json

    import pytest

    from tools.bench import main

    out = tmp_path / "bench_stacked.json"
    main(["stacked", "--options", "2,3", "--batch-sizes", "1,3", "--threads", "1", "--window", "4", "--rounds", "1",
          "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(row["n_options"], row["batch_size"], row["threads"]) for row in rows] == [
        (2, 1, 1), (2, 3, 1), (3, 1, 1), (3, 3, 1)]
    for row in rows:
        assert row["speedup"] == pytest.approx(row["stacked_frames_per_s"] / row["loop_frames_per_s"])
    assert [row["overhead_bound"] for row in rows] == pytest.approx([14 / 9, 14 / 9, 19 / 9, 19 / 9])
    assert f"| 3 | 3 | 1 | {rows[3]['stacked_frames_per_s']:,.0f} |" in out.with_suffix(".md").read_text()
    for bad in ("0,8", "8,x"):
        with pytest.raises(SystemExit):
            main(["stacked", "--batch-sizes", bad, "--out", str(out)])
        assert "--batch-sizes" in capsys.readouterr().err
