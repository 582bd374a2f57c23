"""A full disk (or quota) at a write: one error naming the file, the space left and what to do.

Python's file objects report a full disk as ENOSPC (EDQUOT for a quota), but numpy writes an
array to a real file with C's fwrite and reports the short write as ``OSError: 84800 requested
and 65504 written``, with no errno and no file: a run's final write once ended in that traceback.
`writing(path)` turns both into a `DiskFullError` naming the file; `atomic_write`, the layer
every result and checkpoint file goes through, writes inside it, and so do the writers that
stream into a file of their own (an MCAP log, a place database growing in its folder).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ssmvpr_common.errors import SsmvprError

_SHORT_WRITE = re.compile(r"(\d+) requested and (\d+) written")  # numpy's words for a short fwrite
_NO_ROOM = frozenset({errno.ENOSPC, errno.EDQUOT})


def is_disk_full(exc: BaseException) -> bool:
    """An OSError that says the write found no room: ENOSPC, EDQUOT, or a short write without an
    errno (numpy's `requested and written`)."""
    if not isinstance(exc, OSError):
        return False
    if exc.errno in _NO_ROOM:
        return True
    return exc.errno is None and _SHORT_WRITE.fullmatch(_reason_text(exc)) is not None


def _reason_text(exc: OSError) -> str:
    if exc.strerror:
        return str(exc.strerror)
    return str(exc.args[0]) if len(exc.args) == 1 else str(exc)


class DiskFullError(SsmvprError, OSError):
    """A write the disk (or the quota) had no room for. `advice` says what to do (the CLI adds
    where results can go instead, a run where its last checkpoint is); it derives from OSError so
    a caller that catches a failed write (a checkpoint that cannot be written) still catches it."""

    def __init__(
        self,
        path: str | os.PathLike[str] | None,
        detail: str,
        code: int = errno.ENOSPC,
        free: str | None = None,
        advice: str | None = None,
    ) -> None:
        super().__init__(code, detail, None if path is None else str(path))
        self.path = None if path is None else Path(path)
        self.detail = detail
        self._free = free
        self.advice = advice

    @property
    def free(self) -> str | None:
        """The room left where `path` is, measured when first asked: by then the writer has
        removed its partial file (its space is free again)."""
        if self._free is None and self.path is not None:
            self._free = free_space(self.path)
        return self._free

    @classmethod
    def of(cls, path: str | os.PathLike[str] | None, cause: OSError) -> DiskFullError:
        """The error for `cause` (an OSError `is_disk_full` accepts) raised writing `path`."""
        reason = _reason_text(cause)
        short = _SHORT_WRITE.fullmatch(reason) if cause.errno is None else None
        # numpy counts array items, not bytes
        detail = reason if short is None else f"short write: {int(short[2]):,} of {int(short[1]):,} items written"
        return cls(path, detail, cause.errno if cause.errno is not None else errno.ENOSPC)

    def __reduce__(self) -> tuple[type[DiskFullError], tuple[object, ...]]:
        # across processes (a `map` session on a Ray worker) with its fields, not OSError's args
        return type(self), (self.path, self.detail, self.errno, self.free, self.advice)

    def __str__(self) -> str:
        what = "disk quota exceeded" if self.errno == errno.EDQUOT else "disk full"
        detail = self.detail if self.free is None else f"{self.detail}; {self.free}"
        where = "" if self.path is None else f"{self.path}: "
        advice = f"; {self.advice}" if self.advice else ""
        return f"{where}{what} while writing {'it' if where else 'a file'} ({detail}){advice}"


@contextmanager
def writing(path: str | os.PathLike[str]) -> Iterator[None]:
    """Writes to `path` inside the block: an OSError that means a full disk becomes a
    `DiskFullError` naming `path`; any other error passes unchanged."""
    try:
        yield
    except DiskFullError:
        raise
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        raise DiskFullError.of(path, exc) from exc


def free_space(path: str | os.PathLike[str]) -> str:
    """'12.0 MiB free on /mnt/data': the room left on the file system that holds `path`."""
    place = Path(os.path.abspath(path))
    while not place.exists() and place != place.parent:
        place = place.parent
    try:
        free = shutil.disk_usage(place).free
    except OSError:
        return "free space unknown"
    mount = place
    while not os.path.ismount(mount) and mount != mount.parent:
        mount = mount.parent
    return f"{_size(free)} free on {mount}"


def _size(count: int) -> str:
    if count < 1 << 20:
        return f"{count:,} bytes"
    for unit, shift in (("TiB", 40), ("GiB", 30), ("MiB", 20)):
        if count >= 1 << shift:
            return f"{count / (1 << shift):.1f} {unit}"
    raise AssertionError(count)  # pragma: no cover - every count of a MiB or more has a unit above
