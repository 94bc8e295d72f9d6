"""What every study's results files share: the JSON's provenance (the exact command, date, machine,
settings), its checks, and the three files, `NAME.json`, `NAME.md` (the checks table first) and
`NAME.png`, written together so that they always describe the same runs."""

from __future__ import annotations

import json
import shlex
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools.bench.common import machine


def provenance(argv: Sequence[str], settings: dict[str, Any]) -> dict[str, Any]:
    """The command line that wrote a results file, its date, the machine (CPU model and cores) and the
    study's settings, so that the file says how to make it again and what it was measured on."""
    found = machine()
    return {"command": shlex.join(["ocn-reproduce", *argv]), "date": time.strftime("%Y-%m-%d"),
            "machine": {"cpu": found["cpu"], "cores": found["cores"]}, "settings": settings}


def origin_words(result: dict[str, Any]) -> str:
    """Which command wrote the results, where and when; for a combined study, each source's too."""
    def one(record: dict[str, Any]) -> str:
        machine = record["machine"]
        return f"`{record['command']}` on {machine['cpu']} ({machine['cores']} cores), {record['date']}"

    if "sources" not in result:
        return f"Written by {one(result)}."
    return f"Combined by {one(result)} from: " + "; ".join(one(source) for source in result["sources"]) + "."


def check(name: str, value: float | None, test: Callable[[float], bool]) -> dict[str, Any]:
    """One check: what is checked, the measured value and whether it passes `test`; a value of None (its
    runs are not in the results) makes a check marked not run."""
    if value is None:
        return {"check": f"{name} (not run)", "value": None, "holds": None}
    return {"check": name, "value": value, "holds": bool(test(value))}


def checks_table(checks: list[dict[str, Any]]) -> list[str]:
    """The checks as Markdown table lines."""
    lines = ["| check | measured | holds |", "|---|---|---|"]
    for entry in checks:
        value = "n/a" if entry["value"] is None else f"{entry['value']:.3f}"
        holds = "n/a" if entry["holds"] is None else "yes" if entry["holds"] else "NO"
        lines.append(f"| {entry['check']} | {value} | {holds} |")
    return lines


def rates_cell(rates: dict[str, float]) -> str:
    """Success rates per task (or PIN) for a table cell."""
    return "; ".join(f"{task}: {rate:.2f}" for task, rate in rates.items())


def seconds_cell(wall_s: float | None) -> str:
    """A command's wall seconds for a table cell ("not timed": it ran before timings were kept, or its
    start was lost to an interruption)."""
    return "not timed" if wall_s is None else f"{wall_s:.0f}"


def mean_std(values: Sequence[float]) -> dict[str, float]:
    """Mean and (population) standard deviation over seeds."""
    import numpy as np

    return {"mean": float(np.mean(values)), "std": float(np.std(values))}


def write_results(results: Path, name: str, result: dict[str, Any], markdown: str,
                  figure: Callable[[Path], None]) -> None:
    """`results/NAME.{json,md,png}`: the result, its Markdown and the figure that `figure` draws."""
    import matplotlib

    matplotlib.use("Agg")
    results.mkdir(parents=True, exist_ok=True)
    stem = results / name
    stem.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    stem.with_suffix(".md").write_text(markdown)
    figure(stem.with_suffix(".png"))
