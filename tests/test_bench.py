"""`ocn-bench train`'s report: every measured row, and the ratios computed from the same runs."""

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
                                                  "speedup": 1.6}}],
        "stacked_vs_loop": {"stacked_frames_per_s": 26000.0, "loop_frames_per_s": 24000.0, "speedup": 26 / 24},
        "select_action_s": {"batch_1": 0.0004, "batch_64": 0.002},
    }
    report = _train_markdown(result)
    assert "on the packed view, batch 128, 1 worker, 2 math threads, window 24 | 8,800 real frames/s" in report
    assert "on S1, batch 128, 2 workers, 1 math thread, window 24 | 2,200 real frames/s" in report
    assert "| one worker and two math threads against 2 workers and one (same runs) | 1.60x |" in report
    assert "(stacked is 1.08x)" in report and "| 0.40 ms per step |" in report
    assert ("padding included (as before `OCNCore.unroll_frames`; alternated, best of 3) | stepping only the rows still "
            "in their episode is 1.60x faster") in report


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
    policy.core.step = lambda state, x, start: calls.append(start.shape[0]) or core_step(state, x, start)
    with stepping_every_row(policy):
        every, _ = policy.forward(batch)
    assert calls == [4] * 6  # every row at every step of the window
    calls.clear()
    policy.forward(batch)
    assert calls == [4, 4, 3, 3, 2, 2]  # outside, only the rows still in their episode
    torch.testing.assert_close(every, running)
