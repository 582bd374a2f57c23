"""Resident memory of this process, as the benches report it (Linux /proc and getrusage), in MiB."""

from __future__ import annotations

import resource
from pathlib import Path


def rss_mb() -> float:
    """Resident set size now."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def peak_rss_mb() -> float:
    """The largest resident set size so far (ru_maxrss is in kB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
