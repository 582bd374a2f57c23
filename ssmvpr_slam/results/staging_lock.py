"""Whether a staging folder's writer still lives, so a folder left by a killed call can be told
from one another call is writing right now.

A writer holds an exclusive `flock` on a file inside its staging folder for as long as it runs;
the kernel drops the lock when the process ends, however it ends (SIGKILL and out-of-memory
included). A later call that can take the lock knows the folder is left over. A folder too
young to hold its lock file yet is taken to be in use.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import time
from pathlib import Path

LOCK_NAME = ".writer.lock"
_GRACE_S = 60.0  # a folder this young without its lock file may be in the instant before the lock


class StagingLock:
    """The exclusive lock a writer holds on its staging folder; `release` before publishing."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / LOCK_NAME
        self._fd: int | None = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._fd)
            self._fd = None
            raise

    def release(self, keep_file: bool = False) -> None:
        """Drop the lock, and its file unless `keep_file` (a folder left for a later call keeps it,
        so that call sees a lock no one holds; a published folder carries neither)."""
        if self._fd is None:
            return
        if not keep_file:
            self.path.unlink(missing_ok=True)
        os.close(self._fd)
        self._fd = None


def in_use(folder: Path) -> bool:
    """True while another process holds `folder`'s lock (or may be about to take it)."""
    lock = folder / LOCK_NAME
    if not lock.exists():
        try:
            return time.time() - folder.stat().st_mtime < _GRACE_S
        except OSError:
            return True  # gone meanwhile: not ours to touch
    try:
        fd = os.open(lock, os.O_RDWR)
    except OSError:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)  # closing drops the lock this probe took
    return False


def left_over(base: Path, name: str) -> list[Path]:
    """Staging folders of command `name` in `base` that no live call holds, newest first."""
    pattern = re.compile(rf"^\.{re.escape(name)}_\d{{4}}-\d\d-\d\d_\d\d-\d\d-\d\d\..+\.partial$")
    if not base.is_dir():
        return []
    found = [p for p in base.iterdir() if pattern.match(p.name) and p.is_dir() and not p.is_symlink()]
    return sorted((p for p in found if not in_use(p)), key=lambda p: p.name, reverse=True)


def remove_left_over(base: Path, name: str) -> list[Path]:
    """Remove what killed calls of `name` left in `base`: their staging folders, and folders a
    replacement renamed aside (`.<target>.*.replaced`) whose target was already put in place."""
    removed = left_over(base, name)
    if base.is_dir():
        for aside in base.glob(f".{name}_*.replaced"):
            target = base / aside.name[1:].split(".", 1)[0]
            if aside.is_dir() and target.is_dir() and not in_use(aside):
                removed.append(aside)
    for folder in removed:
        shutil.rmtree(folder, ignore_errors=True)
    return removed
