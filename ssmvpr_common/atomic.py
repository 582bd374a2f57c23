"""Atomic file writes: a temp file in the target's folder, fsync, then ``os.replace``.

A crash mid-write leaves either the old file or none, never a truncated one that a later
reader would take for a complete (shorter) file. A full disk is a `DiskFullError` naming the
target, whoever wrote short (numpy's short write carries no errno): `disk_full.writing`.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO

from ssmvpr_common.disk_full import writing


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], object]) -> Path:
    """Call ``write(handle)`` on a temp file next to ``path``, then move it into place."""
    target = Path(path)
    with writing(target):
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as handle:
                write(handle)
                handle.flush()
                os.fsync(handle.fileno())
            os.chmod(tmp, default_file_mode())  # mkstemp makes 0600; give the usual umask'd mode
            os.replace(tmp, target)
        except OSError as exc:
            Path(tmp).unlink(missing_ok=True)
            if exc.filename is None:  # a write or fsync that failed (a full disk) names no file: name the target
                raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from None
            raise
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return target


def default_file_mode() -> int:
    """Permissions a plain ``open(..., "w")`` would give."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` atomically."""
    return atomic_write(path, lambda handle: handle.write(data))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 text atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))
