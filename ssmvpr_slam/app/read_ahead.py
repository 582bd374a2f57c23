"""An iterator run ahead in a thread of its own, through a bounded queue: the pipeline's one
hand-off between threads.

Why: with `pipeline.overlap` the front half of a run (source, odometry, keyframe selection)
runs ahead of the back half this way, and the source itself runs ahead of the front half: the
front end's thread used to read a frame (parsing the log, decoding the image and the cloud:
4.6 ms a demo frame on 2 cores, 6 ms on the H200's), then wait on kiss-icp, then read the next,
so every frame's reading sat on the front end's critical path. The items, and the iterator's
failure, reach the consumer in the order it gave them, so a run sees exactly what it saw without
the thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")
_POLL_S = 0.1  # how often the reader looks whether the consumer has gone


class _End:
    """The source ended (error None) or raised `error`."""

    def __init__(self, error: BaseException | None = None) -> None:
        self.error = error


class ReadAhead(Generic[T]):
    """Iterate `items` in a reader thread: `depth` items queued for the consumer and one more in
    the reader's hand at most.

    A context manager: leaving it (a stop request, an error downstream) stops the reader, which
    then closes the iterator in its own thread when it can be closed (a generator)."""

    def __init__(self, items: Iterable[T], depth: int, name: str = "slam-read-ahead") -> None:
        if depth < 1:
            raise ValueError(f"read-ahead depth must be 1 or more, got {depth}")
        self._items = items
        self._queue: queue.Queue[T | _End] = queue.Queue(depth)
        self._gone = threading.Event()  # the consumer left: the reader stops
        self._done = False
        self._thread = threading.Thread(target=self._read, name=name, daemon=True)

    @property
    def cancelled(self) -> bool:
        """The consumer has left: an iterator that works long between items may stop early."""
        return self._gone.is_set()

    def __enter__(self) -> ReadAhead[T]:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._gone.set()
        while self._thread.is_alive():  # a reader blocked on a full queue sees `_gone` at its next poll
            self._thread.join(_POLL_S)

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        if self._done:
            raise StopIteration
        while True:
            try:
                item = self._queue.get(timeout=_POLL_S)
                break
            except queue.Empty:
                if not self._thread.is_alive() and self._queue.empty():  # it cannot send its end any more
                    self._done = True
                    raise RuntimeError(f"the {self._thread.name} thread ended without a word") from None
        if isinstance(item, _End):
            self._done = True
            if item.error is not None:
                raise item.error
            raise StopIteration
        return item

    def _read(self) -> None:
        iterator: Iterator[T] | None = None
        end = _End()
        try:
            iterator = iter(self._items)
            for item in iterator:
                if not self._put(item):
                    return
        except BaseException as exc:  # noqa: BLE001  # handed to the consumer, raised there in order
            end = _End(exc)
        finally:
            close = getattr(iterator, "close", None)
            if close is not None and self._gone.is_set():
                close()
        self._put(end)

    def _put(self, item: T | _End) -> bool:
        """Queue `item`; False once the consumer has gone."""
        while not self._gone.is_set():
            try:
                self._queue.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False
