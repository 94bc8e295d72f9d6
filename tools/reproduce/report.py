"""What the reproductions' results files share: where they came from, and their checks table."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from tools.bench import machine


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
