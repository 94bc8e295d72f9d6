"""`ocn-bench`: each benchmark's measuring functions on tiny real runs, its report, where its result goes,
and a --help that imports neither torch nor LeRobot. No speed is asserted: speeds are measured by the
committed benchmark results, never by tests."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

import pytest

from conftest import CRAFT_REPO_ID
from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.tools.bench import BENCHMARKS, main


def _provenance(command: str) -> dict:
    """The fields `new_result` gives a result, for reports built from measured parts."""
    return {"benchmark": command.split()[1], "command": command, "note": "", "date": "2026-12-07",
            "machine": {"cpu": "AMD EPYC", "cores": 2, "python": "3.12.1", "platform": "Linux"}}


def test_help_imports_neither_torch_nor_lerobot():
    """`ocn-bench --help` and every subcommand's, in a fresh interpreter: none imports torch or LeRobot."""
    script = (
        "import contextlib, io, sys\n"
        "from lerobot_policy_ocn.tools.bench import BENCHMARKS, build_parser\n"
        "for argv in [['--help'], *[[name, '--help'] for name in BENCHMARKS]]:\n"
        "    with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.suppress(SystemExit):\n"
        "        build_parser().parse_args(argv)\n"
        "    assert 'usage: ocn-bench' in out.getvalue(), argv\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'lerobot'))\n"
        "assert not heavy, heavy[:5]\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True)
    assert set(BENCHMARKS) == {"train", "ppo", "env", "dial", "stacked", "first-layer", "skills",
                               "quickstart"}


def test_results_go_under_the_working_folder_with_date_machine_and_command(tmp_path, monkeypatch):
    """Without --out a benchmark writes results/bench_NAME.{json,md} under the current folder, and a second
    run overwrites that one pair."""
    monkeypatch.chdir(tmp_path)
    for _ in range(2):
        main(["dial", "--steps", "16", "--pins", "2", "--note", "test run"])
    assert sorted(path.name for path in (tmp_path / "results").iterdir()) == ["bench_dial.json", "bench_dial.md"]
    result = json.loads((tmp_path / "results" / "bench_dial.json").read_text())
    assert result["command"] == "ocn-bench dial --steps 16 --pins 2 --note 'test run'"
    assert result["date"] and result["machine"]["cores"] >= 1 and result["machine"]["cpu"]
    report = (tmp_path / "results" / "bench_dial.md").read_text()
    assert f"Command: `{result['command']}`. Date: {result['date']}. Machine: {result['machine']['cpu']}" in report
    assert "Conditions: test run" in report
    assert result["expert"]["pins"] == 2 and 0.0 <= result["expert"]["success"] <= 1.0
    assert result["env"]["physics_ratio"] > 0


def test_stacked_writes_one_row_per_setting_against_the_goal_and_refuses_bad_lists(tmp_path, capsys):
    out = tmp_path / "stacked.json"
    main(["stacked", "--options", "2,3", "--batch-sizes", "1,3", "--threads", "1", "--window", "4", "--rounds", "1",
          "--out", str(out)])
    result = json.loads(out.read_text())
    rows = result["rows"]
    assert [(row["n_options"], row["batch_size"], row["threads"]) for row in rows] == [
        (2, 1, 1), (2, 3, 1), (3, 1, 1), (3, 3, 1)]
    for row in rows:
        assert row["speedup"] == pytest.approx(row["stacked_frames_per_s"] / row["loop_frames_per_s"])
    assert [row["overhead_bound"] for row in rows] == pytest.approx([14 / 9, 14 / 9, 19 / 9, 19 / 9])
    report = out.with_suffix(".md").read_text()
    assert result["goal"] == 1.5 and "Goal: stacked at least 1.5x the loop" in report
    met = "yes" if rows[3]["speedup"] >= 1.5 else "no"
    assert f"| 3 | 3 | 1 | {rows[3]['stacked_frames_per_s']:,.0f} |" in report and f"| {met} |" in report
    for bad in ("0,8", "8,x"):
        with pytest.raises(SystemExit):
            main(["stacked", "--batch-sizes", bad, "--out", str(out)])
        assert "--batch-sizes" in capsys.readouterr().err


def test_first_layer_times_each_way_on_the_same_policy_and_puts_the_policys_own_back(tmp_path, craft_dataset):
    """Each variant runs the layer it names (the replaced `embedding_bag` backward, the dense features), the
    policy's own comes back after it, and the report has one row per setting with the ratios of its times."""
    import torch

    from lerobot_policy_ocn.ocn.cell import sparse_rows_product
    from lerobot_policy_ocn.tools.bench.models import dataset_policy, embedding_bag_product, first_layer

    policy = dataset_policy(craft_dataset, CRAFT_REPO_ID, "cpu")
    states = torch.zeros(2, 3, 81)
    with first_layer(policy, "embedding_bag"):
        assert policy.core.options.sparse_product is embedding_bag_product
    with first_layer(policy, "dense"):
        assert policy.encoder.sparse(states) is None
    assert policy.core.options.sparse_product is sparse_rows_product
    assert policy.encoder.sparse(states) is not None
    out = tmp_path / "first_layer.json"
    main(["first-layer", "--root", str(craft_dataset), "--batch-sizes", "2,3", "--threads", "1", "--rounds", "1",
          "--block", "1", "--out", str(out)])
    result = json.loads(out.read_text())
    assert [(row["threads"], row["batch_size"]) for row in result["rows"]] == [(1, 2), (1, 3)]
    report = out.with_suffix(".md").read_text()
    for row in result["rows"]:
        times = row["step_s"]
        assert row["speedup"] == pytest.approx(times["embedding_bag"] / times["matmul_backward"])
        assert f"| 1 | {row['batch_size']} | {times['embedding_bag'] * 1000:.1f} |" in report
    assert result["dataset"]["recorded_by"] is None


def test_ppo_times_each_part_of_an_iteration_with_a_checkpoints_options(tmp_path, ocn_checkpoint, capsys):
    out = tmp_path / "ppo.json"
    main(["ppo", "--envs", "3,6", "--iterations", "1", "--task-sets", "s1", "--checkpoint", str(ocn_checkpoint),
          "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["checkpoint"] == str(ocn_checkpoint)
    assert [(row["task_set"], row["envs"]) for row in result["rows"]] == [("s1", 3), ("s1", 6)]
    for row in result["rows"]:
        assert row["frames"] > 0 and row["decisions"] > 0 and row["frames_per_s"] > 0
        parts = row["select_action_s"] + row["env_step_s"]
        assert 0 < parts < row["collect_s"]  # the rest of collecting: processors and bookkeeping
        assert row["trainable_params"] > 0
    report = out.with_suffix(".md").read_text()
    assert "the options of" in report and "| S1 (ADC,CAD,DCA) | 6 |" in report and "S1: 6 envs run" in report
    with pytest.raises(SystemExit):
        main(["ppo", "--task-sets", "s1,s9", "--out", str(out)])
    assert "unknown task sets ['s9']" in capsys.readouterr().err


def test_ppo_without_a_checkpoint_stands_in_a_random_ocn(tmp_path):
    from lerobot_policy_ocn.tools.bench.ppo import iteration_times

    row = iteration_times(None, "BADC,ACBD,CABD", 3, 1)
    assert row["envs"] == 3 and 0 < row["decisions_per_frame"] < 1  # options that run more than one step


def test_env_rates_and_a_record_demos_run():
    from lerobot_policy_ocn.tools.bench import env

    rates = env.env_rates(40)
    assert set(rates) == {"single_env_steps_per_s", "batched_64_core_steps_per_s", "vector_env_64_steps_per_s"}
    assert all(rate > 0 for rate in rates.values())
    recorded = env.record_rate(1, mcap=True)
    assert recorded["episodes"] == 3 and recorded["frames"] > 0 and recorded["wall_s"] > 0
    assert recorded["command"] == ("record_demos --env craft --tasks AC,CD,DA --episodes-per-task 1 --root R "
                                   "--repo-id local/s1 --mcap demo.mcap")
    report = env.markdown({**_provenance("ocn-bench env"), "env_steps": rates, "record_demos": recorded,
                           "record_demos_with_mcap": recorded, "record_demos_import_s": env.import_seconds(repeats=1)})
    assert f"`{recorded['command']}` (3 episodes" in report


def test_train_runs_one_and_two_processes_on_the_same_samples(tmp_path, craft_dataset, capsys):
    """The whole benchmark at a tiny size: 1 and 2 processes of lerobot-train on one global batch, their
    parse scores, and what bounds the ratio; a batch that does not split is refused first."""
    out = tmp_path / "train.json"
    with pytest.raises(SystemExit, match="does not split evenly"):
        main(["train", "--root", str(craft_dataset), "--batch-size", "5", "--out", str(out)])
    main(["train", "--root", str(craft_dataset), "--steps", "2", "--batch-size", "4", "--workers", "0",
          "--eval-rollouts", "1", "--out", str(out)])
    result = json.loads(out.read_text())
    one, two = result["runs"]
    assert one["effective_batch_logged"] == "Effective batch size: 4 x 1 = 4"
    assert two["effective_batch_logged"] == "Effective batch size: 2 x 2 = 4"
    assert one["samples"] == two["samples"] == 8 and two["command"].startswith("torchrun --standalone")
    for run in (one, two):
        assert run["real_frames_per_s"] > 0 and 0.0 <= run["nmi"] <= 1.0 and 0.0 <= run["f1_tol1"] <= 1.0
    assert [row["batch"] for row in result["update_alone"]] == [4, 2]
    assert result["allreduce_s"]["2"]["gradients"] > 0 and result["dataset"]["recorded_by"] is None
    report = out.with_suffix(".md").read_text()
    assert "(its log: Effective batch size: 2 x 2 = 4)" in report and "at most **" in report
    assert f"{one['num_params']:,} floats" in report and "accelerate launch --multi_gpu" in report


def test_train_reads_lerobots_step_lines():
    from lerobot_policy_ocn.tools.bench.train import logged_steps

    log = ("INFO 2026-12-07 ot_train.py:641 step:1K smpl:128K ep:6K epch:1.00 loss:1.2 grdn:0.3 lr:1.0e-03 "
           "updt_s:0.250 data_s:0.010 smp/s:492 nll:1.1 frames_used:1510.500 mean_end:0.2\nINFO other line\n")
    assert logged_steps(log) == [{"step": 1000.0, "updt_s": 0.25, "data_s": 0.01, "frames_used": 1510.5}]


def test_skills_runs_the_plain_commands_from_an_empty_folder(tmp_path):
    from lerobot_policy_ocn.tools.bench import skills
    from lerobot_policy_ocn.tools.bench.common import typed

    args = argparse.Namespace(episodes_per_task=2, device="cpu", batch_size=128)
    commands = skills.plain_commands(tmp_path, 3, 2, args)
    assert {name: typed(command).replace(f"{tmp_path}/", "") for name, command in commands.items()} == {
        "record_demos": "record_demos --env craft --tasks AC,CD,DA --episodes-per-task 2 --root R --repo-id local/s1",
        "lerobot-train": "lerobot-train --policy.type=ocn --policy.device=cpu --dataset.repo_id=local/s1 "
                         "--dataset.root=R --steps=2 --batch_size=128 --output_dir=O --seed=3 --wandb.enable=false "
                         "--policy.push_to_hub=false",
        "ocn-eval": "ocn-eval --policy O/checkpoints/last/pretrained_model --root R --repo-id local/s1 --out M.json",
    }
    commands["lerobot-train"].append("--num_workers=0")  # the test's one change: no data workers to start
    commands["ocn-eval"] += ["--rollouts", "1"]
    timed = skills.timed_pipeline(commands, tmp_path)
    assert set(timed["wall_s"]) == set(commands) and timed["total_wall_s"] >= sum(timed["wall_s"].values())
    assert timed["against_ompn_release"] == pytest.approx(timed["total_wall_s"] / 900.0)
    assert timed["reached_goal"] == (timed["nmi"] >= 0.95)
    runs = [{"seed": 3, "steps": 2, **timed}]
    result = {**_provenance("ocn-bench skills --steps 2"), "nmi_goal": 0.95, "ompn_release_wall_s": 900.0,
              "ompn_release_f1": 0.98, "steps": [2], "seeds": runs, "fastest": skills.fastest(runs)}
    report = skills.markdown(result)
    assert "    record_demos --env craft" in report and f"| 2 | 3 | {timed['wall_s']['record_demos']:.0f} |" in report
    # The title always names the study; the bold headline with a time only where a run met the goal.
    assert ("**Time to skills:" in report) == timed["reached_goal"] and "2 steps: " in report


def test_quickstart_measures_a_command_in_an_empty_folder_against_the_goals(craft_dataset, ocn_checkpoint):
    """`measure` on a real command that writes the quickstart's eval.json (ocn-eval, one rollout), since the
    quickstart itself takes minutes."""
    from lerobot_policy_ocn.tools.bench import quickstart

    measured = quickstart.measure([console_script("ocn-eval"), "--policy", str(ocn_checkpoint), "--root",
                                   str(craft_dataset), "--repo-id", CRAFT_REPO_ID, "--out", str(quickstart.EVAL_JSON),
                                   "--rollouts", "1"])
    assert measured["wall_s"] > 0 and measured["met"]["wall"] == (measured["wall_s"] <= 240.0)
    assert measured["met"]["nmi"] == (measured["nmi"] >= 0.9)
    result = {**_provenance("ocn-bench quickstart"), **measured}
    assert f"| NMI (`outputs/quickstart/eval.json`) | **{measured['nmi']:.3f}** | >= 0.9" in quickstart.markdown(result)


def test_a_run_that_never_exits_after_its_end_line_is_stopped_and_says_so(monkeypatch):
    """The guard against LeRobot's closing `destroy_process_group` hanging (common.run_timed): a command
    alive past the grace after its end line is stopped, its wall time ends at that line and its output
    says so; a command that fails still raises, and one that exits is left alone."""
    from lerobot_policy_ocn.tools.bench import common

    monkeypatch.setattr(common, "TEARDOWN_GRACE_S", 1.0)
    hangs = [sys.executable, "-c",
             "import time; print('step 1'); print('End of training', flush=True); time.sleep(300)"]
    wall, output = common.run_timed(hangs, ends_at="End of training")
    assert wall < 1.0 and output.startswith("step 1\nEnd of training\n")
    assert output.splitlines()[-1].startswith(common.TEARDOWN_STOPPED)
    wall, output = common.run_timed([sys.executable, "-c", "print('End of training')"], ends_at="End of training")
    assert common.TEARDOWN_STOPPED not in output
    with pytest.raises(RuntimeError, match="exited with 3"):
        common.run_timed([sys.executable, "-c", "import sys; print('End of training'); sys.exit(3)"],
                         ends_at="End of training")
