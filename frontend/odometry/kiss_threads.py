"""kiss-icp's thread cap holds for the whole process, and the first registration sets it.

kiss-icp's C++ `Registration` keeps its `tbb::global_control` in a function-local static, so
the `max_num_threads` of the first registration built in a process caps every registration
built after it, whatever they ask for. Measured with kiss-icp 1.3.0 on 2 cores (one process
each, three alignments of 200k points to a 400k-point map): built with 1 then with 0 ("all"),
both ran at CPU/wall 1.00; built with 0 then with 1, both at 1.96. The odometry and the loop
registration both build registrations, so in one process the first of the two settings is the
one that counts; a forked or spawned odometry process (`pipeline.overlap`) has its own.

Every registration this project builds is announced here first, so that a setting that cannot
take effect is reported instead of being silently ignored.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger(__name__)

_first: tuple[int, str] | None = None  # (cap in threads, the setting that asked for it) in this process


def thread_cap(requested: int) -> int:
    """The threads a `max_num_threads` value means: at most every core this process may run on,
    as TBB counts them (a container's CPU set, not the machine's cores); 0 is all of them. TBB
    starts no more worker threads than those cores, whatever cap is asked for."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return min(requested, cores) if requested > 0 else cores


def claim_kiss_icp_threads(requested: int, setting: str) -> int:
    """Announce a registration about to be built with `requested` threads (0: all) for
    `setting` (its config key); returns the cap it will really run with in this process."""
    global _first
    if _first is None:
        _first = (thread_cap(requested), setting)
    cap, first_setting = _first
    if thread_cap(requested) != cap:
        log.warning(
            "%s=%d has no effect in this process: kiss-icp runs every registration on %d thread(s), "
            "fixed by its first one (%s); set both to the same value",
            setting,
            requested,
            cap,
            first_setting,
        )
    return cap
