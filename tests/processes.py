"""This machine's processes, read from /proc: the map tests find the Ray workers running a
session, and keep to their own (by process session or by descent) when another test's Ray runs
beside them under `pytest -n 2`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

PROC = Path("/proc")


@dataclass(frozen=True)
class ProcessStat:
    state: str
    ppid: int
    session: int


def process_stat(pid: int) -> ProcessStat | None:
    """The fields of /proc/PID/stat these tests read, or None once the process is gone. The name
    comes first, in parentheses that may hold anything: the fields are read after its last ')'."""
    try:
        fields = (PROC / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()
        return ProcessStat(state=fields[0], ppid=int(fields[1]), session=int(fields[3]))
    except (OSError, IndexError, ValueError):
        return None


def command_line(pid: int) -> str:
    try:
        return (PROC / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def all_pids() -> list[int]:
    return [int(p.name) for p in PROC.iterdir() if p.name.isdigit()]


def session_workers() -> list[int]:
    """The Ray workers now running a `map` session (`SessionWorker.run_session`), any Ray's."""
    return [pid for pid in all_pids() if "SessionWorker.run_session" in command_line(pid)]


def descends_from(pid: int, ancestor: int) -> bool:
    """`pid` is a child, grandchild... of `ancestor`."""
    while pid > 1:
        stat = process_stat(pid)
        if stat is None:
            return False
        pid = stat.ppid
        if pid == ancestor:
            return True
    return False
