"""How a dataset was recorded: `meta/ocn_recording.json`, one entry per `record_demos` session.

Each session stores its command, date, seed, env mode, reward and tasks, and how far it got: the
episodes it added, the episode attempts it used (the seed stream's position: `--resume` starts after
the attempts of every session), its expert failures and its `status`. The record is committed with
every chunk, not at exit, so it is exact after any kind of end: `recording` while the session runs
(and for good if a SIGKILL or a crash ends it), `finished`, `interrupted by SIGINT` or `interrupted
by SIGTERM`, or `stopped by an error`; `interrupted` is false only for a finished session. Cards,
`ocn-eval`, `ocn-push` and the reproductions read it back.
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
