"""`ocn-reproduce imitation-s1` and `s1` at a tiny size, through real `record_demos`, `lerobot-train`,
`ocn-eval` and `ocn-finetune` subprocesses: the commands they build carry no recipe flag, a finished
run is reused, an interrupted one resumes, a folder of another command is refused, and the results
files hold the command and the checks. One workdir serves every test, in the order written: the
finetuning study reuses the imitation study's OCN clone, as the full-size studies do."""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_policy_ocn.tools.reproduce import main, runs
from lerobot_policy_ocn.tools.reproduce.clones import Model
from lerobot_policy_ocn.tools.reproduce.imitation import VARIANTS
from lerobot_policy_ocn.tools.reproduce.runs import Finetuning, Training, train_command

TINY = ["--episodes-per-task", "20", "--steps", "20", "--batch-size", "8", "--seeds", "1"]
CLONE = "train/craft_s1/ocn/seed1"
# The only `--policy.*` words of a study's default commands: the type and LeRobot's plumbing.
PLUMBING = {"--policy.type=ocn", "--policy.device=cpu", "--policy.push_to_hub=false"}


def policy_words(command: str) -> set[str]:
    return {word for word in shlex.split(command) if word.startswith("--policy.")}


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny imitation-s1 (main variant, seed 1) saving a checkpoint every 10 of its 20 steps, so that
    a run can be cut back to an interrupted one."""
    workdir, results = tmp_path_factory.mktemp("workdir"), tmp_path_factory.mktemp("results")
    patch = pytest.MonkeyPatch()
    patch.setattr(runs, "SAVE_EVERY", 10)
    argv = ["imitation-s1", *TINY, "--variants", "main", "--rollouts", "2", "--workdir", str(workdir),
            "--results", str(results)]
    assert main(argv) == 0
    yield {"workdir": workdir, "results": results, "argv": argv}
    patch.undo()


def test_the_results_hold_the_command_and_the_checks_first(study):
    result = json.loads((study["results"] / "imitation_s1.json").read_text())
    assert result["command"] == shlex.join(["ocn-reproduce", *study["argv"]])
    assert {"cpu", "cores"} <= set(result["machine"])
    assert [check["check"] for check in result["checks"]][:2] == [
        "3 options, T=10: NMI >= 0.95 on every seed", "3 options, T=10: F1@1 >= 0.95 on every seed"]
    assert all(check["holds"] is None for check in result["checks"][2:])  # the ablations did not run
    text = (study["results"] / "imitation_s1.md").read_text()
    assert text.index("## Checks") < text.index("## Mean") and result["command"] in text
    assert (study["results"] / "imitation_s1.png").stat().st_size > 0
    [run] = result["runs"]
    assert policy_words(run["train_command"]) == PLUMBING  # the main variant is the plain recipe


def test_ablations_add_a_model_size_flag_and_nothing_else():
    for name, model in VARIANTS.items():
        command = train_command(model.policy_type, "data", "local/x", "out", 20, 8, 1, model.flags)
        assert policy_words(shlex.join(command)) - PLUMBING == {f"--policy.{k}={v}" for k, v in model.flags.items()}
        assert (name == "main") == (not model.flags)


def test_a_recipe_flag_is_refused():
    for flags in ({"usage_balance": 1.0}, {"recipe": "craft"}, {"expected_nll_weight": 0.1}):
        with pytest.raises(ValueError, match="no recipe flag"):
            train_command("ocn", "data", "local/x", "out", 20, 8, 1, flags)


def test_a_finished_run_is_reused(study):
    timing = (study["workdir"] / CLONE / "timing.json").read_text()
    assert main(study["argv"]) == 0
    assert (study["workdir"] / CLONE / "timing.json").read_text() == timing


def test_an_interrupted_run_resumes_from_its_last_checkpoint(study, monkeypatch):
    monkeypatch.setattr(runs, "SAVE_EVERY", 10)
    checkpoints = study["workdir"] / CLONE / "train" / "checkpoints"
    # As if the run had stopped after its checkpoint at step 10.
    (checkpoints / "last").unlink()
    shutil.rmtree(checkpoints / "000020")
    (checkpoints / "last").symlink_to("000010")
    job = Training(study["workdir"], CLONE, shlex.split((study["workdir"] / CLONE / "command.txt").read_text()))
    assert not job.finished() and job.resumed()[-1] == "--resume=true"
    assert main(study["argv"]) == 0
    assert job.finished() and [entry["resumed"] for entry in job.timing()] == [False, True]
    assert "Resuming" in (study["workdir"] / CLONE / "log.txt").read_text()


def changed(argv: list[str], option: str, value: str) -> list[str]:
    """`argv` with another value of `option`."""
    at = argv.index(option) + 1
    return [*argv[:at], value, *argv[at + 1:]]


def test_a_folder_made_by_another_command_is_refused(study):
    with pytest.raises(SystemExit, match="holds the run of"):  # the same recording, another training
        main(changed(study["argv"], "--steps", "30"))
    with pytest.raises(SystemExit, match="holds the run of"):  # another recording
        main(changed(study["argv"], "--episodes-per-task", "21"))


@pytest.fixture(scope="module")
def finetuned(study: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict:
    """`ocn-reproduce s1` over the study's clone (OCN and OMPN, dense reward, 600 frames), run once for
    whichever test of this module asks first on its worker (pytest-xdist may give the tests that read it
    to different workers): its argv, its results folder and the clone's timings from before it ran."""
    results = tmp_path_factory.mktemp("s1_results")
    argv = ["s1", *TINY, "--methods", "ocn,ompn", "--rewards", "dense", "--frames", "600", "--envs", "3",
            "--workdir", str(study["workdir"]), "--results", str(results)]
    clone_timing = (study["workdir"] / CLONE / "timing.json").read_text()
    assert main(argv) == 0
    return {"argv": argv, "results": results, "clone_timing": clone_timing}


def test_s1_finetunes_over_the_imitation_clone_with_plain_commands(study, finetuned):
    argv, tmp_path = finetuned["argv"], finetuned["results"]
    result = json.loads((tmp_path / "finetune_s1.json").read_text())
    assert result["command"] == shlex.join(["ocn-reproduce", *argv])
    assert (study["workdir"] / CLONE / "timing.json").read_text() == finetuned["clone_timing"]  # the clone, reused
    ocn, ompn = result["runs"]
    assert shlex.split(ocn["command"])[:2] == ["ocn-finetune", "--tasks"]
    assert f"{CLONE}/train/checkpoints/last/pretrained_model" in ocn["command"]
    assert policy_words(ompn["clone_commands"][0]) == {"--policy.type=ompn", *PLUMBING - {"--policy.type=ocn"}}
    assert all(not policy_words(run["command"]) for run in result["runs"])
    assert ocn["curve"] and ocn["curve"][-1]["frames"] >= 600
    names = [check["check"] for check in result["checks"]]
    assert names[0].endswith("(not run)") and names[-1].startswith("dense: OCN's env frames to 90%")
    assert result["checks"][-1]["value"] is not None
    assert (tmp_path / "finetune_s1.md").read_text().index("## Checks") < \
        (tmp_path / "finetune_s1.md").read_text().index("## At the budget")


def test_an_interrupted_finetuning_goes_on_with_resume(study, finetuned):
    folder = next((study["workdir"] / "finetune" / "s1").glob("*/ocn_dense/seed1"))
    job = Finetuning(study["workdir"], str(folder.relative_to(study["workdir"])), [])
    (folder / "out" / "finetune.json").unlink()  # as if stopped after its last PPO iteration
    assert job.resumed()[-1] == "--resume"
    assert main(finetuned["argv"]) == 0
    assert job.finished() and [entry["resumed"] for entry in job.timing()] == [False, True]


def test_a_flag_that_is_not_a_model_size_or_baseline_never_names_a_clone():
    assert Model("OCN").folder == "ocn"
    assert Model("MoE", flags={"hierarchy": "moe"}).with_flags(n_options=2).folder == "ocn_hierarchy-moe_n_options-2"
    assert Model("OMPN", "ompn").with_flags(n_options=2).folder == "ompn"


def test_help_imports_neither_torch_nor_lerobot():
    """What keeps `--help` instant (its time is a benchmark's business, not a test's)."""
    probe = ("import sys; from lerobot_policy_ocn.tools.reproduce import build_parser; parser = build_parser(); "
             "print(any(name.split('.')[0] in ('torch', 'lerobot') for name in sys.modules))")
    heavy = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert heavy == ["False"]
