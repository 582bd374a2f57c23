"""A full disk at a write is one error naming the file and the room left: Python's ENOSPC and
EDQUOT, and numpy's short write, which carries no errno ('84800 requested and 65504 written')
and before reached the user as a traceback."""

from __future__ import annotations

import errno
import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ssmvpr_common.atomic import atomic_write, atomic_write_bytes
from ssmvpr_common.disk_full import DiskFullError, is_disk_full, writing
from ssmvpr_common.errors import SsmvprError

ROOT = Path(__file__).resolve().parents[2]

# a real short write: the file-size limit (SIGXFSZ ignored) makes fwrite stop at 64 KiB, as a
# full disk does, and numpy raises what it raises for a full disk
_SHORT_WRITE = textwrap.dedent(
    """
    import resource, signal, sys
    import numpy as np
    from ssmvpr_common.atomic import atomic_write
    from ssmvpr_common.disk_full import DiskFullError

    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))
    try:
        atomic_write(sys.argv[1], lambda handle: np.save(handle, np.zeros(100_000), allow_pickle=False))
    except DiskFullError as exc:
        print(exc)
    """
)


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE is POSIX's")
def test_numpys_real_short_write_is_a_disk_full_error_naming_the_target(tmp_path: Path) -> None:
    target = tmp_path / "database" / "stage1.npy"
    target.parent.mkdir()
    target.write_bytes(b"the previous version")
    done = subprocess.run([sys.executable, "-c", _SHORT_WRITE, str(target)], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    line = done.stdout.strip()
    assert line.startswith(f"{target}: disk full while writing it (short write: "), line
    assert "of 100,000 items written" in line and " free on " in line, line
    assert target.read_bytes() == b"the previous version"  # the old file stays whole
    assert sorted(p.name for p in target.parent.iterdir()) == ["stage1.npy"]  # no temp file left


@pytest.mark.parametrize(
    ("error", "full"),
    [
        (OSError(errno.ENOSPC, "No space left on device"), True),
        (OSError(errno.EDQUOT, "Disk quota exceeded"), True),
        (OSError("84800 requested and 65504 written"), True),  # numpy's, as raised
        (OSError(None, "84800 requested and 65504 written", "/x/stage1.npy"), True),  # renamed by atomic_write
        (OSError(errno.EPIPE, "Broken pipe"), False),
        (OSError("disk full"), False),  # no errno and not numpy's words: not guessed at
        (OSError(errno.EIO, "84800 requested and 65504 written"), False),  # an errno says what it was
        (ValueError("84800 requested and 65504 written"), False),
    ],
)
def test_what_counts_as_a_full_disk(error: BaseException, full: bool) -> None:
    assert is_disk_full(error) is full


def test_a_full_disk_inside_an_atomic_write_names_the_target_and_the_room_left(tmp_path: Path) -> None:
    target = tmp_path / "out.bin"
    atomic_write_bytes(target, b"complete")

    def fills_up(handle: object) -> None:
        handle.write(b"half")  # type: ignore[attr-defined]
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(DiskFullError) as caught:
        atomic_write(target, fills_up)
    error = caught.value
    assert isinstance(error, SsmvprError) and isinstance(error, OSError) and error.errno == errno.ENOSPC
    assert error.filename == str(target)
    assert str(error).startswith(f"{target}: disk full while writing it (No space left on device; ")
    assert " free on " in str(error) and "\n" not in str(error)
    assert target.read_bytes() == b"complete" and os.listdir(tmp_path) == ["out.bin"]


def test_writing_converts_only_a_full_disk() -> None:
    with pytest.raises(DiskFullError, match="disk quota exceeded while writing it"), writing("/x/y.mcap"):
        raise OSError(errno.EDQUOT, "Disk quota exceeded")
    with pytest.raises(PermissionError), writing("/x/y.mcap"):
        raise PermissionError(errno.EACCES, "Permission denied")


def test_the_error_crosses_processes_whole(tmp_path: Path) -> None:
    """A `map` session runs on a Ray worker: its error is pickled to the driver."""
    error = DiskFullError.of(tmp_path / "stage1.npy", OSError("84800 requested and 65504 written"))
    error.advice = "free space, then resume"
    copy = pickle.loads(pickle.dumps(error))
    assert str(copy) == str(error) and copy.errno == errno.ENOSPC and copy.advice == error.advice


def test_numpy_still_writes_whole_files_through_the_atomic_writer(tmp_path: Path) -> None:
    target = tmp_path / "a.npy"
    atomic_write(target, lambda handle: np.save(handle, np.arange(1000), allow_pickle=False))
    assert np.load(target).tolist() == list(range(1000))
