"""CPU time as the benches count it: this process's and its reaped children's (an odometry process)."""

from __future__ import annotations

import resource


def cpu_seconds() -> tuple[float, float]:
    """CPU seconds used so far by this process (all its threads) and by its reaped children; a
    child's time counts once it has ended and been waited for."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime
