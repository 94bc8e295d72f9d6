"""Learning curves of finetuning runs, read from what `ocn-finetune` writes (`curve.csv`, one row per
PPO iteration): each run's value at the budget, the curves over seeds, sample efficiency, the plot.

One PPO iteration scores about one episode per env, so one row is noisy: a run's curve is the
trailing mean over `FINAL_ROWS` iterations, and its value at the budget is that curve's last point
(the mean of its last three iterations). Over seeds, the curves are interpolated onto
`GRID_POINTS` env-frame points and averaged.

Sample efficiency (issue 71, item 8) replaces "twice the strongest baseline's dense return": the env
frames OCN needs to reach 90% of its own final dense return (its mean curve over seeds first
reaching it) against the frames the best baseline needs to reach that same return, goal <= 0.5x. A
baseline that never reaches it within the budget needs more than the budget, so the ratio is then
at most OCN's frames over the budget, and that bound is what is reported.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

FINAL_ROWS = 3
GRID_POINTS = 40
REACH = 0.9  # the share of OCN's final dense return that the sample-efficiency check races to
EFFICIENCY_GOAL = 0.5


def curve_keys(labels: list[str]) -> list[str]:
    """The entries a study reports: mean return and success, overall and per task (`success[ADC]`)."""
    return ["mean_return", "success", *(f"success[{label}]" for label in labels)]


def read_curve(path: Path, labels: list[str]) -> list[dict[str, float]]:
    """An `ocn-finetune` curve.csv as rows of env frames and `curve_keys`."""
    with open(path, newline="") as handle:
        return [{key: round(float(row[key]), 4) for key in ["frames", *curve_keys(labels)]}
                for row in csv.DictReader(handle)]


def smoothed(curve: list[dict[str, float]], key: str) -> np.ndarray:
    """One entry of a run's curve as the trailing mean over `FINAL_ROWS` iterations."""
    values = np.array([row[key] for row in curve])
    cumulative = np.concatenate([[0.0], np.cumsum(values)])
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - FINAL_ROWS, 0)
    return (cumulative[ends] - cumulative[starts]) / (ends - starts)


def at_budget(curve: list[dict[str, float]], labels: list[str]) -> dict[str, float]:
    """A run's value of every entry at the budget: the mean of its last `FINAL_ROWS` iterations."""
    return {key: float(smoothed(curve, key)[-1]) for key in curve_keys(labels)}


def over_seeds(curves: list[list[dict[str, float]]], labels: list[str]) -> dict[str, Any]:
    """The smoothed curves of several seeds on a common env-frame grid, from the frames where every run has
    scored its first iteration to those where the shortest ends: mean, std, min and max per entry."""
    grid = np.linspace(max(curve[0]["frames"] for curve in curves), min(curve[-1]["frames"] for curve in curves),
                       GRID_POINTS)
    result: dict[str, Any] = {"frames": grid.round(0).tolist()}
    for key in curve_keys(labels):
        values = np.array([np.interp(grid, [row["frames"] for row in curve], smoothed(curve, key)) for curve in curves])
        result[key] = {stat: getattr(values, stat)(0).round(4).tolist() for stat in ("mean", "std", "min", "max")}
    return result


def frames_to_reach(frames: list[float], values: list[float], target: float) -> float | None:
    """The env frames at which a curve first reaches `target` (linear between its points); None if never."""
    for k, value in enumerate(values):
        if value >= target:
            if k == 0:
                return float(frames[0])
            before = values[k - 1]
            return float(frames[k - 1] + (frames[k] - frames[k - 1]) * (target - before) / (value - before))
    return None


def sample_efficiency(ours: dict[str, Any], baselines: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """OCN's frames to 90% of its final dense return against the best baseline's frames to that return,
    from summary rows (`at_budget` and `curves` over seeds) under the dense reward."""
    target = REACH * ours["at_budget"]["mean_return"]["mean"]
    ocn = frames_to_reach(ours["curves"]["frames"], ours["curves"]["mean_return"]["mean"], target)
    theirs = {name: frames_to_reach(row["curves"]["frames"], row["curves"]["mean_return"]["mean"], target)
              for name, row in baselines.items()}
    reached = {name: frames for name, frames in theirs.items() if frames is not None}
    if reached:
        best = min(reached, key=reached.get)
        ratio = ocn / reached[best] if reached[best] else (1.0 if ocn == 0 else float("inf"))
    else:
        best = None
        ratio = ocn / max(row["curves"]["frames"][-1] for row in baselines.values())
    return {"target_return": target, "ocn_frames": ocn, "baseline_frames": theirs, "best_baseline": best,
            "ratio": ratio, "ratio_is_bound": best is None}


def plot(summary: dict[str, dict[str, Any]], names: dict[str, str], labels: list[str], title: str,
         path: Path) -> None:
    """Curves like the paper's figures 4-6: a row per reward, success per task and the mean return,
    each method's mean over seeds with a band of one standard deviation."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import EngFormatter

    keys = [*(f"success[{label}]" for label in labels), "mean_return"]
    rewards = list(dict.fromkeys(row["reward"] for row in summary.values()))
    fig, axes = plt.subplots(max(len(rewards), 1), len(keys), figsize=(3.2 * len(keys), 2.9 * max(len(rewards), 1)),
                             squeeze=False)
    for r, reward in enumerate(rewards):
        for c, key in enumerate(keys):
            ax = axes[r][c]
            for k, (method, name) in enumerate(names.items()):
                row = summary.get(f"{method} | {reward}")
                if row is None:
                    continue
                curve = {stat: np.array(values) for stat, values in row["curves"][key].items()}
                ax.plot(row["curves"]["frames"], curve["mean"], color=f"C{k}", label=name)
                ax.fill_between(row["curves"]["frames"], curve["mean"] - curve["std"], curve["mean"] + curve["std"],
                                color=f"C{k}", alpha=0.2)
            ax.set_title(f"{reward}: {key.replace('success[', 'success ').rstrip(']')}", fontsize=9)
            ax.xaxis.set_major_formatter(EngFormatter())
            ax.grid(alpha=0.3)
            if key != "mean_return":
                ax.set_ylim(-0.02, 1.02)
    axes[0][0].legend(fontsize=8)
    fig.supxlabel("env frames")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
