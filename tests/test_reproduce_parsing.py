"""ocn-reproduce parsing-s1 end to end on a tiny budget: train, score every checkpoint, results, reuse.

The command runs in this process (its training runs are still real `lerobot-train` subprocesses),
so that the test pays for importing LeRobot once, not once per invocation; for the same reason the
S1 data is recorded in this process first, as `imitation-s1` would have left it in the workdir.
"""

import json
from pathlib import Path

import pytest

from ocn_data.record_demos import main as record_demos
from tools.reproduce import imitation, main
from tools.reproduce.parsing import baseline_wins, must_show, score_run

TINY = ["parsing-s1", "--seeds", "1", "--steps", "2", "--eval-every", "1", "--batch-size", "8", "--num-workers", "0",
        "--episodes-per-task", "12", "--methods", "ocn,ompn"]


def _reproduce(tmp_path: Path, *extra: str) -> int:
    return main([*TINY, "--workdir", str(tmp_path / "work"), "--results", str(tmp_path / "results"), *extra])


def test_parsing_s1_scores_every_checkpoint_and_writes_results_then_reuses(tmp_path, capsys):
    import dataclasses

    from ocn_data.episodes_table import load_episodes, split_episodes
    from tools.episode_parsing import (BOUNDARY_THRESHOLDS, choose_boundary_threshold, load_policy,
                                       score_segmentations, segment_episodes)

    work, results = tmp_path / "work", tmp_path / "results"
    assert record_demos(["--env", "craft", "--tasks", imitation.S1_TASKS, "--episodes-per-task", "12", "--root",
                         str(work / "craft_s1"), "--repo-id", imitation.S1_REPO_ID, "--seed", "0"]) == 0
    assert _reproduce(tmp_path) == 0
    first = capsys.readouterr().out
    # The S1 data is imitation-s1's: the same folder and repo id in the workdir.
    assert f"reusing the dataset in {work / 'craft_s1'}" in first
    assert "[1/2] OCN seed 1: 2 checkpoints scored" in first and "[2/2] OMPN seed 1: 2 checkpoints scored" in first

    result = json.loads((results / "parsing_s1.json").read_text())
    assert result["runs_finished"] == result["runs_planned"] == 2
    assert [(run["method"], run["seed"]) for run in result["runs"]] == [("OCN", 1), ("OMPN", 1)]
    for run in result["runs"]:
        assert [row["step"] for row in run["checkpoints"]] == [1, 2]
        assert all(0.0 <= row[m] <= 1.0 for row in run["checkpoints"] for m in ("f1_tol0", "f1_tol1", "align_acc"))
        assert "--save_freq=1" in run["train_command"]
    assert result["runs"][1]["checkpoints"][-1]["nmi"] is None and "OMPN" in result["not_applicable"]
    assert result["methods"]["OCN"]["values"] == pytest.approx(
        {"n_options": 3, "temperature": 10.0, "hidden_size": 128, "mlp_hidden_size": 128, "mlp_depth": 2,
         "optimizer_lr": 1e-3, "controller_lr_scale": 1.0})
    assert result["methods"]["OMPN"]["values"]["n_slots"] == 3 and "ompn_craft" in result["methods"]["OMPN"]["source"]
    assert list(result["summary"]) == ["OCN", "OMPN", "OMPN, count-free"]
    assert result["summary"]["OMPN"]["final"]["nmi"] is None
    assert set(result["summary"]["OCN"]["curves"]["f1_tol1"]) == {"mean", "std", "min", "max"}
    checks = result["must_show"]
    assert checks[0]["check"].startswith("OCN's F1@1 at or above OMPN's") and isinstance(checks[0]["holds"], bool)
    assert checks[1]["holds"] is None and "cannot be compared" in checks[1]["check"]
    ocn_final = result["summary"]["OCN"]["final"]
    assert all(w["baseline_value"] > ocn_final[w["metric"]]["mean"] for w in result["baseline_wins"])

    # The scores are those of an independent parse of one checkpoint.
    data = work / "craft_s1"
    episodes = load_episodes(data, split_episodes(data, "val"))
    policy, preprocessor, _ = load_policy(work / "parsing_s1" / "ocn" / "seed1" / "train" / "checkpoints" / "000001"
                                          / "pretrained_model")
    expected = score_segmentations(episodes, segment_episodes(policy, preprocessor, episodes))
    row = result["runs"][0]["checkpoints"][0]
    assert {m: row[m] for m in ("f1_tol0", "f1_tol1", "align_acc", "nmi")} == pytest.approx(
        {m: expected[m] for m in ("f1_tol0", "f1_tol1", "align_acc", "nmi")})

    # OMPN is also read out count-free, at the threshold that parses training episodes best, and those
    # scores are an independent parse's at that threshold.
    count_free = result["runs"][1]["checkpoints"][-1]["count_free"]
    tuned = {float(key): value for key, value in count_free["tuning_f1_tol1"].items()}
    assert set(tuned) == set(BOUNDARY_THRESHOLDS)
    assert count_free["threshold"] == max(BOUNDARY_THRESHOLDS, key=lambda threshold: (tuned[threshold], -threshold))
    ompn, ompn_preprocessor, _ = load_policy(work / "parsing_s1" / "ompn" / "seed1" / "train" / "checkpoints"
                                             / "000002" / "pretrained_model")
    tuning = load_episodes(data, split_episodes(data, "train")[:len(episodes.tasks)])
    assert choose_boundary_threshold(ompn, ompn_preprocessor, tuning) == (count_free["threshold"], tuned)
    assert ompn.config.boundary_threshold is None  # the policy's own read-out is left as it was
    ompn.config = dataclasses.replace(ompn.config, boundary_threshold=count_free["threshold"])
    expected = score_segmentations(episodes, segment_episodes(ompn, ompn_preprocessor, episodes))
    assert {m: count_free[m] for m in ("f1_tol0", "f1_tol1", "align_acc")} == pytest.approx(
        {m: expected[m] for m in ("f1_tol0", "f1_tol1", "align_acc")}) and count_free["nmi"] is None
    assert result["summary"]["OMPN, count-free"]["final"]["f1_tol1"]["mean"] == pytest.approx(count_free["f1_tol1"])
    assert any(check["check"].startswith("OCN's F1@1 at or above OMPN, count-free's") for check in checks)

    assert (results / "parsing_s1.png").stat().st_size > 0
    report = (results / "parsing_s1.md").read_text()
    assert "| OCN | 1 | 2 |" in report and "| OMPN | 1 | 2 |" in report and "lerobot-train --policy.type=ompn" in report
    assert "| OMPN, count-free | 1 | 2 |" in report and f"seed 1 threshold {count_free['threshold']:g}" in report
    assert "k the episode's true number of subtasks" in report

    cache = work / "parsing_s1" / "ocn" / "seed1" / "parsing.json"
    scored_at = cache.stat().st_mtime_ns
    ompn_cache = work / "parsing_s1" / "ompn" / "seed1" / "parsing.json"
    kept = json.loads(ompn_cache.read_text())
    ompn_cache.write_text(json.dumps([{key: value for key, value in row.items() if key != "count_free"}
                                      for row in kept]))  # as scored before the count-free read-out
    assert _reproduce(tmp_path) == 0
    again = capsys.readouterr().out
    assert f"training {work}" not in again and "resuming" not in again and cache.stat().st_mtime_ns == scored_at
    rescored = json.loads(ompn_cache.read_text())  # the kept scores without it were made again
    assert [row["count_free"] for row in rescored] == [row["count_free"] for row in kept]

    with pytest.raises(SystemExit, match="trained with other settings"):
        _reproduce(tmp_path, "--steps", "1")

    # A later seed in an invocation of its own (for `ocn-reproduce combine`) trains that seed alone.
    assert main([*TINY, "--workdir", str(work), "--results", str(tmp_path / "seed2"), "--methods", "ocn",
                 "--first-seed", "2"]) == 0
    assert "[1/1] OCN seed 2: 2 checkpoints scored" in capsys.readouterr().out
    later = json.loads((tmp_path / "seed2" / "parsing_s1.json").read_text())
    assert [(run["method"], run["seed"]) for run in later["runs"]] == [("OCN", 2)]


def test_a_run_without_the_wanted_checkpoints_is_refused(tmp_path):
    (tmp_path / "run" / "train" / "checkpoints" / "000004" / "pretrained_model").mkdir(parents=True)
    with pytest.raises(SystemExit, match=r"no checkpoint at steps \[2\] \(it has \[4\]\).*--eval-every"):
        score_run(tmp_path / "run", [2, 4], None, 1)


def _summary(**nmi: float | None) -> dict:
    def row(f1: float, value: float | None) -> dict:
        final = {"f1_tol0": f1, "f1_tol1": f1, "align_acc": f1, "nmi": value}
        return {"final": {m: None if v is None else {"mean": v, "std": 0.0} for m, v in final.items()}}

    return {name: row(0.9 if name != "HIL" else 0.95, value) for name, value in nmi.items()}


def test_checks_compare_nmi_with_the_labelled_baselines_and_list_every_baseline_win():
    summary = _summary(OCN=0.8, OMPN=None, compILE=0.1, HIL=0.85)
    checks = {check["check"].split(" (")[0].split(":")[0]: check for check in must_show(summary)}
    assert checks["OCN's F1@1 at or above OMPN's"]["holds"] is True
    assert checks["OCN's NMI at or above OMPN's at the end"]["holds"] is None
    assert checks["OCN's NMI at or above compILE's"]["holds"] is True
    assert checks["OCN's NMI at or above HIL's"]["holds"] is False
    wins = {(w["baseline"], w["metric"]) for w in baseline_wins(summary)}
    assert wins == {("HIL", "f1_tol0"), ("HIL", "f1_tol1"), ("HIL", "align_acc"), ("HIL", "nmi")}
    assert must_show(_summary(OMPN=None)) == [] and baseline_wins(_summary(OMPN=None)) == []


def test_balanced_ocn_family_runs_get_folders_of_their_own(tmp_path):
    import argparse

    from tools.reproduce.parsing import METHODS, method_settings, run_dir

    methods = {method.key: method for method in METHODS}
    paper, balanced = (argparse.Namespace(workdir=tmp_path, usage_balance=w, steps=2, batch_size=8, window_size=24,
                                          num_workers=0, threads=1, controller_lr_scale=1.0, eval_every=1)
                       for w in (0.0, 1.0))
    assert run_dir(paper, methods["hil"], 1) == tmp_path / "parsing_s1" / "hil" / "seed1"
    assert run_dir(balanced, methods["hil"], 1) == tmp_path / "parsing_s1" / "hil_usage_balance1.0" / "seed1"
    assert run_dir(balanced, methods["ompn"], 1) == tmp_path / "parsing_s1" / "ompn" / "seed1"
    assert method_settings(balanced, methods["ocn"])[1]["usage_balance"] == 1.0
    assert "usage_balance" not in method_settings(paper, methods["ocn"])[1]
    assert "usage_balance" not in method_settings(balanced, methods["compile"])[1]
