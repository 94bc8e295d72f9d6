"""How a dataset was recorded: `meta/ocn_recording.json`, one entry per `record_demos` session.

Each session stores its command, date, seed, env mode, reward and tasks, and how it ended
(episodes, attempts, expert failures, interrupted). Cards, `ocn-eval` and `ocn-push` read it back.
"""

from __future__ import annotations

import json
from pathlib import Path

PROVENANCE = "meta/ocn_recording.json"


def load_provenance(root: str | Path) -> dict:
    """The dataset's sessions, or no sessions for a dataset that record_demos did not write."""
    path = Path(root) / PROVENANCE
    return json.loads(path.read_text()) if path.is_file() else {"sessions": []}


def write_provenance(root: str | Path, provenance: dict) -> None:
    (Path(root) / PROVENANCE).write_text(json.dumps(provenance, indent=2))
