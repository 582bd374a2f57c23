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
"""

from __future__ import annotations

import logging
import os
import pickle
import socket
import subprocess
import sys
import weakref
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
        except EOFError:  # the parent went away
            return
        if frame is None:
            return
        try:
            pose = odometry.update(frame)
            scan = (getattr(odometry, "last_scan", None), getattr(odometry, "last_scan_voxel", None))
            reply: tuple[str, Any, Any] = ("pose", (pose, *scan, odometry.stats), records.take())
        except Exception as exc:
            reply = ("error", _portable(exc), records.take())
        connection.send(reply)


def _portable(exc: Exception) -> Exception:
    """The exception itself when it survives pickling, else a RuntimeError that says what it was."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


class OdometryProcess:
    """``make_odometry(config, pose_config)`` run in a child process; the same ``update``,
    ``stats`` and ``last_scan``. ``close()`` (or garbage collection) ends the process."""

    def __init__(
        self, config: OdometryConfig, pose_config: PoseFileConfig | None = None, kept_voxel: float | None = None
    ) -> None:
        self.stats = OdometryStats()
        self.last_scan: np.ndarray | None = None
        self.last_scan_voxel: float | None = None
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
        self._closer = weakref.finalize(self, _stop, self._connection, self._process)
        what = f"starting {config.kind} odometry"
        self._send((config, pose_config, kept_voxel), what)
        kind, payload = self._receive(what, _START_TIMEOUT_S)
        if kind == "error":
            self.close()
            raise payload

    def update(self, frame: Frame) -> np.ndarray:
        what = f"frame {frame.index} (t={frame.timestamp})"
        try:
            self._send(replace(frame, image=None, rear_image=None), what)
            kind, payload = self._receive(what, None)
        except BaseException:  # e.g. a KeyboardInterrupt mid-wait: a reply left unread would answer the next frame
            self.close()
            raise
        if kind == "error":
            raise payload
        pose, self.last_scan, self.last_scan_voxel, self.stats = payload
        return np.asarray(pose)

    def close(self) -> None:
        """End the child process (idempotent)."""
        self._closer()

    def __enter__(self) -> OdometryProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, message: Any, what: str) -> None:
        if not self._closer.alive:
            raise OdometryProcessError(f"{what}: the odometry process was closed")
        try:
            self._connection.send(message)
        except OSError as exc:
            raise self._died(what) from exc

    def _receive(self, what: str, timeout: float | None) -> tuple[str, Any]:
        waited = 0.0
        while not self._connection.poll(_POLL_S):
            waited += _POLL_S
            if self._process.poll() is not None and not self._connection.poll(0):
                raise self._died(what)
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


def _stop(connection: Connection, process: subprocess.Popen[bytes]) -> None:
    """Ask the child to stop, then make sure it has."""
    try:
        connection.send(None)
    except OSError:
        pass
    connection.close()  # a child still writing a reply gets EPIPE, one waiting for a frame EOF: both end
    try:
        process.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
