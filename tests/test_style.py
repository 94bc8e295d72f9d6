"""The code stays clean of what ruff catches (pyproject's `[tool.ruff]`): unused names, likely bugs
such as closures over loop variables or zips of unequal lengths, and lines over 120 characters."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUFF = Path(sys.executable).with_name("ruff")


def ruff_check(*paths: Path) -> subprocess.CompletedProcess[str]:
    command = [str(RUFF), "check", "--no-cache", "--output-format", "concise",
               "--config", str(ROOT / "pyproject.toml"), *map(str, paths)]
    return subprocess.run(command, capture_output=True, text=True, cwd=ROOT, check=False)


def test_the_project_passes_ruff() -> None:
    result = ruff_check(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_flags_what_the_project_config_selects(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text("import os\n\n\ndef f() -> None:\n    x = 1\n\n\n" f"NAME = '{'a' * 120}'\n")
    result = ruff_check(sample)
    assert result.returncode == 1
    assert {"F401", "F841", "E501"} <= {line.split(" ")[1] for line in result.stdout.splitlines() if ": " in line}
