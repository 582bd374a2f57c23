"""Stopping `map` when told: the contract `run` keeps, for a job made of sessions.

The first SIGINT or SIGTERM stops the map promptly: the sessions in flight are cancelled,
those finished stay in the staging folder for the next call, and `map` says so and how to
go on. A second signal quits at once. The handlers go in after Ray has started, which
installs its own (a SIGTERM would otherwise end in Ray's C++ stack dump).
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.stop_signals import stop_signals_handled

log = logging.getLogger(__name__)


class MapStopped(SlamError):
    """`map` stopped by a signal; its finished sessions are kept in `folder`."""

    def __init__(self, signum: int, finished: int, total: int, folder: Path, abandoned: bool = False) -> None:
        self.signum = signum
        name = signal.Signals(signum).name
        how = "quit at once" if abandoned else "stopped"
        super().__init__(
            f"map {how} on {name}: {finished} of {total} session(s) finished, kept in {folder}; run the same "
            f"command again to run the rest (or add --resume {folder})"
        )


class MapStop:
    """Set by the first SIGINT / SIGTERM; the second raises KeyboardInterrupt."""

    def __init__(self) -> None:
        self.signum: int | None = None

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @contextmanager
    def installed(self) -> Iterator[MapStop]:
        def handler(signum: int, _frame: object) -> None:
            if self.signum is not None:
                raise KeyboardInterrupt
            self.signum = signum
            log.warning("%s: stopping the map; finished sessions are kept (send it again to quit at once)",
                        signal.Signals(signum).name)  # fmt: skip

        with stop_signals_handled(handler):
            yield self
