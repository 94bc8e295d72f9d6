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
import signal
import subprocess
import sys
import threading
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


# LeRobot's training script ends with `accelerator.end_training()`, whose `destroy_process_group()` can
# leave a rank waiting forever once its peer has exited (pytorch/pytorch#75097). It happened here once, in
# a full test run: rank 0 sat idle in a futex wait for 18 minutes after logging the end of training, its
# checkpoint written and its peer gone. 42 runs of the same command afterwards (alone, two at once, beside
# two busy loops) all exited.
TEARDOWN_GRACE_S = 120.0
TEARDOWN_STOPPED = "ocn-bench: stopped the run's processes"


def run_timed(command: Sequence[str], cwd: Path | None = None, env: dict[str, str] | None = None,
              ends_at: str | None = None) -> tuple[float, str]:
    """Wall seconds of a subprocess from start to exit, and its output (stdout and stderr as they came); a
    failure raises with the output's tail. The command runs in a session of its own, so that whatever it
    starts (torchrun's ranks) goes with it. With `ends_at`, a line of its log that marks the work as done,
    a run still alive TEARDOWN_GRACE_S after that line is stopped: its wall time ends at the line, and its
    output ends with a line that starts with TEARDOWN_STOPPED, for the caller to report."""
    start = time.perf_counter()
    lines: list[str] = []
    done_at: list[float] = []
    with subprocess.Popen(list(command), cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, start_new_session=True) as proc:
        def read() -> None:
            try:
                for line in proc.stdout:
                    lines.append(line)
                    if ends_at is not None and not done_at and ends_at in line:
                        done_at.append(time.perf_counter())
            except (OSError, ValueError):  # the pipe closed under a stopped run
                return

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        stopped = False
        while proc.poll() is None:
            if done_at and time.perf_counter() - done_at[0] > TEARDOWN_GRACE_S:
                stop(proc)
                stopped = True
                break
            time.sleep(0.2)
        wall = (done_at[0] if stopped else time.perf_counter()) - start
        if stopped:
            reader.join(timeout=5.0)
            lines.append(f"{TEARDOWN_STOPPED} {TEARDOWN_GRACE_S:.0f} s after {ends_at!r}: they had not exited\n")
        else:
            reader.join()
    output = "".join(lines)
    if proc.returncode != 0 and not stopped:
        raise RuntimeError(f"{shlex.join(command)} exited with {proc.returncode}:\n{output[-4000:]}")
    return wall, output


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM, which torchrun passes on to its ranks (each in a session of its own), then SIGKILL to the
    command's session if it is still there a minute later."""
    proc.terminate()
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def typed(command: Sequence[str]) -> str:
    """A command as a user types it: the environment's console scripts by name rather than by their path."""
    scripts = Path(sys.executable).parent
    return shlex.join([Path(part).name if Path(part).parent == scripts else part for part in command])
