"""ocn-reproduce s1/s2 end to end on a tiny budget: clone, finetune, results, reuse."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tools.reproduce.finetune import METHODS, SETTINGS, finetune_command, markdown, must_show, task_labels
from tools.reproduce.runs import TrainedRun

TINY = ["--seeds", "1", "--steps", "2", "--batch-size", "8", "--num-workers", "0", "--episodes-per-task", "12",
        "--frames", "1500", "--envs", "8"]


def _reproduce(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("ocn-reproduce")
    command = [str(script), "s1", *TINY, "--workdir", str(tmp_path / "work"),
               "--results", str(tmp_path / "results"), *extra]
    return subprocess.run(command, capture_output=True, text=True, timeout=600)


def test_s1_clones_finetunes_and_writes_results_then_reuses(tmp_path):
    # HIL's runs go through the same code as MoE's (only the clone's overrides differ), so the tiny end
    # to end run leaves it out for time; test_hil_is_cloned_as_hil_and_checked_against_ocn covers it.
    done = _reproduce(tmp_path, "--rewards", "sparse", "--methods", "ocn,moe,flat")
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads((tmp_path / "results" / "finetune_s1.json").read_text())
    assert result["runs_finished"] == result["runs_planned"] == 3
    assert set(result["summary"]) == {"OCN | sparse", "MoE | sparse", "flat PPO | sparse"}
    assert [r["summary"]["n_options"] for r in result["runs"]] == [3, 3, 5]
    row = result["summary"]["OCN | sparse"]
    assert set(row["at_budget"]) == {"mean_return", "success", "success[ADC]", "success[CAD]", "success[DCA]"}
    assert len(row["curves"]["success"]["mean"]) == len(row["curve_frames"])
    assert row["curve_frames"][-1] >= 1500
    assert all(0.0 <= row["at_budget"][k]["mean"] <= 1.0 for k in ("success", "success[ADC]"))
    assert [c["check"] for c in result["must_show"]][0].startswith("OCN, sparse: success >= 0.9")
    assert (tmp_path / "results" / "finetune_s1.png").stat().st_size > 0
    table = (tmp_path / "results" / "finetune_s1.md").read_text()
    assert all(f"| {name} | sparse | 1 |" in table for name in ("OCN", "MoE", "flat PPO"))
    checks = {c["check"] for c in result["must_show"]}
    assert {"sparse: MoE's mean success below OCN's", "sparse: flat PPO's mean success below OCN's"} <= {
        c.split(" (")[0] for c in checks}
    # S1's OCN clone is the imitation study's main-variant run, shared by both reproductions.
    assert (tmp_path / "work" / "imitation_s1" / "3options_T10" / "seed1" / "train").is_dir()

    again = _reproduce(tmp_path, "--rewards", "sparse", "--methods", "ocn,moe,flat")
    work = [line for line in again.stdout.splitlines() if line.startswith(("training ", "resuming ", "finetuning "))]
    assert again.returncode == 0 and not work, work

    # Another budget or number of envs is another folder: every run stays.
    for setting in (["--frames", "3000"], ["--envs", "4"]):
        other = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse", *setting)
        assert other.returncode == 0, other.stderr[-2000:]
    finetuned = tmp_path / "work" / "finetune_s1"
    assert {"ocn_sparse_frames1500_envs8", "ocn_sparse_frames3000_envs8", "ocn_sparse_frames1500_envs4"} <= {
        path.name for path in finetuned.iterdir()}
    # A folder holding another command's run (one made before a setting entered the folder names) is refused.
    command_file = finetuned / "ocn_sparse_frames1500_envs8" / "seed1" / "finetune_command.txt"
    command_file.write_text(command_file.read_text().replace("--envs 8", "--envs 16"))
    refused = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse")
    assert refused.returncode != 0 and "another command" in refused.stderr


def test_s1_clone_trained_on_or_under_other_settings_is_finetuned_again(tmp_path):
    # Apart from the end-to-end test above, so that the two can run on two pytest workers (-n 2).
    first = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse")
    assert first.returncode == 0, first.stderr[-2000:]
    step = tmp_path / "work" / "imitation_s1" / "3options_T10" / "seed1" / "train" / "checkpoints" / "last" / (
        "training_state/training_step.json")
    assert json.loads(step.read_text())["step"] == 2

    # A finetuning stopped before it wrote its summary (here after its last PPO iteration) goes on from
    # its snapshot with ocn-finetune --resume, instead of starting again.
    run = tmp_path / "work" / "finetune_s1" / "ocn_sparse_frames1500_envs8" / "seed1" / "run"
    curve = (run / "curve.csv").read_text()
    (run / "finetune.json").unlink()
    resumed = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse")
    assert resumed.returncode == 0 and "from where it stopped" in resumed.stdout, resumed.stderr[-2000:]
    summary = json.loads((run / "finetune.json").read_text())
    assert summary["resumed_at_frames"] == summary["frames"] and (run / "curve.csv").read_text() == curve

    # More clone steps extend the clone from its last checkpoint, and its finetuning is made again.
    longer = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse", "--steps", "4")
    assert longer.returncode == 0, longer.stderr[-2000:]
    run_dir = tmp_path / "work" / "imitation_s1" / "3options_T10" / "seed1"
    assert "from step 2" in longer.stdout and "its clones were trained on since" in longer.stdout
    assert json.loads(step.read_text())["step"] == 4
    timing = json.loads((run_dir / "train_wall_s.json").read_text())
    assert [invocation["from_step"] for invocation in timing["invocations"]] == [0, 2]
    run = json.loads((tmp_path / "results" / "finetune_s1.json").read_text())["runs"][0]
    assert "--steps=4" in run["clone_commands"][0]

    # A workdir moved elsewhere extends its runs where they now lie, though their checkpoints' configs
    # name the folders they were trained in: the original is left at its steps.
    moved = tmp_path / "moved"
    shutil.copytree(tmp_path / "work", moved, symlinks=True)
    extended = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse", "--steps", "6", "--workdir", str(moved))
    assert extended.returncode == 0, extended.stderr[-2000:]
    moved_step = moved / step.relative_to(tmp_path / "work")
    assert json.loads(moved_step.read_text())["step"] == 6 and json.loads(step.read_text())["step"] == 4

    # Under the usage balance the OCN clone is the imitation study's balanced run, and both the clone
    # and its finetuning get folders of their own beside the paper-loss ones.
    balanced = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse", "--usage-balance", "1.0")
    assert balanced.returncode == 0, balanced.stderr[-2000:]
    clone_dir = tmp_path / "work" / "imitation_s1" / "3options_T10_usage_balance1.0" / "seed1"
    assert "--policy.usage_balance=1.0" in (clone_dir / "train_command.txt").read_text()
    balanced_out = tmp_path / "work" / "finetune_s1" / "ocn_sparse_usage_balance1.0_frames1500_envs8" / "seed1"
    assert (balanced_out / "run" / "finetune.json").exists()
    assert json.loads(step.read_text())["step"] == 4  # the paper-loss clone is left as it was

    # --settle-steps settles the OCN clone as imitation-s1 does (into the same run's settle folder), and
    # the finetuning over the settled options gets a folder of its own.
    settled = _reproduce(tmp_path, "--methods", "ocn", "--rewards", "sparse", "--usage-balance", "1.0",
                         "--settle-steps", "2")
    assert settled.returncode == 0, settled.stderr[-2000:]
    assert "--policy.termination_penalty=log" in (clone_dir / "settle" / "train_command.txt").read_text()
    out = (tmp_path / "work" / "finetune_s1"
           / "ocn_sparse_usage_balance1.0_settle_steps2_settle_cost0.1_frames1500_envs8" / "seed1")
    assert (out / "run" / "finetune.json").exists()
    result = json.loads((tmp_path / "results" / "finetune_s1.json").read_text())
    assert " && " in result["runs"][0]["clone_commands"][0]
    assert "OCN's: then a settling phase of 2 steps" in (tmp_path / "results" / "finetune_s1.md").read_text()


def test_unknown_method_is_refused(tmp_path):
    done = _reproduce(tmp_path, "--methods", "ocn,options")
    assert done.returncode != 0 and "unknown method or reward ['options']" in done.stderr


def test_s2_pools_the_options_of_both_cloned_models(tmp_path):
    import argparse

    args = argparse.Namespace(frames=100, envs=4, entropy=0.001, gamma=0.97)
    clones = [TrainedRun(tmp_path / name / "pretrained_model", "", None) for name in ("ab", "cd")]
    command = finetune_command(args, SETTINGS["s2"], METHODS[0], "sparse", 1, clones, tmp_path / "out")
    assert ([command[i + 1] for i, word in enumerate(command) if word == "--checkpoint"]
            == [str(c.checkpoint) for c in clones])
    assert command[command.index("--tasks") + 1] == "BADC,ACBD,CABD"
    assert command[command.index("--temperature") + 1] == "1"  # spelled out: older default runs are refused
    assert "--entropy" not in command  # the paper's bonus: runs made before it could change are reused


def test_a_non_default_entropy_bonus_envs_or_discount_reach_ocn_finetune_and_get_folders_of_their_own(tmp_path):
    import argparse

    from tools.reproduce.finetune import ppo_suffix, study_settings

    args = argparse.Namespace(frames=1_500_000, default_frames=300_000, envs=4, entropy=0.01, gamma=0.99,
                              default_gamma=0.97)
    command = finetune_command(args, SETTINGS["s2"], METHODS[0], "sparse", 1, [], tmp_path / "out")
    assert command[command.index("--entropy") + 1] == "0.01"
    assert command[command.index("--envs") + 1] == "4"
    assert command[command.index("--gamma") + 1] == "0.99"
    assert ppo_suffix(args) == "_frames1500000_entropy0.01_envs4_gamma0.99"
    default = argparse.Namespace(frames=300_000, default_frames=300_000, entropy=0.001, envs=64, gamma=0.97,
                                 default_gamma=0.97)
    assert ppo_suffix(default) == ""
    assert "--gamma" not in finetune_command(default, SETTINGS["s1"], METHODS[0], "sparse", 1, [], tmp_path / "out")
    # Files from before the flags were added ran at the paper's values.
    assert study_settings({"setting": "s1", "settings": {"frames": 300_000}})["entropy"] == 0.001
    assert study_settings({"setting": "s1", "settings": {"frames": 300_000}})["gamma"] == 0.97
    # and cloned the setting's number of options.
    assert study_settings({"setting": "s2", "settings": {"frames": 300_000}})["n_options"] == 2


def test_hil_is_cloned_as_hil_and_checked_against_ocn(tmp_path):
    import argparse

    hil = {method.key: method for method in METHODS}["hil"]
    assert hil.name == "HIL" and hil.overrides == {"hierarchy": "hil"}
    args = argparse.Namespace(frames=100, envs=4, entropy=0.001, gamma=0.97)
    clone = TrainedRun(tmp_path / "hil" / "pretrained_model", "", None)
    command = finetune_command(args, SETTINGS["s1"], hil, "sparse", 1, [clone], tmp_path / "out")
    assert "--flat" not in command and command[command.index("--checkpoint") + 1] == str(clone.checkpoint)

    def row(success: float, mean_return: float) -> dict:
        values = {"success": success, "mean_return": mean_return,
                  **{f"success[{task}]": success for task in SETTINGS["s1"].tasks.split(",")}}
        return {"at_budget": {key: {"mean": value} for key, value in values.items()}}

    summary = {f"{name} | {reward}": row(success, 2 * success) for reward in ("sparse", "dense")
               for name, success in (("OCN", 0.95), ("HIL", 0.97), ("MoE", 0.1))}

    def named_checks() -> dict:
        return {check["check"].split(" (")[0]: check for check in must_show(SETTINGS["s1"], summary)}

    checks = named_checks()
    assert not checks["sparse: HIL's mean success below OCN's"]["holds"]
    assert checks["sparse: MoE's mean success below OCN's"]["holds"]
    assert checks["dense: OCN's return at least twice the best baseline's"]["value"] == pytest.approx(0.95 / 0.97)
    assert "dense: twice the best baseline's return within reach at some budget" not in checks  # no curves

    # With the curves: no S1 return exceeds 3, and MoE never returned below 1.6 on its mean curve.
    summary["MoE | dense"]["curves"] = {"mean_return": {"mean": [1.7, 1.6, 2.2]}}
    summary["HIL | dense"]["curves"] = {"mean_return": {"mean": [0.4, 1.9, 2.5]}}
    reach = named_checks()["dense: twice the best baseline's return within reach at some budget"]
    assert reach["value"] == pytest.approx(3 / 1.6) and not reach["holds"]
    summary["MoE | dense"]["curves"]["mean_return"]["mean"][1] = 1.4
    reach = named_checks()["dense: twice the best baseline's return within reach at some budget"]
    assert reach["value"] == pytest.approx(3 / 1.4) and reach["holds"]


def test_compile_is_cloned_with_its_own_defaults_and_finetuned_over_its_decoders(craft_dataset, tmp_path):
    import argparse

    from tools.reproduce.finetune import clone_settings
    from tools.reproduce.runs import train_command

    method = {method.key: method for method in METHODS}["compile"]
    assert method.name == "compILE" and method.policy_type == "compile"
    args = argparse.Namespace(steps=2, batch_size=8, window_size=24, num_workers=0, threads=1,
                              controller_lr_scale=0.1, frames=100, envs=4, entropy=0.001, gamma=0.97)
    settings, overrides = clone_settings(args, SETTINGS["s2"], method)
    command = train_command(settings, craft_dataset, "local/craft_small", tmp_path / "train", 1, overrides)
    assert command[1] == "--policy.type=compile" and "--policy.window_size=24" in command
    ocn_only = ("--policy.n_options", "--policy.temperature", "--policy.controller_lr_scale")
    assert not any(word.startswith(ocn_only) for word in command)
    clones = [TrainedRun(tmp_path / name / "pretrained_model", "", None) for name in ("ab", "cd")]
    command = finetune_command(args, SETTINGS["s2"], method, "sparse", 1, clones, tmp_path / "out")
    checkpoints = [command[i + 1] for i, word in enumerate(command) if word == "--checkpoint"]
    assert "--flat" not in command and checkpoints == [str(clone.checkpoint) for clone in clones]


def _s1_results_markdown(methods: list[str], settings: dict | None = None) -> str:
    """S1's results file for one sparse seed of each of `methods` (placeholder figures)."""
    setting = SETTINGS["s1"]
    stat = {"mean": 0.5, "std": 0.0}
    at_budget = {key: stat for key in ("mean_return", "success", *(f"success[{t}]" for t in task_labels(setting)))}
    summary = {f"{name} | sparse": {"method": name, "reward": "sparse", "seeds": [1], "at_budget": at_budget,
                                    "frames_per_s": 100.0} for name in methods}
    result = {"setting": setting.name, "command": "ocn-reproduce s1", "date": "2025-01-01",
              "machine": {"cpu": "cpu", "cores": 2}, "settings": {"frames": 100, "envs": 4, **(settings or {})},
              "runs_finished": 2, "runs_planned": 2, "wall_s": 60.0, "summary": summary, "must_show": []}
    return markdown(result)


def test_results_header_notes_compiles_options_only_when_compile_ran():
    def header(methods: list[str]) -> str:
        return _s1_results_markdown(methods).split("## Checks")[0]

    note = "3 options per cloned model (compILE: one per latent category of its decoder), cloned by"
    assert note in header(["OCN", "compILE"])
    assert "3 options per cloned model, cloned by" in header(["OCN", "MoE"]) and "compILE" not in header(["OCN", "MoE"])
    assert ("3 options per cloned model (OMPN: none, its whole network is finetuned), cloned by"
            in header(["OCN", "OMPN"]))


def test_ompn_is_cloned_with_its_own_defaults_finetuned_whole_in_s1_only_and_checked_against_ocn(craft_dataset,
                                                                                                tmp_path):
    import argparse

    from tools.reproduce import main
    from tools.reproduce.finetune import add_parsers, clone_settings
    from tools.reproduce.runs import train_command

    ompn = {method.key: method for method in METHODS}["ompn"]
    args = argparse.Namespace(steps=2, batch_size=8, window_size=24, num_workers=0, threads=1,
                              controller_lr_scale=0.1, frames=100, envs=4, entropy=0.001, gamma=0.97)
    settings, overrides = clone_settings(args, SETTINGS["s1"], ompn)
    command = train_command(settings, craft_dataset, "local/craft_small", tmp_path / "train", 1, overrides)
    assert command[1] == "--policy.type=ompn" and "--policy.window_size=24" in command
    assert not any(word.startswith(("--policy.n_options", "--policy.temperature", "--policy.controller_lr_scale"))
                   for word in command)
    clone = TrainedRun(tmp_path / "ompn" / "pretrained_model", "", None)
    command = finetune_command(args, SETTINGS["s1"], ompn, "sparse", 1, [clone], tmp_path / "out")
    assert "--flat" not in command and command[command.index("--checkpoint") + 1] == str(clone.checkpoint)
    assert "--temperature" not in command  # ocn-finetune refuses it for OMPN, which has no controller
    flat = {method.key: method for method in METHODS}["flat"]
    assert "--temperature" not in finetune_command(args, SETTINGS["s1"], flat, "sparse", 1, [], tmp_path / "flat")

    ocn = {key: {"mean": 0.5} for key in ("success", *(f"success[{t}]" for t in task_labels(SETTINGS["s1"])))}
    summary = {"OCN | sparse": {"at_budget": ocn}, "OMPN | sparse": {"at_budget": {"success": {"mean": 0.7}}}}
    checks = {check["check"].split(" (")[0]: check["holds"] for check in must_show(SETTINGS["s1"], summary)}
    assert checks["sparse: OMPN's mean success below OCN's"] is False

    parser = argparse.ArgumentParser()
    add_parsers(parser.add_subparsers(dest="experiment"))
    assert "ompn" in parser.parse_args(["s1"]).methods and "ompn" not in parser.parse_args(["s2"]).methods
    with pytest.raises(SystemExit, match="OMPN cannot pool the skills of several cloned models"):
        main(["s2", "--methods", "ocn,ompn", "--workdir", str(tmp_path / "work"), "--results", str(tmp_path / "r")])
    assert not (tmp_path / "work").exists()


def test_packed_clones_load_the_packed_view_in_folders_of_their_own_and_share_imitations_run(tmp_path):
    import argparse

    from tools.reproduce import dial, finetune, imitation, parsing

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    for module in (imitation, parsing, dial):
        module.add_parser(sub)
    finetune.add_parsers(sub)

    def parsed(*words: str) -> argparse.Namespace:
        return parser.parse_args([*words, "--workdir", str(tmp_path), "--usage-balance", "1.0"])

    methods = {method.key: method for method in METHODS}
    packed, windows = parsed("s2", "--window-start", "packed"), parsed("s2")
    for key in ("ocn", "moe", "hil", "compile"):
        assert finetune.clone_settings(packed, SETTINGS["s2"], methods[key])[1]["window_start"] == "packed"
        assert "window_start" not in finetune.clone_settings(windows, SETTINGS["s2"], methods[key])[1]
    assert finetune.clone_dir(packed, SETTINGS["s2"], methods["moe"], "craft_s2_ab", 1) == (
        tmp_path / "clone" / "craft_s2_ab" / "moe_usage_balance1.0_packed" / "seed1")
    assert (finetune.clone_dir(packed, SETTINGS["s2"], methods["compile"], "craft_s2_ab", 1).parent.name
            == "compile_packed")
    assert (finetune.clone_dir(windows, SETTINGS["s2"], methods["moe"], "craft_s2_ab", 1).parent.name
            == "moe_usage_balance1.0")
    assert finetune.clone_study_suffix(packed, methods["flat"]) == ""

    # S1's OCN clone is the run that imitation-s1 trains under the same balance, loading and loss (the
    # study's recipe adds the expected NLL, which s1 does not by default).
    study = parsed("imitation-s1", "--window-start", "packed", "--expected-nll-weight", "0")
    shared = imitation.run_dir(tmp_path, imitation.VARIANTS[0], 1, imitation.study_overrides(study))
    assert finetune.clone_dir(parsed("s1", "--window-start", "packed"), SETTINGS["s1"], methods["ocn"],
                              "craft_s1", 1) == shared
    assert shared.parent.name == "3options_T10_usage_balance1.0_packed"
    assert (parsing.run_dir(parsed("parsing-s1", "--window-start", "packed"), methods["ompn"], 1).parent.name
            == "ompn_packed")
    # --switch-cost reaches OCN's clones alone, and S1's OCN clone is still imitation-s1's run under it.
    switching = parsed("s2", "--window-start", "packed", "--switch-cost", "0.3")
    assert finetune.clone_settings(switching, SETTINGS["s2"], methods["ocn"])[1]["switch_cost"] == 0.3
    assert "switch_cost" not in finetune.clone_settings(switching, SETTINGS["s2"], methods["moe"])[1]
    assert finetune.clone_dir(switching, SETTINGS["s2"], methods["ocn"], "craft_s2_ab", 1).parent.name == (
        "ocn_usage_balance1.0_packed_switch_cost0.3")
    assert finetune.clone_dir(switching, SETTINGS["s2"], methods["moe"], "craft_s2_ab", 1).parent.name == (
        "moe_usage_balance1.0_packed")
    study = parsed("imitation-s1", "--window-start", "packed", "--switch-cost", "0.3", "--expected-nll-weight", "0")
    shared = imitation.run_dir(tmp_path, imitation.VARIANTS[0], 1, imitation.study_overrides(study))
    s1_switching = parsed("s1", "--window-start", "packed", "--switch-cost", "0.3")
    assert finetune.clone_dir(s1_switching, SETTINGS["s1"], methods["ocn"], "craft_s1", 1) == shared
    assert shared.parent.name == "3options_T10_usage_balance1.0_packed_switch_cost0.3"
    # So does --expected-nll-weight, and S1's OCN clone is imitation-s1's run under the same weight.
    weighted = parsed("s1", "--window-start", "packed", "--expected-nll-weight", "0.1")
    assert finetune.clone_settings(weighted, SETTINGS["s1"], methods["ocn"])[1]["expected_nll_weight"] == 0.1
    assert "expected_nll_weight" not in finetune.clone_settings(weighted, SETTINGS["s1"], methods["moe"])[1]
    study = parsed("imitation-s1", "--window-start", "packed", "--expected-nll-weight", "0.1")
    shared = imitation.run_dir(tmp_path, imitation.VARIANTS[0], 1, imitation.study_overrides(study))
    assert finetune.clone_dir(weighted, SETTINGS["s1"], methods["ocn"], "craft_s1", 1) == shared
    assert shared.parent.name == "3options_T10_usage_balance1.0_packed_expected_nll_weight0.1"
    assert finetune.clone_dir(weighted, SETTINGS["s1"], methods["moe"], "craft_s1", 1).parent.name == (
        "moe_usage_balance1.0_packed")
    # Dial's clones take the packed view too (its normaliser standardises the packed columns).
    assert parsed("dial").window_start == "episode"
    assert dial.clone_dir(parsed("dial", "--window-start", "packed"), methods["ocn"], 1) == (
        tmp_path / "clone" / "dial2" / "ocn_usage_balance1.0_packed" / "seed1")


def test_dart_noise_reaches_every_clones_recording_and_the_results_header(tmp_path):
    import argparse

    from tools.reproduce import finetune
    from tools.reproduce.runs import record_dataset

    parser = argparse.ArgumentParser()
    finetune.add_parsers(parser.add_subparsers())
    args = parser.parse_args(["s2", "--dart-noise", "0.1", "--episodes-per-task", "2", "--workdir", str(tmp_path)])
    # A workdir whose first demonstration set was recorded without noise is refused before any training.
    record_dataset(tmp_path / "craft_s2_ab", "AB,BA", "local/craft_s2_ab", 2, 0)
    with pytest.raises(SystemExit, match="--dart-noise 0.1"):
        finetune.clone(args, SETTINGS["s2"], METHODS[0], 1)
    assert not (tmp_path / "clone").exists()

    assert "demonstrations recorded with DART noise 0.1" in _s1_results_markdown(["OCN"], {"dart_noise": 0.1})
    assert "DART" not in _s1_results_markdown(["OCN"])


def test_a_pool_size_and_the_settling_settings_reach_the_clones_and_name_their_folders(tmp_path):
    import argparse

    from tools.reproduce import finetune, imitation

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    imitation.add_parser(sub)
    finetune.add_parsers(sub)
    settle = ["--settle-steps", "2000", "--settle-usage-balance-options", "3", "--settle-usage-balance-exact",
              "--settle-switch-cost", "0.3"]

    def parsed(*words: str) -> argparse.Namespace:
        return parser.parse_args([*words, "--workdir", str(tmp_path), "--usage-balance", "1.0",
                                  "--window-start", "packed"])

    methods = {method.key: method for method in METHODS}
    six = parsed("s1", "--n-options", "6", *settle)
    for key in ("ocn", "moe", "hil"):
        assert finetune.clone_settings(six, SETTINGS["s1"], methods[key])[1]["n_options"] == 6
    for key in ("compile", "ompn"):
        assert "n_options" not in finetune.clone_settings(six, SETTINGS["s1"], methods[key])[1]
    assert finetune.clone_dir(six, SETTINGS["s1"], methods["moe"], "craft_s1", 1).parent.name == (
        "moe_usage_balance1.0_packed_n_options6")
    # The setting's own pool size is spelled out nowhere, so the clones made before the option are reused.
    for same in (parsed("s1"), parsed("s1", "--n-options", "3"), parsed("s2", "--n-options", "2")):
        assert finetune.options_override(same, methods["moe"]) == {}
    three = parsed("s1", "--n-options", "3")
    assert (finetune.clone_dir(three, SETTINGS["s1"], methods["moe"], "craft_s1", 1).parent.name
            == "moe_usage_balance1.0_packed")

    # S1's OCN clone is imitation-s1's 6-option run, settled in the same folder under the same settings.
    study = parsed("imitation-s1", *settle, "--expected-nll-weight", "0")
    shared = imitation.run_dir(tmp_path, imitation.VARIANTS[2], 1, imitation.study_overrides(study))
    assert finetune.clone_dir(six, SETTINGS["s1"], methods["ocn"], "craft_s1", 1) == shared
    assert shared.parent.name == "6options_T10_usage_balance1.0_packed"
    assert finetune.clone_settling(six, methods["ocn"]) == imitation.settling(study)
    assert finetune.clone_settling(six, methods["ocn"]).policy == {
        "usage_balance_options": 3, "usage_balance_exact": True, "switch_cost": 0.3}
    assert finetune.clone_settling(six, methods["moe"]) is None
    # The finetuning runs over those clones get folders of their own.
    assert finetune.clone_suffix(six, methods["ocn"]) == (
        "_usage_balance1.0_packed_n_options6_settle_steps2000_settle_cost0.1_settle_usage_balance_options3"
        "_settle_usage_balance_exact_settle_switch_cost0.3")
    assert finetune.clone_suffix(six, methods["moe"]) == "_usage_balance1.0_packed_n_options6"
    # A 4-option pool, which imitation-s1 has no variant of, is cloned into a folder named the same way.
    four = parsed("s1", "--n-options", "4")
    assert finetune.clone_dir(four, SETTINGS["s1"], methods["ocn"], "craft_s1", 1).parent.name == (
        "4options_T10_usage_balance1.0_packed")

    header = _s1_results_markdown(["OCN"], {"n_options": 6, "settle_steps": 2000, "settle_termination_cost": 0.1,
                                            "settle_usage_balance_exact": True}).split("## Checks")[0]
    assert "6 options per cloned model, cloned by" in header
    assert "`--policy.usage_balance_exact=true`" in header
    assert "3 options per cloned model" in _s1_results_markdown(["OCN"])
