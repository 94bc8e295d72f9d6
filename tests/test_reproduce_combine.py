"""`ocn-reproduce combine` joins the results of invocations run side by side and refuses what does not
belong together; the sample-efficiency check races OCN against the best baseline on env frames."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lerobot_policy_ocn.tools.reproduce import curves, finetune, imitation, main

LABELS = finetune.SETTINGS["s1"].labels
SETTINGS = {"frames": 1000, "envs": 8, "episodes_per_task": 20, "steps": 20, "batch_size": 8}


def _run(method: str, reward: str, seed: int, top: float, reach_at: float = 500.0) -> dict:
    """A finetuning run whose curve climbs linearly from 0 to `top` at `reach_at` env frames, then stays."""
    curve = [{"frames": float(f), **{key: top * min(f / reach_at, 1.0) for key in curves.curve_keys(LABELS)}}
             for f in range(100, 1001, 100)]
    return {"method": method, "reward": reward, "seed": seed, "command": f"ocn-finetune {method}",
            "clone_commands": [], "clone_wall_s": [], "wall_s": 60.0, "frames_per_s": 100.0, "curve": curve}


def _finetune_file(path: Path, runs: list[dict], **settings) -> Path:
    """An S1 results JSON of `runs`, as `ocn-reproduce s1` writes it."""
    result = {"command": "ocn-reproduce s1", "date": "2026-12-07", "machine": {"cpu": "AMD EPYC", "cores": 2},
              "settings": {**SETTINGS, "seeds": sorted({run["seed"] for run in runs}), **settings},
              **finetune.study(finetune.SETTINGS["s1"], runs), "wall_s": 600}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result))
    return path


def _combine(tmp_path: Path, *files: Path) -> dict:
    assert main(["combine", *map(str, files), "--results", str(tmp_path / "out")]) == 0
    return json.loads(next((tmp_path / "out").glob("*.json")).read_text())


def test_combined_study_is_made_again_over_every_file(tmp_path):
    ocn = _finetune_file(tmp_path / "a" / "finetune_s1.json", [_run("ocn", "sparse", 1, 0.95)])
    others = _finetune_file(tmp_path / "b" / "finetune_s1.json", [_run("moe", "sparse", 1, 0.4),
                                                                 _run("ocn", "sparse", 2, 0.97)])
    result = _combine(tmp_path, ocn, others)
    assert result["command"].startswith("ocn-reproduce combine") and len(result["sources"]) == 2
    assert result["summary"]["ocn | sparse"]["seeds"] == [1, 2]
    ocn_bar, moe_below = result["checks"][:2]
    assert (ocn_bar["value"], moe_below["value"]) == pytest.approx((0.96, 0.4))
    assert ocn_bar["holds"] and moe_below["holds"]
    assert result["wall_s"] == 1200
    for suffix in ("md", "png"):
        assert (tmp_path / "out" / f"finetune_s1.{suffix}").stat().st_size > 0


def test_files_measured_differently_are_refused(tmp_path):
    a = _finetune_file(tmp_path / "a.json", [_run("ocn", "sparse", 1, 0.9)])
    b = _finetune_file(tmp_path / "b.json", [_run("ocn", "sparse", 2, 0.9)], frames=2000)
    with pytest.raises(SystemExit, match="different settings, frames"):
        _combine(tmp_path, a, b)


def test_a_run_in_two_files_is_refused(tmp_path):
    a = _finetune_file(tmp_path / "a.json", [_run("ocn", "sparse", 1, 0.9)])
    b = _finetune_file(tmp_path / "b.json", [_run("ocn", "sparse", 1, 0.8)])
    with pytest.raises(SystemExit, match="in both"):
        _combine(tmp_path, a, b)


def test_files_of_different_studies_are_refused(tmp_path):
    a = _finetune_file(tmp_path / "a.json", [_run("ocn", "sparse", 1, 0.9)])
    b = tmp_path / "b.json"
    b.write_text(json.dumps({**json.loads(a.read_text()), "study": imitation.STUDY}))
    with pytest.raises(SystemExit, match="different studies"):
        _combine(tmp_path, a, b)


def _imitation_run(variant: str, seed: int, nmi: float) -> dict:
    table = {"subtasks": ["A", "C", "D"], "table": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}
    scores = {"f1_tol0": 1.0, "f1_tol1": 1.0, "align_acc": 1.0, "nmi": nmi, "mean_success_rate": 1.0,
              "success_rate": {"AC": 1.0}, "option_table": table, "diagonal": [1.0] * 3, "diagonal_mean": 1.0}
    return {"variant": variant, "seed": seed, "train_command": "lerobot-train", "train_wall_s": 1.0,
            "eval_command": "ocn-eval", "scores": scores}


def test_imitation_seeds_of_two_invocations_make_one_study(tmp_path):
    files = []
    for seed, runs in ((1, [_imitation_run("main", 1, 0.99), _imitation_run("options2", 1, 0.5)]),
                       (2, [_imitation_run("main", 2, 0.96)])):
        path = tmp_path / f"seed{seed}.json"
        path.write_text(json.dumps({"command": "ocn-reproduce imitation-s1", "date": "2026-12-07",
                                    "machine": {"cpu": "x", "cores": 2},
                                    "settings": {**SETTINGS, "rollouts": 2, "seeds": [seed]},
                                    **imitation.study(runs), "wall_s": 10}))
        files.append(path)
    result = _combine(tmp_path, *files)
    assert result["summary"]["main"]["seeds"] == [1, 2]
    nmi, f1, below = result["checks"][:3]
    assert (nmi["value"], nmi["holds"], f1["holds"]) == (0.96, True, True)
    assert below["holds"] and below["value"] == 0.5


def test_sample_efficiency_races_to_ninety_percent_of_ocns_final_return(tmp_path):
    def row(run: dict) -> dict:
        return finetune.summarise([run], LABELS)[f"{run['method']} | dense"]

    ocn = row(_run("ocn", "dense", 1, 3.0, reach_at=200))
    found = curves.sample_efficiency(ocn, {"hil": row(_run("hil", "dense", 1, 3.0, reach_at=800))})
    assert found["target_return"] == pytest.approx(2.7)
    assert found["ratio"] == pytest.approx(found["ocn_frames"] / found["baseline_frames"]["hil"])
    assert found["ratio"] < curves.EFFICIENCY_GOAL and not found["ratio_is_bound"]
    never = curves.sample_efficiency(ocn, {"moe": row(_run("moe", "dense", 1, 1.0))})
    assert never["ratio_is_bound"] and never["ratio"] == pytest.approx(never["ocn_frames"] / 1000)


def test_frames_to_reach_interpolates_between_iterations():
    assert curves.frames_to_reach([100, 200, 300], [0.0, 1.0, 2.0], 1.5) == 250
    assert curves.frames_to_reach([100, 200], [2.0, 3.0], 1.0) == 100
    assert curves.frames_to_reach([100, 200], [0.0, 0.5], 1.0) is None
