"""What every benchmark shares: where its result goes, what it records beside its numbers (the date,
the machine, the exact command), the report's header, and timing helpers.

Nothing here imports torch or LeRobot, so that `ocn-bench --help` stays instant.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

RESULTS = Path("results")


def machine() -> dict[str, Any]:
    """What the numbers were measured on: the CPU model, its cores, Python and the OS."""
    cpu = "unknown"
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                 if line.startswith("model name")]
        cpu = names[0] if names else cpu
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}


def add_common_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """--out and --note, which every benchmark takes."""
    parser.add_argument("--out", type=Path, default=RESULTS / f"bench_{name}.json",
                        help="JSON file to write, with its Markdown twin beside it (a relative path is under the "
                             "current folder; an existing pair is overwritten)")
    parser.add_argument("--note", default="", help="conditions of the run, stored with the results")


def int_list(text: str) -> list[int]:
    """A comma-separated list of positive integers, e.g. `1,8,64`."""
    try:
        values = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def new_result(args: argparse.Namespace) -> dict[str, Any]:
    """The fields every result starts with: which benchmark, when, where, by which command, and the note."""
    return {"benchmark": f"ocn-bench {args.benchmark}", "date": datetime.date.today().isoformat(),
            "machine": machine(), "command": args.command, "note": args.note}


def header(title: str, result: dict[str, Any]) -> str:
    """A report's title and its provenance paragraph (command, date, machine, and the note's conditions)."""
    m = result["machine"]
    conditions = f"Conditions: {result['note']}\n\n" if result["note"] else ""
    return (f"# {title}\n\n"
            f"Command: `{result['command']}`. Date: {result['date']}. Machine: {m['cpu']}, {m['cores']} cores, "
            f"Python {m['python']} ({m['platform']}).\n\n{conditions}")


def write(result: dict[str, Any], markdown: str, out: Path) -> None:
    """The JSON and its Markdown twin, overwriting the benchmark's previous pair, and the Markdown on stdout."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown)
    print(markdown)


def best_rate(call: Callable[[], None], calls: int, items_per_call: int, repeats: int = 3) -> float:
    """Items per second of `calls` calls, the best of `repeats` timings (a shared machine only ever slows
    a run down, so the fastest is the least disturbed)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            call()
        best = min(best, time.perf_counter() - start)
    return calls * items_per_call / best


def run_timed(command: Sequence[str], cwd: Path | None = None, env: dict[str, str] | None = None,
              ) -> tuple[float, str]:
    """Wall seconds of a subprocess from start to exit, and its stdout and stderr together; a failure
    raises with the output's tail."""
    start = time.perf_counter()
    proc = subprocess.run(list(command), cwd=cwd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    output = proc.stdout + proc.stderr
    if proc.returncode != 0:
        raise RuntimeError(f"{shlex.join(command)} exited with {proc.returncode}:\n{output[-4000:]}")
    return wall, output


def typed(command: Sequence[str]) -> str:
    """A command as a user types it: the environment's console scripts by name rather than by their path."""
    scripts = Path(sys.executable).parent
    return shlex.join([Path(part).name if Path(part).parent == scripts else part for part in command])
