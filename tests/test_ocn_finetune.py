"""`ocn-finetune`: option pools, the finetuned checkpoint as LeRobot loads it, and bad input."""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
from pathlib import Path

import pytest
import torch

from lerobot_policy_ocn.envs.craft.batch import CraftBatch
from lerobot_policy_ocn.envs.craft.world import parse_task, task_description
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_STATE
from lerobot_policy_ocn.tools.eval.parsing import load_ocn, load_policy
from lerobot_policy_ocn.tools.cli.ocn_finetune import main
from lerobot_policy_ocn.tools.rl.finetuning import merge_option_pools, save_checkpoint

torch.set_num_threads(1)

ADC = task_description(parse_task("ADC"))
CAD = task_description(parse_task("CAD"))


def variant(path: Path, seed: int, **changes) -> PreTrainedPolicy:
    """A policy of the type of the checkpoint at `path` (`ocn` or `compile`), like it but with `changes`
    to its config and fresh weights drawn from `seed`."""
    source, _, _ = load_policy(path)
    torch.manual_seed(seed)
    return type(source)(dataclasses.replace(source.config, pretrained_path=None, **changes)).eval()


def save_variant(base: Path, path: Path, seed: int, **changes) -> Path:
    """`variant` saved as a checkpoint folder with the base checkpoint's processors."""
    _, preprocessor, postprocessor = load_policy(base)
    save_checkpoint(variant(base, seed, **changes), preprocessor, postprocessor, path)
    return path


@pytest.fixture(scope="module")
def second_checkpoint(ocn_checkpoint, tmp_path_factory) -> Path:
    """A compatible checkpoint with 2 options of its own (S2's second model)."""
    return save_variant(ocn_checkpoint, tmp_path_factory.mktemp("second") / "pretrained_model", seed=7, n_options=2)


@pytest.fixture(scope="module")
def finetuned(ocn_checkpoint, second_checkpoint, tmp_path_factory) -> Path:
    """ocn-finetune on two new tasks over the pooled options of both checkpoints (3 + 2 options)."""
    out = tmp_path_factory.mktemp("finetune") / "run"
    args = ["--checkpoint", str(ocn_checkpoint), "--checkpoint", str(second_checkpoint), "--tasks", "ADC,CAD",
            "--reward", "dense", "--frames", "1500", "--envs", "8", "--max-steps", "30", "--seed", "1",
            "--batch-size", "32", "--out", str(out)]
    assert main(args) == 0
    return out


def test_merged_pool_options_act_exactly_as_in_their_own_models(ocn_checkpoint):
    first, _, _ = load_ocn(ocn_checkpoint)
    second = variant(ocn_checkpoint, seed=11, n_options=2)
    pool = merge_option_pools([first, second], [ADC])
    assert pool.config.n_options == 5 and pool.config.execution == "hard" and pool.config.tasks == [ADC]
    obs = CraftBatch(6).reset(seeds=range(6), tasks=["ADC"] * 6)
    x = pool.encoder(torch.from_numpy(obs))
    h = torch.randn(5, 6, pool.config.hidden_size)
    with torch.no_grad():
        pooled = pool.core.options(x, h)
        own = [first.core.options(x, h[:3]), second.core.options(x, h[3:])]
    for field in ("logits", "hidden", "end"):
        expected = torch.cat([getattr(out, field) for out in own])
        torch.testing.assert_close(getattr(pooled, field), expected, rtol=1e-6, atol=1e-6, msg=field)
    torch.testing.assert_close(pool.core.option_init, torch.cat([first.core.option_init, second.core.option_init]))
    assert pool.core.controller.n_out == 5 and pool.core.controller_init.shape == (1, pool.config.hidden_size)


def test_pooled_option_runs_alone_like_its_source(ocn_checkpoint):
    """The same option, run alone from its initial state for a few steps, chooses the same greedy
    actions and reports the same terminations in the pool as in its own model."""
    first, _, _ = load_ocn(ocn_checkpoint)
    second = variant(ocn_checkpoint, seed=11, n_options=2)
    pool = merge_option_pools([first, second], [ADC])
    craft = CraftBatch(4)
    obs = craft.reset(seeds=range(4), tasks=["ADC"] * 4)
    source_h = pool_h = None
    restart = torch.ones(4, dtype=torch.bool)
    for _ in range(5):
        state = torch.from_numpy(obs).float()
        action, source_h, end = second.act_with_options(state, torch.full((4,), 1), source_h, restart, greedy=True)
        pool_action, pool_h, pool_end = pool.act_with_options(state, torch.full((4,), 4), pool_h, restart, greedy=True)
        assert torch.equal(action, pool_action)
        torch.testing.assert_close(end, pool_end, rtol=1e-6, atol=1e-6)
        restart = torch.zeros(4, dtype=torch.bool)
        obs, *_ = craft.step(action.long().numpy().ravel())


def test_new_controller_gets_temperature_one_whatever_the_checkpoints(ocn_checkpoint):
    """The imitation phase's temperature (10 here) is not carried into the fresh controller; an
    explicit temperature still is."""
    slow = variant(ocn_checkpoint, seed=3, temperature=10.0)
    assert merge_option_pools([slow], [ADC]).config.temperature == 1.0
    assert merge_option_pools([slow], [ADC], temperature=4.0).config.temperature == 4.0


def test_pools_of_different_sizes_are_refused_with_the_field(ocn_checkpoint):
    first, _, _ = load_ocn(ocn_checkpoint)
    with pytest.raises(ValueError, match=r"hidden_size is 16 vs 8"):
        merge_option_pools([first, variant(ocn_checkpoint, seed=1, hidden_size=8)], [ADC])
    with pytest.raises(ValueError, match=r"mlp_depth is 2 vs 1"):
        merge_option_pools([first, variant(ocn_checkpoint, seed=1, mlp_depth=1)], [ADC])


def test_finetune_writes_the_curve_and_a_checkpoint_that_keeps_the_options(finetuned, ocn_checkpoint,
                                                                          second_checkpoint):
    with open(finetuned / "curve.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert rows and {"frames", "mean_return", "success", "success[ADC]", "success[CAD]"} <= set(rows[0])
    frames = [int(row["frames"]) for row in rows]
    assert frames == sorted(frames) and frames[-1] >= 1500
    assert all(0.0 <= float(row["success"]) <= 1.0 for row in rows)
    assert (finetuned / "curve.png").stat().st_size > 0
    summary = json.loads((finetuned / "finetune.json").read_text())
    assert summary["n_options"] == 5 and summary["tasks"] == [ADC, CAD] and summary["frames"] == frames[-1]

    policy, _, _ = load_ocn(finetuned / "pretrained_model")
    assert policy.config.execution == "hard" and policy.config.tasks == [ADC, CAD]
    sources = [load_ocn(ocn_checkpoint)[0], load_ocn(second_checkpoint)[0]]
    for name, param in policy.core.options.named_parameters():
        assert torch.equal(param, torch.cat([s.core.options.get_parameter(name) for s in sources])), name
    assert torch.equal(policy.core.option_init, torch.cat([s.core.option_init for s in sources]))
    assert not torch.equal(policy.core.controller_init, torch.zeros_like(policy.core.controller_init))


def hard_rollout(checkpoint: Path, codes: list[str], max_steps: int) -> list[torch.Tensor]:
    """Run a finetuned checkpoint through its processors on one map per task code; returns, for each
    step, the rows [E] where the controller chose (all rows, done or not, step together)."""
    policy, preprocessor, postprocessor = load_ocn(checkpoint)
    assert policy.config.execution == "hard"
    craft = CraftBatch(len(codes), max_steps=max_steps)
    obs = craft.reset(seeds=range(len(codes)), tasks=codes)
    tasks = [task_description(parse_task(code)) for code in codes]
    policy.reset()
    decided = []
    while not craft.done.all():
        batch = preprocessor({OBS_STATE: torch.from_numpy(obs).float(), "task": tasks})
        action = postprocessor(policy.select_action(batch))
        assert action.shape == (len(codes), 1)
        decided.append(policy.last_step.decided)
        obs, *_ = craft.step(action.long().numpy().ravel())
    return decided


def decisions_match_frames(out: Path) -> bool:
    """Every iteration of a curve spent exactly one env frame per controller decision."""
    rows = list(csv.DictReader(open(out / "curve.csv")))
    frames = [0] + [int(row["frames"]) for row in rows]
    return all(round(float(row["decisions_per_episode"]) * int(row["episodes"])) == after - before
               for row, (before, after) in zip(rows, itertools.pairwise(frames), strict=True))


def test_finetuned_checkpoint_runs_in_hard_mode_through_its_processors(finetuned):
    decided = hard_rollout(finetuned / "pretrained_model", ["ADC", "CAD", "ADC", "CAD"], max_steps=12)
    assert decided[0].all() and sum(int(rows.sum()) for rows in decided) >= 4
    assert not decisions_match_frames(finetuned)  # OCN's options last several steps


def lerobot_eval_rollout(checkpoint: Path, env: str, task: str, max_steps: int) -> tuple[dict, PreTrainedPolicy]:
    """The path `lerobot-eval --policy.path=CHECKPOINT --env.type=ENV --env.task=TASK` takes, in process
    (without a fresh interpreter's imports): the policy and both processor pairs built as it builds
    them, one batched rollout in 2 envs. Returns the rollout and the policy."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.envs.factory import make_env, make_env_config, make_env_pre_post_processors
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.scripts.lerobot_eval import rollout

    path = str(checkpoint)
    env_cfg = make_env_config(env, task=task, max_steps=max_steps)
    policy_cfg = PreTrainedConfig.from_pretrained(path)
    policy_cfg.pretrained_path = path
    policy = make_policy(cfg=policy_cfg, env_cfg=env_cfg).eval()
    preprocessor, postprocessor = make_pre_post_processors(policy_cfg, pretrained_path=path)
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=policy_cfg)
    vec = make_env(env_cfg, n_envs=2)[env][0]
    try:
        out = rollout(vec, policy, env_preprocessor, env_postprocessor, preprocessor, postprocessor, seeds=[0, 1])
    finally:
        vec.close()
    return out, policy


def test_finetuned_checkpoint_runs_under_lerobot_eval_rollout(finetuned):
    out, policy = lerobot_eval_rollout(finetuned / "pretrained_model", "craft", "ADC", max_steps=15)
    assert out["action"].shape[0] == 2 and out["success"].dtype == torch.bool


def assert_refused(cases: dict[str, list[str]], capsys: pytest.CaptureFixture) -> None:
    """Each command line of `cases` exits with code 2 and one line on stderr that holds its key."""
    for message, argv in cases.items():
        assert main(argv) == 2, message
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1 and err.startswith("ocn-finetune: "), err


def test_bad_input_is_one_line_and_exit_code_2(ocn_checkpoint, tmp_path, capsys):
    incompatible = save_variant(ocn_checkpoint, tmp_path / "small" / "pretrained_model", seed=2, hidden_size=8)
    full = tmp_path / "full"
    full.mkdir()
    (full / "x").write_text("x")
    base = ["--checkpoint", str(ocn_checkpoint), "--frames", "10", "--envs", "2"]
    cases = {
        "unknown subtask letter": [*base, "--tasks", "AXD", "--out", str(tmp_path / "a")],
        "no config.json": ["--checkpoint", str(tmp_path), "--tasks", "ADC", "--out", str(tmp_path / "b")],
        "not an empty folder": [*base, "--tasks", "ADC", "--out", str(full)],
        "envs cannot run 3 tasks": [*base, "--tasks", "ADC,CAD,DCA", "--out", str(tmp_path / "c")],
        "hidden_size is 16 vs 8": [*base, "--checkpoint", str(incompatible), "--tasks", "ADC",
                                   "--out", str(tmp_path / "d")],
        "Give either --checkpoint (one or more) or --flat": [*base, "--flat", "--tasks", "A",
                                                             "--out", str(tmp_path / "e")],
        "Give either --checkpoint": ["--tasks", "A", "--out", str(tmp_path / "f")],
    }
    assert_refused(cases, capsys)
    assert not any((tmp_path / name).exists() for name in "abcdef")


def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for option in ("--checkpoint", "--flat", "--tasks", "--reward", "--frames", "--envs", "--seed", "--out"):
        assert option in text


def test_finetuning_is_seeded(ocn_checkpoint, tmp_path):
    def curve(out: Path) -> list[dict]:
        argv = ["--checkpoint", str(ocn_checkpoint), "--tasks", "ADC", "--frames", "300", "--envs", "4",
                "--max-steps", "20", "--seed", "5", "--out", str(out)]
        assert main(argv) == 0
        rows = list(csv.DictReader(open(out / "curve.csv")))
        return [{key: value for key, value in row.items() if key != "seconds"} for row in rows]

    assert curve(tmp_path / "one") == curve(tmp_path / "two")
    first, _, _ = load_ocn(tmp_path / "one" / "pretrained_model")
    second, _, _ = load_ocn(tmp_path / "two" / "pretrained_model")
    for (name, a), (_, b) in zip(first.state_dict().items(), second.state_dict().items(), strict=True):
        assert torch.equal(a, b), name


def test_an_interrupted_run_resumes_exactly_where_it_stopped(ocn_checkpoint, tmp_path, monkeypatch, capsys):
    """A run stopped in its third iteration and resumed with --resume runs only the iterations left and ends
    with the curve and weights of the same run left alone; other settings, or nothing to resume, are refused."""
    from lerobot_policy_ocn.tools.rl.ppo import PPOTrainer

    def argv(out: Path, *changes: str) -> list[str]:
        return ["--checkpoint", str(ocn_checkpoint), "--tasks", "ADC", "--frames", "400", "--envs", "4",
                "--max-steps", "20", "--seed", "5", "--out", str(out), *changes]

    def curve(out: Path) -> list[dict]:
        return [{key: value for key, value in row.items() if key != "seconds"}
                for row in csv.DictReader(open(out / "curve.csv"))]

    assert main(argv(tmp_path / "straight")) == 0
    iterations = len(curve(tmp_path / "straight"))
    assert iterations >= 4

    update, updates = PPOTrainer.update, []

    def counted_update(self, batch):
        updates.append(1)
        if len(updates) == 3 and interrupting:
            raise KeyboardInterrupt
        return update(self, batch)

    monkeypatch.setattr(PPOTrainer, "update", counted_update)
    interrupting = True
    with pytest.raises(KeyboardInterrupt):
        main(argv(tmp_path / "stopped"))
    assert not (tmp_path / "stopped" / "finetune.json").exists()
    assert len(curve(tmp_path / "stopped")) == 2

    capsys.readouterr()
    assert_refused({
        "seed: 5 there, 6 here": argv(tmp_path / "stopped", "--resume", "--seed", "6"),
        "no run to go on with": argv(tmp_path / "empty", "--resume"),
        "holds a finished run": argv(tmp_path / "straight", "--resume"),
        "--resume goes on with an interrupted run": argv(tmp_path / "stopped"),
    }, capsys)

    interrupting, updates[:] = False, []
    assert main(argv(tmp_path / "stopped", "--resume", "--threads", "1")) == 0
    assert len(updates) == iterations - 2
    assert curve(tmp_path / "stopped") == curve(tmp_path / "straight")
    summary = json.loads((tmp_path / "stopped" / "finetune.json").read_text())
    assert summary["resumed_at_frames"] == int(curve(tmp_path / "straight")[1]["frames"])
    straight, _, _ = load_ocn(tmp_path / "straight" / "pretrained_model")
    resumed, _, _ = load_ocn(tmp_path / "stopped" / "pretrained_model")
    for (name, a), (_, b) in zip(straight.state_dict().items(), resumed.state_dict().items(), strict=True):
        assert torch.equal(a, b), name


# ---- baselines: MoE and HIL checkpoints, flat PPO--------------------------------------------------


def test_finetuning_an_moe_checkpoint_queries_the_controller_at_every_step(ocn_checkpoint, tmp_path):
    moe = save_variant(ocn_checkpoint, tmp_path / "moe" / "pretrained_model", seed=5, hierarchy="moe")
    out = tmp_path / "run"
    argv = ["--checkpoint", str(moe), "--tasks", "ADC,CAD", "--frames", "400", "--envs", "4", "--max-steps", "20",
            "--seed", "2", "--batch-size", "32", "--out", str(out)]
    assert main(argv) == 0
    assert decisions_match_frames(out)
    policy, _, _ = load_ocn(out / "pretrained_model")
    source, _, _ = load_ocn(moe)
    assert policy.config.hierarchy == "moe" and policy.config.n_options == 3
    for name, param in policy.core.options.named_parameters():
        assert torch.equal(param, source.core.options.get_parameter(name)), name
    decided = hard_rollout(out / "pretrained_model", ["ADC", "CAD"], max_steps=10)
    assert len(decided) == 10 and all(rows.all() for rows in decided)


def test_moe_and_ocn_options_are_not_pooled(ocn_checkpoint):
    first, _, _ = load_ocn(ocn_checkpoint)
    with pytest.raises(ValueError, match="hierarchy is 'ocn' vs 'moe'"):
        merge_option_pools([first, variant(ocn_checkpoint, seed=1, hierarchy="moe")], [ADC])


def test_finetuning_a_hil_checkpoint_queries_the_controller_every_skill_length_steps(ocn_checkpoint, tmp_path):
    hil = save_variant(ocn_checkpoint, tmp_path / "hil" / "pretrained_model", seed=5, hierarchy="hil", skill_length=3)
    out = tmp_path / "run"
    argv = ["--checkpoint", str(hil), "--tasks", "ADC,CAD", "--frames", "400", "--envs", "4", "--max-steps", "20",
            "--seed", "2", "--batch-size", "32", "--out", str(out)]
    assert main(argv) == 0
    rows = list(csv.DictReader(open(out / "curve.csv")))
    frames = [0] + [int(row["frames"]) for row in rows]
    for row, (before, after) in zip(rows, itertools.pairwise(frames), strict=True):
        decisions, episodes = round(float(row["decisions_per_episode"]) * int(row["episodes"])), int(row["episodes"])
        assert (after - before) / 3 <= decisions < (after - before) / 3 + episodes  # ceil(frames / 3) each
    policy, _, _ = load_ocn(out / "pretrained_model")
    source, _, _ = load_ocn(hil)
    assert policy.config.hierarchy == "hil" and policy.config.skill_length == 3 and policy.config.n_options == 3
    for name, param in policy.core.options.named_parameters():
        assert torch.equal(param, source.core.options.get_parameter(name)), name
    assert torch.equal(policy.core.option_init, source.core.option_init)
    decided = hard_rollout(out / "pretrained_model", ["ADC", "CAD"], max_steps=10)
    assert [rows.tolist() for rows in decided] == [[t % 3 == 0] * 2 for t in range(10)]


def test_hil_options_of_other_skill_lengths_are_not_pooled(ocn_checkpoint):
    first = variant(ocn_checkpoint, seed=1, hierarchy="hil")
    with pytest.raises(ValueError, match="fixed_skill_length is 4 vs 3"):
        merge_option_pools([first, variant(ocn_checkpoint, seed=2, hierarchy="hil", skill_length=3)], [ADC])
    pool = merge_option_pools([first, variant(ocn_checkpoint, seed=2, hierarchy="hil")], [ADC])
    assert pool.config.hierarchy == "hil" and pool.core.skill_length == 4


def test_flat_ppo_writes_the_same_curve_and_a_checkpoint_of_primitive_actions(tmp_path):
    out = tmp_path / "flat"
    argv = ["--flat", "--tasks", "A,D", "--frames", "400", "--envs", "4", "--max-steps", "10", "--hidden-size", "16",
            "--seed", "1", "--batch-size", "32", "--out", str(out)]
    assert main(argv) == 0
    assert decisions_match_frames(out)
    header = next(csv.reader(open(out / "curve.csv")))
    assert {"frames", "mean_return", "success", "success[A]", "success[D]", "policy_loss"} <= set(header)
    summary = json.loads((out / "finetune.json").read_text())
    assert summary["flat"] and summary["checkpoints"] == [] and summary["hierarchy"] == "moe"
    assert summary["n_options"] == 5 and summary["temperature"] == 1.0
    policy, _, _ = load_ocn(out / "pretrained_model")
    assert policy.config.hidden_size == 16
    assert torch.equal(policy.core.options.b_out[:, 0, :5].argmax(-1), torch.arange(5))
    assert not torch.equal(policy.core.controller_init, torch.zeros_like(policy.core.controller_init))
    decided = hard_rollout(out / "pretrained_model", ["A", "D"], max_steps=6)
    assert all(rows.all() for rows in decided)


def test_controller_report_accounts_for_every_step_and_names_each_options_subtask(finetuned, tmp_path):
    from lerobot_policy_ocn.tools.research.controller_report import main as controller_report

    out = tmp_path / "report.json"
    assert controller_report(["--policy", str(finetuned / "pretrained_model"), "--tasks", "ADC,CAD", "--episodes", "6",
                              "--rollouts", "3", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["tasks"] == ["ADC", "CAD"]
    table = result["option_subtask_success"]
    assert table["subtasks"] == ["A", "D", "C"] and len(table["table"]) == 5  # 3 + 2 pooled options
    best = {i: table["subtasks"][max(range(3), key=lambda j: (row[j], -j))] for i, row in enumerate(table["table"])}
    assert set(result["oracle_controller"]["success_rate"]) == {"ADC", "CAD"}
    for task, report in result["controller"].items():
        decisions = report["decisions"]
        assert sum(d["count"] for d in decisions) == pytest.approx(6 * report["decisions_per_episode"])
        assert all(d["option_serves"] == best[d["option"]] for d in decisions)
        assert {d["subtask"] for d in decisions if d["done"] == 0} == {task[0]}  # the first decision: the first subtask
        lengths = [(report[f"mean_length_{kind}"] or 0.0) for kind in ("success", "failure")]
        successes = round(6 * report["success_rate"])
        steps = lengths[0] * successes + lengths[1] * (6 - successes)
        rounding = 0.005 * sum(d["count"] for d in decisions)  # mean_steps has 2 decimals
        assert sum(d["count"] * d["mean_steps"] for d in decisions) == pytest.approx(steps, abs=rounding)
        detours = sum(d["count"] for d in decisions if d["option_serves"] != d["subtask"])
        assert report["detour_share"] == pytest.approx(detours / sum(d["count"] for d in decisions))
