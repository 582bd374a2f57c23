"""SIGINT and SIGTERM handled for a block: what `run`'s frame loop, a results write and `map` each
do with a stop request differs, how the handlers go in and come out does not."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def stop_signals_handled(handler: Callable[[int, Any], None]) -> Iterator[None]:
    """`handler` on SIGINT and SIGTERM for the block, the previous handlers put back after. Off
    the main thread, where Python installs no handler, the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, handler) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
