"""Command-line tools: benchmarks, evaluation, reproductions and the quickstart."""

import sys
from pathlib import Path


def console_script(name: str) -> str:
    """Path of a console script of the running environment (it sits beside the interpreter)."""
    return str(Path(sys.executable).with_name(name))
