"""The loop that feeds a `SlamSystem`: frames in until the source ends or a stop is requested.

Mirrors kiss-icp's `OdometryPipeline`: one class owns the loop. A stop request (Ctrl-C,
SIGTERM) ends it after the current frame; a source that fails midway (a truncated log) ends
it with the frames before the fault kept; an unexpected error while processing a frame ends
it too, and the caller re-raises once the frames so far are saved. Either way the system's
`finish()` then gives a complete result of what was processed.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry.base import Odometry
from loopclosure.backbone import Backbone
from ssmvpr_slam.backend.pose_graph import PoseGraph
from ssmvpr_slam.config import SlamConfig
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.result import RunResult, StreamEnd
from ssmvpr_slam.system import RunState, SlamSystem

log = logging.getLogger(__name__)


class StopFlag:
    """Set by SIGINT/SIGTERM; the loop checks it between frames."""

    def __init__(self) -> None:
        self.requested = False

    @contextmanager
    def installed(self) -> Iterator[StopFlag]:
        def handler(signum: int, _frame: object) -> None:
            self.requested = True
            log.warning("stop requested (%s): finishing the current frame", signal.Signals(signum).name)

        if threading.current_thread() is not threading.main_thread():
            yield self  # signal handlers can only be installed from the main thread
            return
        previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            yield self
        finally:
            for s, h in previous.items():
                signal.signal(s, h)


class SlamPipeline:
    """Streams frames into a `SlamSystem` (built here, or handed in with `around`)."""

    def __init__(
        self,
        config: SlamConfig,
        odometry: Odometry,
        backbone: Backbone,
        prior_map: PriorMap | None = None,
        graph: PoseGraph | None = None,
    ) -> None:
        self._use(SlamSystem(config, odometry, backbone, prior_map, graph))

    @classmethod
    def around(cls, system: SlamSystem) -> SlamPipeline:
        """A loop feeding an existing system (e.g. one restored from a checkpoint)."""
        pipeline = cls.__new__(cls)
        pipeline._use(system)
        return pipeline

    def _use(self, system: SlamSystem) -> None:
        self.system = system
        self.stop = StopFlag()
        self.ending = StreamEnd()
        self.step_error: Exception | None = None  # the exception that ended the loop, for the caller

    # the system's parts, for callers that inspect a run (tests, benchmarks)
    @property
    def config(self) -> SlamConfig:
        return self.system.config

    @property
    def state(self) -> RunState:
        return self.system.state

    @property
    def detector(self):  # noqa: ANN201
        return self.system.detector

    @property
    def graph(self):  # noqa: ANN201
        return self.system.graph

    @property
    def odometry(self) -> Odometry:
        return self.system.odometry

    @property
    def prior_map(self) -> PriorMap | None:
        return self.system.prior_map

    def run(self, frames: Iterable[Frame], on_frame: Callable[[RunState], None] | None = None) -> RunState:
        """Process every frame (or until a stop request); returns the system's state."""
        start = time.perf_counter()
        iterator = iter(frames)
        source_error: str | None = None
        with self.stop.installed():
            while not self.stop.requested:
                try:
                    frame = next(iterator)
                except StopIteration:
                    break
                except FrontendInputError as exc:  # e.g. a log cut short: keep what came before
                    source_error = str(exc)
                    log.error("source stopped: %s", exc)
                    break
                if self.stop.requested:  # requested while the source was producing this frame
                    break
                try:
                    self.system.process(frame)
                except Exception as exc:  # keep everything processed so far; the caller re-raises
                    self.step_error = exc
                    log.exception("frame %s failed", frame.index)
                    break
                if on_frame is not None:
                    on_frame(self.state)
        error = None if self.step_error is None else f"{type(self.step_error).__name__}: {self.step_error}"
        seconds = self.ending.seconds + time.perf_counter() - start
        self.ending = StreamEnd(self.stop.requested, source_error, error, seconds)
        return self.state

    def finish(self) -> RunResult:
        """The system's result, with how the stream ended (optimises once; see SlamSystem.finish)."""
        return self.system.finish(self.ending)
