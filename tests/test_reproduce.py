"""ocn-reproduce reuses a finished run, or a recorded dataset, only when the same settings made it; it plans
the chosen runs and hands `lerobot-train` any train split, however long."""

import json
from pathlib import Path

import pytest

from ocn_data.record_demos import main as record_demos
from tools.reproduce.runs import TrainedRun, check_recorded_as, check_reusable, evaluate_run, record_dataset

from conftest import CRAFT_REPO_ID

COMMAND = "/venv/bin/lerobot-train --policy.type=ocn --dataset.root={root} --steps={steps} --output_dir={root}/out"


def _write_record(run_dir, command):
    run_dir.mkdir(parents=True)
    (run_dir / "record.json").write_text(json.dumps({"train_command": command}))


def test_reuse_ignores_moved_paths(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/old/place", steps=5000))
    check_reusable(tmp_path / "run", COMMAND.format(root="/new/place", steps=5000))


def test_reuse_refuses_other_settings_and_fewer_steps(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --seed=1")
    with pytest.raises(SystemExit, match="trained with other settings"):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --seed=2")
    with pytest.raises(SystemExit, match="trained with other settings"):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=250) + " --seed=1")
    with pytest.raises(SystemExit, match="trained with other settings"):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=9000) + " --seed=2")


def test_a_run_is_extended_to_more_steps_only_under_a_rate_that_ignores_the_run_length(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=5000))
    check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=20000))
    # A rate dropped at a fixed step is the same over the first steps of a longer run.
    step = " --policy.lr_schedule=step --policy.lr_decay_step=3000"
    _write_record(tmp_path / "step", COMMAND.format(root="/data", steps=2000) + step)
    check_reusable(tmp_path / "step", COMMAND.format(root="/data", steps=5000) + step)
    with pytest.raises(SystemExit, match="trained with other settings"):
        check_reusable(tmp_path / "step", COMMAND.format(root="/data", steps=5000) + step.replace("3000", "4000"))
    _write_record(tmp_path / "cosine", COMMAND.format(root="/data", steps=5000) + " --policy.lr_schedule=cosine")
    with pytest.raises(SystemExit, match="only under a learning-rate schedule of constant or step"):
        check_reusable(tmp_path / "cosine", COMMAND.format(root="/data", steps=20000) + " --policy.lr_schedule=cosine")


def test_unfinished_run_is_checked_by_its_command_file(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "train_command.txt").write_text(COMMAND.format(root="/data", steps=250) + " --seed=1\n")
    with pytest.raises(SystemExit, match="--seed=1"):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=250) + " --seed=2")
    check_reusable(tmp_path / "empty", COMMAND.format(root="/data", steps=5000))


def test_reuse_ignores_how_often_a_run_logs_and_saves(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --save_freq=5000 --log_freq=50")
    check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --save_freq=1000 --log_freq=10")


def test_reuse_ignores_argument_order(tmp_path):
    _write_record(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --policy.n_options=3 --seed=1")
    check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --seed=1 --policy.n_options=3")
    with pytest.raises(SystemExit):
        check_reusable(tmp_path / "run", COMMAND.format(root="/data", steps=5000) + " --seed=2 --policy.n_options=3")


def test_a_reused_score_comes_under_the_labels_it_is_asked_with(tmp_path):
    command = COMMAND.format(root="/data", steps=5000) + " --seed=4"
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "record.json").write_text(json.dumps(
        {"seed": 1, "restarts": {"chosen_seed": 4}, "train_command": command, "scores": {"nmi": 0.3}}))
    trained = TrainedRun(tmp_path / "run" / "checkpoint", command, 762.0)
    labels = {"seed": 1, "restarts": {"chosen_seed": 4, "train_wall_s": 1900.0}}
    # No ocn-eval runs (the checkpoint does not exist): the record is reused, with this call's labels.
    record = evaluate_run(tmp_path / "run", trained, tmp_path / "data", "local/tiny", 1, labels)
    assert record["restarts"] == labels["restarts"] and record["scores"] == {"nmi": 0.3}
    assert record["train_wall_s"] == 762.0


def _recording(root, seed=0):
    return ["--env", "craft", "--tasks", "AC", "--episodes-per-task", "2", "--root", str(root), "--repo-id",
            "local/tiny", "--seed", str(seed)]


def test_a_dataset_is_reused_only_when_recorded_with_the_same_settings(tmp_path, capsys):
    data = tmp_path / "data"
    assert record_demos(_recording(data)) == 0
    record_dataset(data, "AC", "local/tiny", 2, 0)
    assert f"reusing the dataset in {data}" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="recorded by: record_demos .*--seed 0"):
        record_dataset(data, "AC", "local/tiny", 2, 1)
    with pytest.raises(SystemExit, match="--episodes-per-task 3"):
        record_dataset(data, "AC", "local/tiny", 3, 0)
    with pytest.raises(SystemExit, match="--dart-noise 0.1"):
        record_dataset(data, "AC", "local/tiny", 2, 0, dart_noise=0.1)
    noisy = tmp_path / "noisy"
    record_dataset(noisy, "AC", "local/tiny", 2, 0, dart_noise=0.1)
    capsys.readouterr()
    record_dataset(noisy, "AC", "local/tiny", 2, 0, dart_noise=0.1)
    assert f"reusing the dataset in {noisy}" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="recorded by: record_demos .*--dart-noise 0.1"):
        record_dataset(noisy, "AC", "local/tiny", 2, 0)


def test_a_moved_dataset_is_still_reused_but_one_of_unknown_origin_is_not(tmp_path):
    assert record_demos(_recording(tmp_path / "old")) == 0
    (tmp_path / "old").rename(tmp_path / "new")
    check_recorded_as(tmp_path / "new", _recording(tmp_path / "new"))
    (tmp_path / "new" / "meta" / "ocn_recording.json").unlink()
    with pytest.raises(SystemExit, match="no record_demos session"):
        check_recorded_as(tmp_path / "new", _recording(tmp_path / "new"))


def test_imitation_runs_under_non_default_study_settings_get_their_own_folder_and_policy_settings():
    from tools.reproduce import imitation

    def parsed(*argv):
        parser = imitation.argparse.ArgumentParser()
        imitation.add_parser(parser.add_subparsers())
        return parser.parse_args(["imitation-s1", *argv])

    # The study's defaults are its S1 recipe; every run under them lives in the recipe's folder.
    recipe = parsed()
    assert (recipe.window_size, recipe.dart_noise) == (32, 0.1)
    assert imitation.study_overrides(recipe) == {"usage_balance": 1.0, "window_start": "packed",
                                                 "expected_nll_weight": 0.1}
    assert imitation.run_dir(Path("w"), imitation.VARIANTS[0], 1, imitation.study_overrides(recipe)) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0_packed_expected_nll_weight0.1/seed1")

    def overrides(*argv):
        """The settings that name a run's folder, counted from the study's defaults before its recipe."""
        return imitation.study_overrides(parsed("--window-start", "episode", "--expected-nll-weight", "0", *argv))

    paper = ("--usage-balance", "0")
    assert overrides(*paper) == overrides(*paper, "--lr-schedule", "constant", "--obs-encoder", "craft") == {}
    assert overrides() == {"usage_balance": 1.0}  # the study's own default
    assert overrides(*paper, "--lr-schedule", "cosine") == {"lr_schedule": "cosine"}
    both = overrides(*paper, "--obs-encoder", "craft_full_view", "--lr-schedule", "cosine")
    assert both == {"lr_schedule": "cosine", "obs_encoder": "craft_full_view"}
    main = imitation.VARIANTS[0]
    assert imitation.run_dir(Path("w"), main, 1) == Path("w/imitation_s1/3options_T10/seed1")
    assert imitation.run_dir(Path("w"), main, 1, overrides(*paper, "--lr-schedule", "cosine")) == Path(
        "w/imitation_s1/3options_T10_cosine/seed1")
    assert imitation.run_dir(Path("w"), main, 2, both) == Path(
        "w/imitation_s1/3options_T10_cosine_craft_full_view/seed2")
    assert imitation.run_dir(Path("w"), main, 1, overrides()) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0/seed1")
    assert overrides("--optimizer-lr", "0.001") == {"usage_balance": 1.0}
    faster = overrides("--optimizer-lr", "0.002")
    assert faster == {"usage_balance": 1.0, "optimizer_lr": 0.002}
    assert imitation.run_dir(Path("w"), main, 1, faster) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0_optimizer_lr0.002/seed1")
    decayed = overrides("--weight-decay", "1.0", "--window-start", "packed")
    assert decayed == {"usage_balance": 1.0, "optimizer_weight_decay": 1.0, "window_start": "packed"}
    assert imitation.run_dir(Path("w"), main, 1, decayed) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0_optimizer_weight_decay1.0_packed/seed1")
    assert overrides("--usage-balance-options", "0") == {"usage_balance": 1.0}
    spare = overrides("--usage-balance-options", "3")
    assert spare == {"usage_balance": 1.0, "usage_balance_options": 3}
    assert imitation.run_dir(Path("w"), imitation.VARIANTS[2], 1, spare) == Path(
        "w/imitation_s1/6options_T10_usage_balance1.0_usage_balance_options3/seed1")
    words = imitation.balance_options_words
    assert words({"usage_balance_options": 3}) == " over 3 options' worth of usage (`--policy.usage_balance_options`)"
    assert words({}) == words({"usage_balance_options": 0}) == ""
    counted = overrides("--usage-balance-options", "3", "--usage-balance-source", "posterior")
    assert counted == {"usage_balance": 1.0, "usage_balance_options": 3, "usage_balance_source": "posterior"}
    assert imitation.run_dir(Path("w"), imitation.VARIANTS[2], 1, counted) == Path(
        "w/imitation_s1/6options_T10_usage_balance1.0_usage_balance_options3_posterior/seed1")
    assert words(counted) == (" over 3 options' worth of usage (`--policy.usage_balance_options`), usage counted as "
                              "the options' posterior shares (`--policy.usage_balance_source`)")
    charged = overrides("--explained-termination-cost", "0.3")
    assert charged == {"usage_balance": 1.0, "explained_termination_cost": 0.3}
    assert imitation.run_dir(Path("w"), main, 1, charged) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0_explained_termination_cost0.3/seed1")
    assert imitation.cost_words({"explained_termination_cost": 0.3}) == (
        ", explained-termination cost 0.3 (`--policy.explained_termination_cost`)")
    switching = overrides("--switch-cost", "0.3")
    assert switching == {"usage_balance": 1.0, "switch_cost": 0.3}
    assert imitation.run_dir(Path("w"), main, 1, switching) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0_switch_cost0.3/seed1")
    assert imitation.cost_words({"explained_termination_cost": 0.3, "switch_cost": 0.5}) == (
        ", explained-termination cost 0.3 (`--policy.explained_termination_cost`), "
        "option-switch cost 0.5 (`--policy.switch_cost`)")
    assert imitation.cost_words({}) == ""
    expected = overrides("--expected-nll-weight", "0.1")
    assert expected == {"usage_balance": 1.0, "expected_nll_weight": 0.1}
    assert imitation.run_dir(Path("w"), main, 1, expected) == Path(
        "w/imitation_s1/3options_T10_usage_balance1.0_expected_nll_weight0.1/seed1")
    assert imitation.cost_words(expected) == ", expected NLL weighted 0.1 (`--policy.expected_nll_weight`)"


def test_imitation_runs_can_be_limited_to_chosen_variants():
    from tools.reproduce import imitation

    def planned(*argv):
        parser = imitation.argparse.ArgumentParser()
        imitation.add_parser(parser.add_subparsers())
        args = parser.parse_args(["imitation-s1", *argv])
        return [(imitation._slug(variant.name), seed) for variant, seed in imitation.planned_runs(args)]

    assert planned("--seeds", "2") == [("3options_T10", 1), ("3options_T10", 2), ("2options_T10", 1),
                                       ("6options_T10", 1), ("3options_T1", 1)]
    assert planned("--seeds", "2", "--ablation-seeds", "0") == [("3options_T10", 1), ("3options_T10", 2)]
    assert planned("--variants", "6options_T10,3options_T10", "--seeds", "1", "--ablation-seeds", "2") == [
        ("3options_T10", 1), ("6options_T10", 1), ("6options_T10", 2)]
    assert planned("--first-seed", "3", "--seeds", "2", "--ablation-seeds", "0") == [("3options_T10", 3),
                                                                                     ("3options_T10", 4)]
    with pytest.raises(SystemExit, match="unknown \\['7options'\\]"):
        planned("--variants", "7options")


def test_a_train_split_too_long_for_one_argument_reaches_lerobot_train_through_a_file(craft_dataset, tmp_path,
                                                                                     monkeypatch):
    import subprocess

    from ocn_data.episodes_table import split_episodes
    from tools.reproduce import runs
    from tools.reproduce.runs import TrainSettings, train_command

    monkeypatch.setattr(runs, "MAX_SPLIT_ARGUMENT", 10)  # every split counts as too long
    settings = TrainSettings(steps=1, batch_size=4, window_size=24, num_workers=0, policy={"hidden_size": 8})
    command = train_command(settings, craft_dataset, CRAFT_REPO_ID, tmp_path / "train", 1, {})
    assert command[4] == f"--config_path={tmp_path / 'train_split.json'}"
    assert not any(word.startswith("--dataset.episodes") for word in command)
    subprocess.run(command, check=True, capture_output=True)
    saved = json.loads(
        (tmp_path / "train" / "checkpoints" / "last" / "pretrained_model" / "train_config.json").read_text())
    assert saved["dataset"]["episodes"] == [int(e) for e in split_episodes(craft_dataset, "train")]
    assert saved["dataset"]["repo_id"] == CRAFT_REPO_ID and saved["policy"]["hidden_size"] == 8


def test_a_run_lists_the_machines_that_trained_it(tmp_path):
    from tools.reproduce.runs import machine_name, trained_on

    assert trained_on(tmp_path) == []
    invocations = [{"from_step": 0, "wall_s": 1.0}, {"from_step": 1000, "wall_s": 2.0, "machine": "X (2 cores)"},
                   {"from_step": 2000, "wall_s": 2.0, "machine": "X (2 cores)"}, {"from_step": 3000, "wall_s": 2.0,
                                                                                  "machine": machine_name()}]
    (tmp_path / "train_wall_s.json").write_text(json.dumps({"invocations": invocations, "total": 7.0}))
    assert trained_on(tmp_path) == ["not recorded", "X (2 cores)", machine_name()]


def test_a_run_whose_first_steps_were_not_timed_says_from_which_step_its_wall_time_counts(tmp_path):
    from tools.reproduce.report import train_time_words
    from tools.reproduce.runs import timed_from_step

    assert timed_from_step(tmp_path) == 0
    invocations = [{"from_step": 2000, "wall_s": 3187.7}, {"from_step": 4000, "wall_s": 10.0}]
    (tmp_path / "train_wall_s.json").write_text(json.dumps({"invocations": invocations, "total": 3197.7}))
    assert timed_from_step(tmp_path) == 2000
    assert train_time_words({"train_wall_s": 3197.7, "train_timed_from_step": 2000}) == "3198 (steps 2000+)"
    assert train_time_words({"train_wall_s": 812.4, "train_timed_from_step": 0}) == "812"
    assert train_time_words({"train_wall_s": None}) == "not timed"


def _imitation_args(results, *argv):
    from tools.reproduce import imitation

    parser = imitation.argparse.ArgumentParser()
    imitation.add_parser(parser.add_subparsers())
    args = parser.parse_args(["imitation-s1", "--results", str(results), *argv])
    args.argv = ["imitation-s1", *argv]
    return args


def _imitation_record(variant, seed, nmi):
    scores = {"f1_tol0": 0.9, "f1_tol1": 0.9, "align_acc": 0.9, "nmi": nmi, "diagonal": [0.9, 0.9, 0.9],
              "diagonal_mean": 0.9, "off_diagonal_max": 0.1, "mean_success_rate": 0.9,
              "success_rate": {"AC": 0.9, "CD": 0.9, "DA": 0.9}}
    return {"variant": variant, "seed": seed, "train_wall_s": 60.0, "scores": scores}


def test_imitation_keeps_the_earlier_runs_of_the_same_study_and_refuses_another_studys_file(tmp_path):
    from tools.reproduce import imitation

    earlier_args = _imitation_args(tmp_path, "--seeds", "2", "--variants", "3options_T10")
    earlier = [_imitation_record("3 options, T=10", 1, 0.9), _imitation_record("3 options, T=10", 2, 0.8)]
    imitation.write_results(earlier_args, [{"made_by": {"command": "ocn-reproduce first", "date": "d",
                                                         "machine": imitation.provenance(earlier_args)["machine"]},
                                            **r} for r in earlier], 2, 1.0)

    args = _imitation_args(tmp_path, "--seeds", "2", "--variants", "3options_T10,6options_T10")
    kept = imitation.earlier_runs(args, imitation.planned_runs(args))
    assert kept == []  # this invocation remakes both main seeds
    args = _imitation_args(tmp_path, "--variants", "6options_T10")
    kept = imitation.earlier_runs(args, imitation.planned_runs(args))
    assert [(r["variant"], r["seed"], r["made_by"]["command"]) for r in kept] == [
        ("3 options, T=10", 1, "ocn-reproduce first"), ("3 options, T=10", 2, "ocn-reproduce first")]

    new = {"made_by": {"command": "ocn-reproduce second", "date": "e", "machine": kept[0]["made_by"]["machine"]},
           **_imitation_record("6 options, T=10", 1, 0.7)}
    result = imitation.write_results(args, imitation.in_study_order([new, *kept]), 3, 1.0)
    assert [(r["variant"], r["seed"]) for r in result["runs"]] == [
        ("3 options, T=10", 1), ("3 options, T=10", 2), ("6 options, T=10", 1)]
    assert result["summary"]["3 options, T=10"]["nmi"]["mean"] == pytest.approx(0.85)
    assert {c["check"]: c["holds"] for c in result["must_show"]}["6 options, T=10: NMI >= 0.9"] is False
    text = (tmp_path / "imitation_s1.md").read_text()
    assert "| `ocn-reproduce first` | d |" in text and "3 options, T=10 seed 1; 3 options, T=10 seed 2 |" in text
    assert "| `ocn-reproduce second` | e |" in text and "6 options, T=10 seed 1 |" in text

    with pytest.raises(SystemExit, match="other settings \\(steps 5000 there, 250 here\\)"):
        imitation.earlier_runs(_imitation_args(tmp_path, "--steps", "250"), [])

    # A file written before --usage-balance existed holds runs of the paper's loss (a balance of 0).
    path = tmp_path / "imitation_s1.json"
    written = json.loads(path.read_text())
    del written["settings"]["usage_balance"]
    path.write_text(json.dumps(written))
    with pytest.raises(SystemExit, match="other settings \\(usage_balance 0.0 there, 1.0 here\\)"):
        imitation.earlier_runs(args, [])
    assert len(imitation.earlier_runs(_imitation_args(tmp_path, "--usage-balance", "0"), [])) == 3
