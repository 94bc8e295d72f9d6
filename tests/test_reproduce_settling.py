"""ocn-reproduce imitation-s1 settles each run: a second lerobot-train run from the first one's last
checkpoint under the log termination cost, scored before and after, on a tiny budget."""

import json
import subprocess
import sys
from pathlib import Path

from safetensors.torch import load_file

TINY = ["--seeds", "1", "--ablation-seeds", "0", "--steps", "2", "--batch-size", "8", "--num-workers", "0",
        "--episodes-per-task", "12", "--rollouts", "2"]


def _reproduce(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("ocn-reproduce")
    command = [str(script), "imitation-s1", *TINY, "--workdir", str(tmp_path / "work"),
               "--results", str(tmp_path / "results"), *extra]
    return subprocess.run(command, capture_output=True, text=True, timeout=600)


def _weights(checkpoint: Path) -> dict:
    return load_file(checkpoint / "model.safetensors")


def test_imitation_settles_each_run_from_its_checkpoint_and_scores_both(tmp_path):
    done = _reproduce(tmp_path, "--settle-steps", "2", "--settle-termination-cost", "0.3")
    assert done.returncode == 0, done.stderr[-2000:]
    # The study's defaults: its S1 recipe (packed view, DART recording, expected NLL).
    run = tmp_path / "work" / "imitation_s1" / "3options_T10_usage_balance1.0_packed_expected_nll_weight0.1" / "seed1"
    first, settled = (run / "train", run / "settle" / "train")
    command = (run / "settle" / "train_command.txt").read_text()
    # lerobot-train reads the dataset's packed view; ocn-eval scores on the recorded dataset.
    view = tmp_path / "work" / "craft_s1_packed32"
    assert f"--dataset.root={view} " in (run / "train_command.txt").read_text() and f"--dataset.root={view} " in command
    assert f"--policy.path={first / 'checkpoints' / 'last' / 'pretrained_model'}" in command
    assert "--policy.termination_cost=0.3" in command and "--policy.termination_penalty=log" in command
    config = json.loads((settled / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert (config["termination_cost"], config["termination_penalty"], config["usage_balance"]) == (0.3, "log", 1.0)

    # The settling run starts from the first run's weights: two Adam steps at lr 1e-3 move each weight by
    # at most 2e-3, while a fresh initialisation would be far off.
    before = _weights(first / "checkpoints" / "last" / "pretrained_model")
    after = _weights(settled / "checkpoints" / "last" / "pretrained_model")
    assert before.keys() == after.keys()
    assert max(float((after[k] - before[k]).abs().max()) for k in before) < 5e-3
    assert any(not (after[k] == before[k]).all() for k in before)

    result = json.loads((tmp_path / "results" / "imitation_s1.json").read_text())
    (record,) = result["runs"]
    assert record["train_command"].count("lerobot-train") == 2 and " && " in record["train_command"]
    assert record["before_settling"]["nmi"] == json.loads((run / "record.json").read_text())["scores"]["nmi"]
    settled_eval = json.loads((run / "settle" / "eval.json").read_text())
    assert {key: record["scores"][key] for key in settled_eval} == settled_eval
    text = (tmp_path / "results" / "imitation_s1.md").read_text()
    assert "settling phase of 2 steps from the last checkpoint at log termination cost 0.3" in text
    assert "| 3 options, T=10, before settling | 1 |" in text
    assert text.rstrip().endswith("| 3 options, T=10 seed 1 |")  # the invocation that trained it
    assert "option x subtask success of the main variant's seed 1" in text
    assert ((tmp_path / "results" / "imitation_s1_option_table.png").read_bytes()
            == (run / "settle" / "eval.png").read_bytes())

    # Reused as it is; a file of settled runs refuses runs made without settling, which go to their own file.
    again = _reproduce(tmp_path, "--settle-steps", "2", "--settle-termination-cost", "0.3")
    assert again.returncode == 0
    assert not [line for line in again.stdout.splitlines() if line.startswith(("training ", "resuming ", "rescoring "))]
    text = (tmp_path / "results" / "imitation_s1.md").read_text()
    assert text.rstrip().endswith("| 3 options, T=10 seed 1 (found trained) |")
    unsettled = _reproduce(tmp_path, "--settle-steps", "0")
    assert unsettled.returncode != 0 and "settle_steps 2 there, 0 here" in unsettled.stderr

    # Policy settings of the settling phase alone: a folder of its own beside the first settling, from the same run.
    spare = _reproduce(tmp_path, "--settle-steps", "2", "--settle-termination-cost", "0.3",
                       "--settle-usage-balance-options", "2", "--settle-usage-balance-exact", "--settle-switch-cost",
                       "0.2", "--results", str(tmp_path / "results_spare"))
    assert spare.returncode == 0, spare.stderr[-2000:]
    spare_dir = run / "settle_usage_balance_options2_usage_balance_exact_switch_cost0.2"
    spare_config = json.loads(
        (spare_dir / "train" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert (spare_config["usage_balance_options"], spare_config["usage_balance_exact"], spare_config["switch_cost"],
            spare_config["n_options"]) == (2, True, 0.2, 3)
    assert f"--policy.path={first / 'checkpoints' / 'last' / 'pretrained_model'}" in (
        spare_dir / "train_command.txt").read_text()
    assert (run / "settle" / "train" / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").exists()
    assert ("log termination cost 0.3, `--policy.usage_balance_options=2`, `--policy.usage_balance_exact=true`, "
            "`--policy.switch_cost=0.2`"
            in (tmp_path / "results_spare" / "imitation_s1.md").read_text())
    # Settled by this invocation from a run an earlier one trained: not found trained.
    assert (tmp_path / "results_spare" / "imitation_s1.md").read_text().rstrip().endswith("| 3 options, T=10 seed 1 |")
    refused = _reproduce(tmp_path, "--settle-steps", "2", "--settle-termination-cost", "0.3",
                         "--results", str(tmp_path / "results_spare"))
    assert refused.returncode != 0 and "settle_switch_cost 0.2 there, None here" in refused.stderr

    # A first run extended to more steps is settled again, from its new last checkpoint.
    longer = _reproduce(tmp_path, "--steps", "4", "--settle-steps", "2", "--settle-termination-cost", "0.3",
                        "--results", str(tmp_path / "results_4"))
    assert longer.returncode == 0, longer.stderr[-2000:]
    assert "settling" in longer.stdout and "its run was trained on since" in longer.stdout
    timing = json.loads((run / "settle" / "train_wall_s.json").read_text())
    assert [invocation["from_step"] for invocation in timing["invocations"]] == [0]
    assert "--steps=4" in (run / "settle" / "settled_from.txt").read_text()
    moved = max(float((_weights(settled / "checkpoints" / "last" / "pretrained_model")[k] - after[k]).abs().max())
                for k in after)
    assert moved > 0

    # An ablation added in a later session, whose workdir no longer holds the main runs' option tables,
    # keeps the table those runs left in the results folder.
    table = (tmp_path / "results" / "imitation_s1_option_table.png").read_bytes()
    (run / "settle" / "eval.png").unlink()
    ablation = _reproduce(tmp_path, "--settle-steps", "2", "--settle-termination-cost", "0.3", "--seeds", "0",
                          "--ablation-seeds", "1", "--variants", "2options_T10")
    assert ablation.returncode == 0, ablation.stderr[-2000:]
    result = json.loads((tmp_path / "results" / "imitation_s1.json").read_text())
    assert [r["variant"] for r in result["runs"]] == ["3 options, T=10", "2 options, T=10"]
    assert result["option_table_seed"] == 1
    assert (tmp_path / "results" / "imitation_s1_option_table.png").read_bytes() == table
