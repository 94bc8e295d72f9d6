"""Checks of command-line outputs and ids, run before any work so that a bad one costs nothing.

Every tool that writes refuses, in one line naming the path or the id and the fix, before it reads a
checkpoint or records an episode: an output folder it could not write in (read-only, no permission,
a file where a folder should be) and a repo id that is not ORG/NAME.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def check_repo_id(repo_id: str, flag: str = "--repo-id") -> None:
    """A Hub repo id is ORG/NAME: exactly one slash, and characters the Hub accepts."""
    from huggingface_hub.utils import HFValidationError, validate_repo_id

    if repo_id.count("/") != 1 or not all(repo_id.split("/")):
        raise ValueError(f"{flag} {repo_id!r} must be ORG/NAME with exactly one slash (e.g. local/craft_s1).")
    try:
        validate_repo_id(repo_id)
    except HFValidationError as error:
        raise ValueError(f"{flag} {repo_id!r} is not a valid Hub repo id: {error}") from None


def check_can_create(path: str | Path, flag: str) -> None:
    """Refuse an output path that cannot be created: the nearest folder that exists above it must
    take a new file (a probe file, removed at once, asks the filesystem itself, so a read-only mount,
    a missing permission and a full quota all answer here)."""
    path = Path(path)
    folder = path.absolute().parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{flag} {path}: {folder} is a file, not a folder; choose another path.")
    try:
        descriptor, probe = tempfile.mkstemp(prefix=".ocn-write-check-", dir=folder)
    except OSError as error:
        raise ValueError(
            f"{flag} {path}: cannot write in {folder} ({error.strerror}); choose a folder you can write to."
        ) from None
    os.close(descriptor)
    os.unlink(probe)
