"""What the reproductions' results files share: where they came from, their checks table, curves
summarised over seeds, and how they are written."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from tools.bench import machine


def machine_words(record: dict[str, Any]) -> str:
    """A `tools.bench.machine()` record in a few words: "AMD EPYC (2 cores)"."""
    return f"{record['cpu']} ({record['cores']} cores)"


def origin_words(result: dict[str, Any]) -> str:
    """Which command wrote the results, where and when; for a study combined from several results files
    (`ocn-reproduce combine`), the invocation behind each of them too."""
    own = f"`{result['command']}` on {machine_words(result['machine'])}, {result['date']}"
    if "sources" not in result:
        return f"Written by {own}."
    each = "; ".join(f"`{source['command']}` on {machine_words(source['machine'])}, {source['date']} "
                     f"({', '.join(source['methods'])})" for source in result["sources"])
    return f"Combined by {own}, from the results of: {each}."


def train_time_words(record: dict[str, Any]) -> str:
    """A run's training wall seconds for a table cell, saying from which step they count when the
    run's first steps were trained before invocations were timed."""
    wall, start = record["train_wall_s"], record.get("train_timed_from_step", 0)
    if wall is None:
        return "not timed"
    return f"{wall:.0f}" if start == 0 else f"{wall:.0f} (steps {start}+)"


def provenance(args: argparse.Namespace) -> dict[str, Any]:
    """The command line, date, machine and every setting of this invocation, so that a results file
    says how to make it again and what it was measured on."""
    return {
        "command": "ocn-reproduce " + " ".join(sys.argv[1:] if args.argv is None else args.argv),
        "date": time.strftime("%Y-%m-%d"),
        "machine": machine(),
        "settings": {key: str(value) if isinstance(value, Path) else value for key, value in vars(args).items()
                     if key not in ("func", "argv")},
    }


def checks_table(checks: list[dict[str, Any]]) -> list[str]:
    """A study's checks as Markdown table lines: what is checked, the measured value and whether it
    holds ("n/a" for a check that cannot be made; its text says why)."""
    lines = ["| check | measured | holds |", "|---|---|---|"]
    for check in checks:
        value = "n/a" if check["value"] is None else f"{check['value']:.3f}"
        holds = "n/a" if check["holds"] is None else "yes" if check["holds"] else "NO"
        lines.append(f"| {check['check']} | {value} | {holds} |")
    return lines


def over_seeds(values: np.ndarray) -> dict[str, list[float]]:
    """Mean, std, min and max over seeds of curves [seeds, points] sampled at the same points, for
    the mean line and the band (one std or min-max) of a study's plot."""
    return {stat: getattr(values, stat)(0).round(4).tolist() for stat in ("mean", "std", "min", "max")}


def write_result_files(results: Path, name: str, result: dict[str, Any], text: str) -> Path:
    """`results/NAME.json` (the result) and `results/NAME.md` (its Markdown `text`); returns the
    path stem `results/NAME`, beside which a study puts its plots."""
    results.mkdir(parents=True, exist_ok=True)
    stem = results / name
    stem.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    stem.with_suffix(".md").write_text(text)
    return stem
