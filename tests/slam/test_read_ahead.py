"""ssmvpr_slam.app.read_ahead: a source read in a thread of its own, its frames and its failure
handed on in order, and a reader that stops, and releases the source, when the consumer leaves."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from frontend.errors import FrontendInputError
from ssmvpr_slam.app.read_ahead import ReadAhead


def test_items_come_in_order_and_from_another_thread() -> None:
    threads: set[str] = set()

    def source() -> Iterator[int]:
        for i in range(50):
            threads.add(threading.current_thread().name)
            yield i

    with ReadAhead(source(), depth=3) as ahead:
        assert list(ahead) == list(range(50))
        assert list(ahead) == []  # ended: stays ended
    assert threads == {"slam-read-ahead"}


def test_a_source_failure_comes_after_the_items_before_it() -> None:
    def source() -> Iterator[int]:
        yield from range(4)
        raise FrontendInputError("demo.mcap: truncated after 4 frames")

    got = []
    with ReadAhead(source(), depth=2) as ahead:
        with pytest.raises(FrontendInputError, match="truncated after 4 frames"):
            for item in ahead:
                got.append(item)
        with pytest.raises(StopIteration):
            next(ahead)
    assert got == [0, 1, 2, 3]


def test_it_reads_at_most_depth_ahead_and_leaving_stops_and_closes_the_source() -> None:
    read: list[int] = []
    closed = threading.Event()

    def source() -> Iterator[int]:
        try:
            for i in range(1000):
                read.append(i)
                yield i
        finally:
            closed.set()

    with ReadAhead(source(), depth=2) as ahead:
        assert next(ahead) == 0
        deadline = time.monotonic() + 5
        while len(read) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.2)  # time to read further, were it not bounded
        assert len(read) == 4  # 0 taken, 1 and 2 queued, 3 in the reader's hand
    assert closed.is_set()  # the generator was closed in the reader's thread before __exit__ returned
    assert len(read) == 4


def test_leaving_at_once_does_not_hang_on_a_full_queue() -> None:
    start = time.monotonic()
    with ReadAhead(iter(range(10_000)), depth=1):
        time.sleep(0.05)
    assert time.monotonic() - start < 2


def test_depth_zero_is_refused() -> None:
    with pytest.raises(ValueError, match="depth must be 1 or more"):
        ReadAhead([], 0)


def test_a_source_that_cannot_even_start_is_raised_not_waited_on() -> None:
    class Broken:
        def __iter__(self) -> Iterator[int]:
            raise FrontendInputError("demo.mcap: not an MCAP file")

    with ReadAhead(Broken(), depth=2) as ahead, pytest.raises(FrontendInputError, match="not an MCAP file"):
        next(ahead)


def test_a_reader_gone_without_its_end_is_an_error_not_a_hang(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ReadAhead, "_read", lambda self: None)  # a reader killed before it could say why
    with ReadAhead(iter(range(3)), depth=2) as ahead, pytest.raises(RuntimeError, match="ended without a word"):
        next(ahead)


def test_an_iterator_working_long_between_items_sees_the_consumer_leave() -> None:
    """The overlapped producer reads frames that make no keyframe between items: it stops on
    `cancelled` instead of reading the rest of the log after the consumer has gone."""
    read: list[int] = []

    def source() -> Iterator[int]:
        yield 0
        for i in range(1, 10_000):
            if ahead.cancelled:
                return
            read.append(i)
            time.sleep(0.001)

    ahead = ReadAhead(source(), depth=1, name="slam-front-end")
    with ahead:
        assert not ahead.cancelled and next(ahead) == 0
    assert ahead.cancelled and len(read) < 9_000
