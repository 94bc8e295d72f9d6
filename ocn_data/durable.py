"""Files and folders that a SIGKILL, a full disk or a power cut cannot leave half-written.

`write_atomic(path, data)` and `atomic_output(path)`: one file, written to a hidden temporary name
beside it (`.NAME.ocn-partial`), fsynced and `os.replace`d over the target, so the path holds the old
content or the new one, never a part.

`FolderTransaction(root)`: a new version of a whole folder (a dataset), built beside it in
`.NAME.ocn-staging` from hard links to the current files plus the new and rewritten ones, fsynced,
then swapped with the folder in one step: Linux's `renameat2(RENAME_EXCHANGE)`. A LeRobot dataset
is several files that must agree (data files, episode tables, `meta/info.json`, statistics); no
order of single-file renames keeps them in agreement at every instant, one swap of the folder does.
Readers see the old version or the new one. A file is never changed in place: a rewritten file is
a new inode (`fresh`), so the hard links of the old version keep its content.

Where the system cannot exchange two folders (not Linux, or a filesystem without it), the swap is
two renames (the folder to `.NAME.ocn-previous`, the staged one into place); `recover` puts the
previous version back if a kill fell between them. What an interrupted transaction leaves beside the
folder is always one of these two names, and `recover` (run by `record_demos` and `ocn-doctor
--repair`) removes it.
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

STAGING_SUFFIX = ".ocn-staging"
PREVIOUS_SUFFIX = ".ocn-previous"
PARTIAL_SUFFIX = ".ocn-partial"
# renameat2() arguments: relative paths resolve from the working directory; swap the two paths.
AT_FDCWD = -100
RENAME_EXCHANGE = 2
# What renameat2() answers where the kernel or the filesystem cannot exchange.
EXCHANGE_UNSUPPORTED = {errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP}


def fsync_path(path: Path) -> None:
    """Flush a file's or a folder's entries to the disk (a folder: the names it holds)."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


@contextmanager
def atomic_output(path: str | Path) -> Iterator[BinaryIO]:
    """A binary handle whose content replaces `path` only once it is complete and on the disk: a
    crash or an error leaves the old file (or none), never a part of the new one."""
    path = Path(path)
    partial = path.with_name(f".{path.name}{PARTIAL_SUFFIX}")
    try:
        with open(partial, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


def write_atomic(path: str | Path, data: bytes | str) -> None:
    """Write `data` to `path` so that a crash leaves the old file or the new one, never a part."""
    with atomic_output(path) as handle:
        handle.write(data.encode() if isinstance(data, str) else data)


def staging_path(root: Path) -> Path:
    """Where a transaction builds the next version of `root` (and, after the swap, holds the old one)."""
    return root.parent / f".{root.name}{STAGING_SUFFIX}"


def previous_path(root: Path) -> Path:
    """Where the two-rename swap parks the current version of `root` for an instant."""
    return root.parent / f".{root.name}{PREVIOUS_SUFFIX}"


def leftovers(root: Path) -> list[Path]:
    """What interrupted transactions left beside `root`."""
    return [path for path in (staging_path(root), previous_path(root)) if path.exists()]


def recover(root: str | Path) -> list[str]:
    """Undo what an interrupted transaction left beside `root`: the previous version goes back in
    place if the folder is missing, the rest is removed. Returns one line per thing done."""
    root = Path(root)
    done = []
    previous = previous_path(root)
    if previous.exists() and not root.exists():
        previous.rename(root)
        done.append(f"restored {root} from {previous}, where a swap cut off by a kill had left it")
    for leftover in leftovers(root):
        shutil.rmtree(leftover)
        done.append(f"removed {leftover}, left by a write cut off by a kill")
    return done


def _exchange(first: Path, second: Path) -> bool:
    """Swap two paths in one step; False where the system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    renameat2 = getattr(ctypes.CDLL(None, use_errno=True), "renameat2", None)
    if renameat2 is None:
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(AT_FDCWD, os.fsencode(first), AT_FDCWD, os.fsencode(second), RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in EXCHANGE_UNSUPPORTED:
        return False
    raise OSError(code, os.strerror(code), str(second))


def _link_tree(source: Path, target: Path) -> None:
    """`target` as a copy of the folder `source` made of hard links (copies where links fail)."""
    for folder, subfolders, files in os.walk(source):
        relative = Path(folder).relative_to(source)
        (target / relative).mkdir()
        for name in [*files, *(d for d in subfolders if (Path(folder) / d).is_symlink())]:
            origin, copy = Path(folder) / name, target / relative / name
            if origin.is_symlink():
                copy.symlink_to(os.readlink(origin))
                continue
            try:
                os.link(origin, copy)
            except OSError:  # a filesystem without hard links: a copy is slower, as safe
                shutil.copy2(origin, copy)


class FolderTransaction:
    """The next version of the folder `root`, built beside it and swapped in by `publish`.

    Write new or rewritten files at the paths `fresh(relative)` gives, call `publish()`, and always
    `discard()` at the end (before publishing it drops the new version, after it the old one).
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.staging = staging_path(self.root)
        self._written: list[Path] = []
        if self.staging.exists():
            shutil.rmtree(self.staging)
        self.root.parent.mkdir(parents=True, exist_ok=True)
        if self.root.exists():
            _link_tree(self.root, self.staging)
        else:
            self.staging.mkdir()

    def fresh(self, relative: str | Path) -> Path:
        """The staged path of `relative`, emptied for a new file: the old version keeps its own."""
        path = self.staging / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.unlink(missing_ok=True)
        self._written.append(path)
        return path

    def remove(self, relative: str | Path) -> None:
        """Leave `relative` out of the new version."""
        (self.staging / relative).unlink()

    def publish(self) -> None:
        """Flush the new version to the disk, then put it in place of the folder in one step."""
        for path in self._written:
            if path.exists():
                fsync_path(path)
        for folder, _, _ in os.walk(self.staging):
            fsync_path(Path(folder))
        if not self.root.exists():
            self.staging.rename(self.root)
        elif not _exchange(self.staging, self.root):
            previous = previous_path(self.root)
            self.root.rename(previous)
            self.staging.rename(self.root)
            shutil.rmtree(previous)
        fsync_path(self.root.parent)

    def discard(self) -> None:
        """Remove the staging folder: the unpublished version, or after `publish` the replaced one."""
        shutil.rmtree(self.staging, ignore_errors=True)
