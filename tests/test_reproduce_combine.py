"""ocn-reproduce combine: one finetuning or parsing study from the results files of separate invocations."""

import json
from pathlib import Path

import pytest

from tools.reproduce import main
from tools.reproduce.finetune import SETTINGS, at_budget, summarise, task_labels

LABELS = task_labels(SETTINGS["s2"])


def _run(method: str, success: float, seed: int = 1) -> dict:
    """One sparse-reward run whose success climbs linearly to `success` over 1,000 env frames."""
    curve = [{"frames": float(frames), "mean_return": success * frames / 1000, "success": success * frames / 1000,
              **{f"success[{label}]": success * frames / 1000 for label in LABELS}} for frames in range(0, 1001, 100)]
    return {"method": method, "reward": "sparse", "seed": seed, "command": f"ocn-finetune {method}",
            "clone_commands": [], "clone_wall_s": [], "clones_trained_on": [], "summary": {"frames_per_s": 100.0},
            "at_budget": at_budget(curve, LABELS), "curve": curve}


def _study(path: Path, runs: list[dict], legacy: bool = False, **settings) -> Path:
    """An S2 results file of `runs`, laid out as `ocn-reproduce s2` writes it (`legacy`: as it wrote it
    before runs kept their curves, and before the settings `settings` names None existed)."""
    summary = summarise(runs, LABELS)
    kept = [{k: v for k, v in run.items() if k not in ("curve", "at_budget")} for run in runs] if legacy else runs
    recipe = {"frames": 1000, "envs": 8, "dart_noise": 0.1, "settle_steps": 1000, "settle_termination_cost": 0.1,
              **settings}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "command": f"ocn-reproduce s2 --methods {','.join(run['method'] for run in runs)}", "date": "2026-12-01",
        "machine": {"cpu": "AMD EPYC", "cores": 2}, "setting": "s2",
        "settings": {key: value for key, value in recipe.items() if value is not None},
        "runs_finished": len(runs), "runs_planned": len(runs), "summary": summary, "must_show": [],
        "runs": kept, "wall_s": 600.0,
    }))
    return path


def _combine(tmp_path: Path, *files: Path) -> dict:
    assert main(["combine", *map(str, files), "--results", str(tmp_path / "out")]) == 0
    return json.loads((tmp_path / "out" / "finetune_s2.json").read_text())


def test_combined_study_checks_every_baseline_against_ocn(tmp_path):
    ocn = _study(tmp_path / "a" / "finetune_s2.json", [_run("OCN", 0.95)])
    baselines = _study(tmp_path / "b" / "finetune_s2.json", [_run("flat PPO", 0.1), _run("MoE", 1.0)])
    assert main(["combine", str(baselines), str(ocn), "--results", str(tmp_path / "both")]) == 0

    result = json.loads((tmp_path / "both" / "finetune_s2.json").read_text())
    assert list(result["summary"]) == ["OCN | sparse", "MoE | sparse", "flat PPO | sparse"]
    together = summarise([_run("OCN", 0.95), _run("MoE", 1.0), _run("flat PPO", 0.1)], LABELS)
    assert result["summary"] == json.loads(json.dumps(together))
    checks = {check["check"].split(" (")[0]: check["holds"] for check in result["must_show"]}
    assert checks == {"OCN, sparse: success >= 0.8 on each of BADC, ACBD, CABD": True,
                      "sparse: MoE's mean success below OCN's": False,
                      "sparse: flat PPO's mean success below OCN's": True}
    assert result["runs_finished"] == 3 and result["wall_s"] == 1200.0
    text = (tmp_path / "both" / "finetune_s2.md").read_text()
    assert "Combined by `ocn-reproduce combine" in text
    assert "`ocn-reproduce s2 --methods OCN` on AMD EPYC (2 cores), 2026-12-01 (OCN)" in text
    assert "(MoE, flat PPO)" in text and "DART noise 0.1" in text and "wall time of the invocations 20 min" in text
    assert (tmp_path / "both" / "finetune_s2.png").stat().st_size > 0


@pytest.mark.parametrize("second, problem", [
    ({"runs": [_run("MoE", 0.5)], "frames": 2000}, "differ in frames"),
    ({"runs": [_run("MoE", 0.5)], "gamma": 0.995}, "differ in gamma"),
    ({"runs": [_run("OCN", 0.5)]}, "the OCN run with reward sparse and seed 1 is in both"),
])
def test_files_of_another_recipe_or_with_the_same_rows_are_refused(tmp_path, second, problem):
    first = _study(tmp_path / "a.json", [_run("OCN", 0.95)])
    other = _study(tmp_path / "b.json", second.pop("runs"), **second)
    with pytest.raises(SystemExit, match=problem):
        main(["combine", str(first), str(other), "--results", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_a_file_that_is_not_a_finetuning_study_is_refused_by_name(tmp_path):
    study = _study(tmp_path / "a.json", [_run("OCN", 0.95)])
    imitation = tmp_path / "imitation_s1.json"
    imitation.write_text(json.dumps({"variants": {}}))
    with pytest.raises(SystemExit, match="imitation_s1.json is not a results file"):
        main(["combine", str(study), str(imitation), "--results", str(tmp_path / "out")])


def test_seeds_of_one_method_from_several_files_make_one_row(tmp_path):
    """A file written before runs kept their curves (one seed per row) combines with new seeds of the
    same method: the row is over all seeds, as if one invocation had run them."""
    first = _study(tmp_path / "a.json", [_run("OCN", 0.9, seed=1), _run("MoE", 0.3, seed=1)], legacy=True)
    later = _study(tmp_path / "b.json", [_run("OCN", 0.7, seed=2), _run("OCN", 0.8, seed=3)])
    result = _combine(tmp_path, first, later)

    row = result["summary"]["OCN | sparse"]
    assert row["seeds"] == [1, 2, 3]
    assert row["at_budget"]["success"]["mean"] == pytest.approx((0.9 * 0.9 + 0.7 * 0.9 + 0.8 * 0.9) / 3)
    assert row["curves"]["success"]["max"][-1] == pytest.approx(0.9)
    assert result["summary"]["MoE | sparse"]["seeds"] == [1]
    assert [source["methods"] for source in result["sources"]] == [["OCN", "MoE"], ["OCN"]]
    assert "| OCN | sparse | 3 |" in (tmp_path / "out" / "finetune_s2.md").read_text()
    # The combined file keeps every run's curve, so it combines again with later seeds.
    again = _combine(tmp_path, tmp_path / "out" / "finetune_s2.json",
                     _study(tmp_path / "c.json", [_run("MoE", 0.5, 2)]))
    assert again["summary"]["MoE | sparse"]["seeds"] == [1, 2]
    assert again["summary"]["OCN | sparse"] == row


def test_a_file_without_run_curves_and_rows_over_seeds_is_refused(tmp_path):
    pooled = _study(tmp_path / "a.json", [_run("OCN", 0.9, seed=1), _run("OCN", 0.8, seed=2)], legacy=True)
    other = _study(tmp_path / "b.json", [_run("MoE", 0.3)])
    with pytest.raises(SystemExit, match=r"a.json keeps no curve per run .* over seeds \[1, 2\]"):
        main(["combine", str(pooled), str(other), "--results", str(tmp_path / "out")])


def test_a_setting_a_file_leaves_out_counts_as_its_default(tmp_path):
    """Files written before `--dart-noise`, `--window-start`, the usage balance, settling or `--gamma`
    existed leave those settings out; they ran at the defaults and combine with files that spell them out."""
    defaults = {"dart_noise": 0.0, "window_start": "episode", "usage_balance": 0.0, "settle_steps": 0,
                "settle_termination_cost": 0.0, "gamma": 0.97}
    old = _study(tmp_path / "a.json", [_run("OCN", 0.9)], legacy=True, **{key: None for key in defaults})
    new = _study(tmp_path / "b.json", [_run("MoE", 0.3)], **defaults)
    merged = _combine(tmp_path, old, new)["settings"]
    assert {key: merged[key] for key in defaults} == defaults
    noisy = _study(tmp_path / "c.json", [_run("MoE", 0.3)], **{**defaults, "dart_noise": 0.1})
    with pytest.raises(SystemExit, match="differ in dart_noise"):
        main(["combine", str(old), str(noisy), "--results", str(tmp_path / "refused")])


def _parsing_run(method: str, seed: int, f1: float, nmi: float | None) -> dict:
    """One parsing run scored at steps 500 and 1000, ending at F1 `f1` and NMI `nmi`."""
    rows = [{"step": step, "f1_tol0": f1 * step / 1000, "f1_tol1": f1 * step / 1000, "align_acc": f1,
             "nmi": None if nmi is None else nmi * step / 1000, "wall_s": 1.0} for step in (500, 1000)]
    if nmi is None:
        rows = [{**row, "no_labels": "no per-step labels"} for row in rows]
    return {"method": method, "seed": seed, "train_command": f"lerobot-train --policy.type={method.lower()}",
            "train_wall_s": 100.0, "score_wall_s": 2.0, "checkpoints": rows,
            "hyperparameters": {"policy_type": method.lower(), "values": {}, "source": "its config"}}


def _parsing_study(path: Path, runs: list[dict], **settings) -> Path:
    """A parsing_s1.json of `runs`, laid out as `ocn-reproduce parsing-s1` writes it."""
    from tools.reproduce import parsing

    recipe = {"experiment": "parsing-s1", "steps": 1000, "batch_size": 8, "window_size": 24, "eval_every": 500,
              "controller_lr_scale": 1.0, "episodes_per_task": 12, "data_seed": 0, "window_start": "packed",
              "usage_balance": 1.0, "workdir": str(path.parent), **settings}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({
        "command": f"ocn-reproduce parsing-s1 --methods {','.join(run['method'] for run in runs)}",
        "date": "2026-12-03", "machine": {"cpu": "AMD EPYC", "cores": 2}, "settings": recipe,
        **parsing.study(runs, len(runs), 36, 300.0)}))
    return path


def test_parsing_studies_combine_into_one_with_the_checks_made_again(tmp_path):
    ocn = _parsing_study(tmp_path / "a" / "parsing_s1.json",
                         [_parsing_run("OCN", 1, 0.9, 0.8), _parsing_run("OMPN", 1, 1.0, None)])
    later = _parsing_study(tmp_path / "b" / "parsing_s1.json",
                           [_parsing_run("compILE", 1, 0.5, 0.3), _parsing_run("HIL", 1, 0.6, 0.9),
                            _parsing_run("OCN", 2, 0.7, 0.6)], workdir="elsewhere")
    assert main(["combine", str(ocn), str(later), "--results", str(tmp_path / "out")]) == 0

    result = json.loads((tmp_path / "out" / "parsing_s1.json").read_text())
    assert list(result["summary"]) == ["OCN", "OMPN", "compILE", "HIL"]
    assert result["summary"]["OCN"]["seeds"] == [1, 2]
    assert result["summary"]["OCN"]["final"]["f1_tol1"]["mean"] == pytest.approx(0.8)
    assert result["summary"]["OCN"]["curves"]["nmi"]["min"] == pytest.approx([0.3, 0.6])
    checks = {check["baseline"] + " " + check["metric"]: check["holds"] for check in result["must_show"]}
    assert checks == {"OMPN f1_tol1": False, "OMPN nmi": None, "compILE nmi": True, "HIL nmi": False}
    assert {(w["baseline"], w["metric"]) for w in result["baseline_wins"]} == {
        ("OMPN", "f1_tol0"), ("OMPN", "f1_tol1"), ("OMPN", "align_acc"), ("HIL", "nmi")}
    assert result["runs_finished"] == 5 and result["wall_s"] == 600.0 and result["val_episodes"] == 36
    assert result["settings"]["experiment"] == "parsing-s1" and "workdir" not in result["settings"]
    assert [source["methods"] for source in result["sources"]] == [["OCN", "OMPN"], ["OCN", "compILE", "HIL"]]
    text = (tmp_path / "out" / "parsing_s1.md").read_text()
    assert "Combined by `ocn-reproduce combine" in text and "wall time of the invocations 10.0 min" in text
    assert "- HIL beats OCN on NMI: 0.900 against 0.700" in text
    assert (tmp_path / "out" / "parsing_s1.png").stat().st_size > 0
    # The combined file combines again.
    more = _parsing_study(tmp_path / "c" / "parsing_s1.json", [_parsing_run("HIL", 2, 0.6, 0.5)])
    assert main(["combine", str(tmp_path / "out" / "parsing_s1.json"), str(more),
                 "--results", str(tmp_path / "again")]) == 0
    assert json.loads((tmp_path / "again" / "parsing_s1.json").read_text())["summary"]["HIL"]["seeds"] == [1, 2]


@pytest.mark.parametrize("second, problem", [
    ({"steps": 2000}, "differ in steps"),
    ({"window_start": "episode"}, "differ in window_start"),
    ({"run": ("OCN", 1)}, "the OCN run with seed 1 is in both"),
])
def test_parsing_studies_of_another_recipe_or_with_the_same_run_are_refused(tmp_path, second, problem):
    first = _parsing_study(tmp_path / "a.json", [_parsing_run("OCN", 1, 0.9, 0.8)])
    method, seed = second.pop("run", ("HIL", 1))
    other = _parsing_study(tmp_path / "b.json", [_parsing_run(method, seed, 0.6, 0.5)], **second)
    with pytest.raises(SystemExit, match=problem):
        main(["combine", str(first), str(other), "--results", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_a_parsing_study_and_a_finetuning_study_are_refused_together(tmp_path):
    parsing = _parsing_study(tmp_path / "parsing_s1.json", [_parsing_run("OCN", 1, 0.9, 0.8)])
    finetuning = _study(tmp_path / "finetune_s2.json", [_run("OCN", 0.95)])
    with pytest.raises(SystemExit, match="different kinds: .*parsing_s1.json: parsing; .*finetune_s2.json: finetune"):
        main(["combine", str(parsing), str(finetuning), "--results", str(tmp_path / "out")])
