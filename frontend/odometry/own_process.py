"""An odometry that runs in a process of its own, so that other threads keep running beside it.

kiss-icp's Python binding holds the GIL for the whole of ``register_frame`` (tens of ms a
scan): a thread beside it cannot run a line of Python meanwhile, so overlapping odometry with
the backbone in threads gained little. Here the odometry lives in a child Python process and
``update`` waits on a socket, which releases the GIL. The child gets each frame without its
camera images (odometry never reads them) and answers with the pose, the scan kiss-icp
motion-compensated, the counters and its log records, so the parent's object reads as the
odometry itself.

The child is a fresh ``python -c`` rather than multiprocessing's spawn, which would re-run the
caller's main script in the child. A child that
dies (a C++ abort on a scan) becomes an `OdometryProcessError` naming the frame, so the caller
keeps what it processed so far instead of the whole run going down. The child has a session of
its own, so a Ctrl-C in the terminal reaches only the parent, which stops after the current
frame as it does without the child; the child ends when the parent closes the socket or exits.
POSIX only (the socket is handed over as an inherited file descriptor).

Frames go to the child from a sender thread, so a caller may hand it the next frames
(`submit`, or `submitted_ahead` over a stream of frames) before it has taken the pose of this
one: the child registers frame k+1 while the caller keeps frame k, and the poses come back in
the order the frames went. The child's reply and the next frame then cross the socket at once;
from one thread both sends could block on each other, hence the thread.
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import socket
import subprocess
import sys
import threading
import time
import weakref
from collections import deque
from collections.abc import Iterator
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from frontend.config import OdometryConfig, PoseFileConfig
from frontend.errors import FrontendError
from frontend.frame import Frame
from frontend.odometry.base import OdometryStats

_POLL_S = 0.5  # how often a wait checks that the child is still alive
_START_TIMEOUT_S = 120.0
# run by `python -c` (not -m, which would import this module twice, nor multiprocessing's spawn)
_CHILD = "import sys; from frontend.odometry.own_process import serve; serve(int(sys.argv[1]))"
_STOP = object()  # the sender's last message: tell the child to stop, then end


class OdometryProcessError(FrontendError, RuntimeError):
    """The odometry's process ended or could not start."""


class _Records(logging.Handler):
    """The child's log records, sent with the next reply and logged again by the parent."""

    def __init__(self) -> None:
        super().__init__()
        self.pending: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.pending.append((record.name, record.levelno, record.getMessage()))

    def take(self) -> list[tuple[str, int, str]]:
        taken, self.pending = self.pending, []
        return taken


def serve(fd: int) -> None:
    """The child: build the odometry from the first message, then answer one frame at a time."""
    connection = Connection(fd)
    from frontend.odometry.factory import make_in_process  # the child's only odometry import

    records = _Records()
    logging.getLogger().addHandler(records)  # warnings and above, the root logger's default
    try:
        config, pose_config, kept_voxel = connection.recv()
        odometry = make_in_process(config, pose_config, kept_voxel)
    except Exception as exc:
        connection.send(("error", _portable(exc), records.take()))
        return
    connection.send(("ready", None, records.take()))
    while True:
        try:
            frame = connection.recv()
        except (EOFError, OSError):  # the parent went away, perhaps in the middle of a frame
            return
        if frame is None:
            return
        try:
            start = time.perf_counter()
            pose = odometry.update(frame)
            seconds = time.perf_counter() - start
            scan = (getattr(odometry, "last_scan", None), getattr(odometry, "last_scan_voxel", None))
            reply: tuple[str, Any, Any] = ("pose", (pose, *scan, odometry.stats, seconds), records.take())
        except Exception as exc:
            reply = ("error", _portable(exc), records.take())
        try:
            connection.send(reply)
        except OSError:  # the parent closed the socket with frames still in flight: it wants none of them
            return


def _portable(exc: Exception) -> Exception:
    """The exception itself when it survives pickling, else a RuntimeError that says what it was."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


class _Sender:
    """The thread that writes frames to the child, in the order given; it holds no reference to
    the `OdometryProcess`, so that garbage collection still ends the child."""

    def __init__(self, connection: Connection) -> None:
        self.outbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.sent = 0  # frames written to the child
        self.failure: BaseException | None = None  # why it stopped sending (a frame that would not pickle, ...)
        self.hurry = False  # replies are left unread: the child may be blocked writing one, so do not wait on it
        self.thread = threading.Thread(target=self._send_all, args=(connection,), name="odometry-sender", daemon=True)
        self.thread.start()

    def _send_all(self, connection: Connection) -> None:
        while (message := self.outbox.get()) is not _STOP:
            try:
                connection.send(message)
            except BaseException as exc:  # the receiving side reports it (or the child's death) for the frame
                self.failure = exc
                return
            self.sent += 1
        try:
            connection.send(None)  # the child's signal to stop
        except OSError:
            pass

    def stop(self, timeout: float) -> None:
        """Drop the frames not yet sent (nobody will take their poses), send the child's stop and
        wait for that at most `timeout` seconds (a frame being sent waits for the child to read it)."""
        try:
            while True:
                self.outbox.get_nowait()
        except queue.Empty:
            pass
        self.outbox.put(_STOP)
        if threading.current_thread() is not self.thread:  # a finalizer may run in any thread, this one too
            self.thread.join(0.0 if self.hurry else timeout)


class OdometryProcess:
    """``make_odometry(config, pose_config)`` run in a child process; the same ``update``,
    ``stats`` and ``last_scan``, and ``submit`` to hand it frames ahead. ``close()`` (or garbage
    collection) ends the process."""

    def __init__(
        self, config: OdometryConfig, pose_config: PoseFileConfig | None = None, kept_voxel: float | None = None
    ) -> None:
        self.stats = OdometryStats()
        self.last_scan: np.ndarray | None = None
        self.last_scan_voxel: float | None = None
        self.last_update_s: float | None = None
        """Seconds the child spent in the last `update` itself; the rest of the caller's wait was
        the frame's way there and back (pickling, the socket, getting the GIL back)."""
        self._pending: deque[tuple[str, int]] = deque()  # frames submitted (label, number), poses not yet taken
        self._submitted = 0  # frames handed to the sender so far
        ours, theirs = socket.socketpair()
        env = dict(os.environ)  # the child imports what this process can (tools put the repo on sys.path)
        env["PYTHONPATH"] = os.pathsep.join(p for p in [*sys.path, env.get("PYTHONPATH", "")] if p)
        # the child waits for each frame: idle OpenMP threads must sleep, not spin on cores the
        # backbone needs (an explicit OMP_WAIT_POLICY in the environment wins)
        env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        with theirs:
            self._process = subprocess.Popen(
                [sys.executable, "-c", _CHILD, str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, env=env,
                start_new_session=True,  # a Ctrl-C in the terminal is the parent's to handle, not the child's
            )  # fmt: skip
        self._connection = Connection(ours.detach())
        what = f"starting {config.kind} odometry"
        try:
            self._connection.send((config, pose_config, kept_voxel))
        except OSError:
            pass  # the child is already gone: the wait below says so
        self._sender = _Sender(self._connection)
        self._closer = weakref.finalize(self, _stop, self._connection, self._process, self._sender)
        kind, payload = self._receive(what, _START_TIMEOUT_S)
        if kind == "error":
            self.close()
            raise payload

    def submit(self, frame: Frame) -> None:
        """Hand `frame` to the child now (without its images, which odometry never reads); it is
        registered while this thread goes on, and `update(frame)` takes its pose. Frames must be
        taken in the order they were submitted."""
        if not self._closer.alive:
            raise OdometryProcessError(f"{frame.label}: the odometry process was closed")
        message = replace(frame, image=None, rear_image=None)
        self._sender.outbox.put(message)
        self._pending.append((frame.label, self._submitted))
        self._submitted += 1

    def update(self, frame: Frame) -> np.ndarray:
        """The pose of `frame`: the oldest frame submitted and not yet taken, or, with none
        pending, `frame` submitted now."""
        if not self._pending:
            self.submit(frame)
        what, number = self._pending[0]
        if frame.label != what:
            raise RuntimeError(f"OdometryProcess.update: {frame.label} taken before {what}, submitted earlier")
        try:
            kind, payload = self._receive(what, None, number)
            self._pending.popleft()
        except BaseException:  # e.g. a KeyboardInterrupt mid-wait: a reply left unread would answer the next frame
            self.close()
            raise
        if kind == "error":
            raise payload
        pose, self.last_scan, self.last_scan_voxel, self.stats, self.last_update_s = payload
        return np.asarray(pose)

    def close(self) -> None:
        """End the child process (idempotent); frames still in flight are dropped."""
        self._sender.hurry = bool(self._pending)
        self._pending.clear()
        self._closer()

    def __enter__(self) -> OdometryProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _receive(self, what: str, timeout: float | None, number: int | None = None) -> tuple[str, Any]:
        """The next reply (`what` names it in errors); `number`: the submitted frame it answers,
        which a sender that failed on a later frame has still sent."""
        waited = 0.0
        while not self._connection.poll(_POLL_S):
            waited += _POLL_S
            if self._process.poll() is not None and not self._connection.poll(0):
                raise self._died(what)
            unsent = number is None or self._sender.sent <= number
            if self._sender.failure is not None and unsent and not self._connection.poll(0):
                failure = self._sender.failure
                self.close()
                raise OdometryProcessError(f"{what}: could not be sent to the odometry process ({failure})")
            if timeout is not None and waited >= timeout:
                self.close()
                raise OdometryProcessError(f"{what}: the odometry process did not answer in {timeout:.0f} s")
        try:
            kind, payload, records = self._connection.recv()
        except (EOFError, OSError) as exc:
            raise self._died(what) from exc
        for name, level, message in records:
            logging.getLogger(name).log(level, "%s", message)
        return kind, payload

    def _died(self, what: str) -> OdometryProcessError:
        try:
            code = self._process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            code = None
        self.close()
        return OdometryProcessError(f"{what}: the odometry process ended (exit code {code})")


def submitted_ahead(frames: Iterator[Frame], odometry: OdometryProcess, depth: int) -> Iterator[Frame]:
    """`frames` as they come, each handed to the odometry's process `depth` frames before it is
    yielded, so that the child registers the next frames while the caller handles this one.

    The caller must take each frame's pose (`update`) in order. A source that fails midway still
    yields the frames it gave before its fault, then raises it; frames handed over but never
    yielded (the caller stopped early, or a KeyboardInterrupt from the source, which is raised at
    once) are dropped when the odometry is closed, as it must be then."""
    window: deque[Frame] = deque()
    fault: BaseException | None = None
    ended = False
    while True:
        while not ended and len(window) <= depth:
            try:
                frame = next(frames)
            except StopIteration:
                ended = True
            except Exception as exc:  # e.g. a log cut short: raised after the frames before it
                fault, ended = exc, True
            else:
                odometry.submit(frame)
                window.append(frame)
        if window:
            yield window.popleft()
        elif fault is not None:
            raise fault
        else:
            return


def _shut(connection: Connection) -> None:
    """Shut the socket down both ways, which close() alone does not do to a send blocked in another thread."""
    sock = socket.socket(fileno=connection.fileno())  # the same descriptor, not a copy
    try:
        sock.shutdown(socket.SHUT_RDWR)
    finally:
        sock.detach()  # the Connection still owns it and closes it


def _stop(connection: Connection, process: subprocess.Popen[bytes], sender: _Sender) -> None:
    """Ask the child to stop, then make sure it has."""
    sender.stop(timeout=1.0)
    try:  # wakes a send still blocked on a child busy registering; the child's next read or reply then fails
        _shut(connection)
    except OSError:
        pass
    if threading.current_thread() is not sender.thread:
        sender.thread.join(1.0)  # its send has failed by now: the socket is not closed under it
    connection.close()  # a child still writing a reply gets EPIPE, one waiting for a frame EOF: both end
    try:
        process.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
