"""`ocn-bench quickstart`: `ocn-quickstart` as a user runs it, a subprocess in an empty folder, timed from
start to exit, and the NMI its `outputs/quickstart/eval.json` reports, against the quickstart's goals."""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any

from lerobot_policy_ocn.tools import console_script
from lerobot_policy_ocn.tools.bench.common import add_common_arguments, header, run_timed

WALL_GOAL_S = 240.0
NMI_GOAL = 0.9
EVAL_JSON = Path("outputs/quickstart/eval.json")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_common_arguments(parser, "quickstart")


def measure(command: list[str]) -> dict[str, Any]:
    """`command` (the quickstart) run in an empty folder: its wall seconds, and the scores of the
    `outputs/quickstart/eval.json` it writes there, against the goals."""
    with tempfile.TemporaryDirectory() as tmp:
        wall, _ = run_timed(command, cwd=Path(tmp))
        scores = json.loads((Path(tmp) / EVAL_JSON).read_text())
    return {"wall_s": wall, "nmi": scores["nmi"], "f1_tol1": scores["f1_tol1"], "wall_goal_s": WALL_GOAL_S,
            "nmi_goal": NMI_GOAL,
            "met": {"wall": wall <= WALL_GOAL_S, "nmi": scores["nmi"] is not None and scores["nmi"] >= NMI_GOAL}}


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The measurements; `ocn-bench` adds the provenance and writes the report (`markdown`)."""
    return measure([console_script("ocn-quickstart")])


def markdown(r: dict[str, Any]) -> str:
    met = {key: "met" if value else "**not met**" for key, value in r["met"].items()}
    return (
        header("Quickstart: wall time and parse quality", r)
        + "`ocn-quickstart` with its defaults, run in an empty folder as a subprocess (interpreter start, "
        "recording, training, evaluation and the viewer files included).\n\n"
        "| what | result | goal |\n|---|---|---|\n"
        f"| wall time | **{r['wall_s']:.0f} s** | <= {r['wall_goal_s']:.0f} s ({met['wall']}) |\n"
        f"| NMI (`{EVAL_JSON}`) | **{r['nmi']:.3f}** | >= {r['nmi_goal']} ({met['nmi']}) |\n"
        f"| F1@1 | {r['f1_tol1']:.3f} | |\n"
    )
