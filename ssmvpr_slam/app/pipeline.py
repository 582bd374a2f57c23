"""The loop that feeds a `SlamSystem`: frames in until the source ends or a stop is requested.

Mirrors kiss-icp's `OdometryPipeline`: one class owns the loop. A stop request (Ctrl-C,
SIGTERM) ends it after the current frame; a source that fails midway (a truncated log) ends
it with the frames before the fault kept; an unexpected error while processing a frame ends
it too, and the caller re-raises once the frames so far are saved. Either way the system's
`finish()` then gives a complete result of what was processed.

With `pipeline.overlap` the source, the odometry and keyframe selection (`SlamSystem.front`)
run in a producer thread that hands keyframes to this thread (`SlamSystem.back`: backbone,
recognition, registration, iSAM2) through a queue of `pipeline.overlap_queue_keyframes`
(`ReadAhead`), so decoding and kiss-icp proceed while the backbone runs; the source itself reads
`pipeline.read_ahead_frames` frames ahead in a thread of its own the same way, so decoding a frame
overlaps kiss-icp's registration of the one before. kiss-icp keeps the GIL while it
registers a scan, so the runner then builds the odometry in a process of its own
(`OdometryProcess`) and the producer thread only waits on it; that process gets each frame
`pipeline.odometry_ahead_frames` frames early (`submitted_ahead`), so it registers the next scan
while the producer keeps this keyframe. With `pipeline.encode_ahead` the keyframes pass through
an encoder thread on their way (`_encoded_ahead`), so the backbone encodes the next keyframe while
this one is recognised. Signals, progress and checkpoints stay
in the calling thread. On a stop request the producer takes no further frame (those read ahead
are dropped) and the keyframes already queued are still processed (at most the queue's length,
and the two in the encoder's hand and queue),
so the result covers exactly the frames taken; the back half sees the same keyframes in the same order as without overlap.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, replace

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry.base import Odometry
from frontend.odometry.own_process import OdometryProcess, submitted_ahead
from loopclosure.backbone import Backbone
from ssmvpr_common.errors import SsmvprError
from ssmvpr_slam.app.heap import HeapTrimmer
from ssmvpr_slam.app.read_ahead import ReadAhead
from ssmvpr_slam.app.realtime import SensorClock
from ssmvpr_slam.backend.pose_graph import PoseGraph
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.run_result import RunResult, StreamEnd
from ssmvpr_slam.run_state import KeyframeInput, RunState
from ssmvpr_slam.stop_signals import stop_signals_handled
from ssmvpr_slam.system import SlamSystem

log = logging.getLogger(__name__)


@dataclass
class _ProducerEnd:
    """Why the producer stopped reading (filled in its thread, read here once it has ended)."""

    source_error: str | None = None
    error: Exception | None = None


class StopFlag:
    """Set by SIGINT/SIGTERM; the loop checks it between frames."""

    def __init__(self) -> None:
        self.requested = False

    @contextmanager
    def installed(self) -> Iterator[StopFlag]:
        def handler(signum: int, _frame: object) -> None:
            self.requested = True
            log.warning("stop requested (%s): finishing the current frame", signal.Signals(signum).name)

        with stop_signals_handled(handler):
            yield self


class SlamPipeline:
    """Streams frames into a `SlamSystem` (handed in, or built from its parts with `build`)."""

    def __init__(self, system: SlamSystem) -> None:
        """A loop feeding `system` (built with `build`, or restored from a checkpoint)."""
        self.system = system
        self.stop = StopFlag()
        self.ending = StreamEnd()
        self.step_error: Exception | None = None  # the exception that ended the loop, for the caller
        self.heap = HeapTrimmer(self.config.pipeline.release_heap_every_keyframes)
        # `run --realtime`: frames at their recorded rate, late keyframes without recognition
        self.clock: SensorClock | None = None

    @classmethod
    def build(
        cls,
        config: SlamConfig,
        odometry: Odometry,
        backbone: Backbone,
        prior_map: PriorMap | None = None,
        graph: PoseGraph | None = None,
    ) -> SlamPipeline:
        """A pipeline around a new `SlamSystem` of these parts."""
        return cls(SlamSystem(config, odometry, backbone, prior_map, graph))

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
        """Process every frame (or until a stop request); returns the system's state.

        on_frame is called after each frame (with overlap: after each keyframe, and once at the
        end), in the calling thread."""
        start = time.perf_counter()
        settings = self.config.pipeline
        with self.stop.installed(), ExitStack() as stack:
            if settings.overlapped and settings.read_ahead_frames:  # decoding beside the odometry
                frames = stack.enter_context(ReadAhead(frames, settings.read_ahead_frames))
            iterator = iter(frames) if self.clock is None else self.clock.paced(frames)
            if settings.overlapped:
                source_error = self._run_overlapped(iterator, on_frame)
            else:
                source_error = self._run_sequential(iterator, on_frame)
        error = None if self.step_error is None else f"{type(self.step_error).__name__}: {self.step_error}"
        seconds = self.ending.seconds + time.perf_counter() - start
        self.ending = StreamEnd(self.stop.requested, source_error, error, seconds)
        return self.state

    def _next_frame(self, iterator: Iterator[Frame]) -> tuple[Frame | None, str | None]:
        """(the next frame, None), or (None, why the source stopped early) at its end."""
        try:
            return next(iterator), None
        except StopIteration:
            return None, None
        except FrontendInputError as exc:  # e.g. a log cut short: keep what came before
            log.error("source stopped: %s", exc)
            return None, str(exc)

    def _run_sequential(self, iterator: Iterator[Frame], on_frame: Callable[[RunState], None] | None) -> str | None:
        while not self.stop.requested:
            frame, source_error = self._next_frame(iterator)
            if frame is None:
                return source_error
            if self.stop.requested:  # requested while the source was producing this frame
                break
            try:
                self._process(frame)
            except Exception as exc:  # keep everything processed so far; the caller re-raises
                self.step_error = exc
                _log_failure(f"frame {frame.index}", exc)
                break
            self._after_step(on_frame)
        return None

    def _run_overlapped(self, iterator: Iterator[Frame], on_frame: Callable[[RunState], None] | None) -> str | None:
        """The front half in a producer thread, the back half here (see the module docstring)."""
        end = _ProducerEnd()
        ahead = self.config.pipeline.odometry_ahead_frames
        if ahead and self.clock is None and isinstance(self.odometry, OdometryProcess):
            iterator = submitted_ahead(iterator, self.odometry, ahead)
        depth = self.config.pipeline.overlap_queue_keyframes
        encoded: ReadAhead[KeyframeInput] | None = None
        front = self._front_half(
            iterator, end, lambda: keyframes.cancelled or (encoded is not None and encoded.cancelled)
        )
        keyframes = ReadAhead(front, depth, "slam-front-end")
        with ExitStack() as stages:  # leaving it (a back-end failure) stops the encoder, then the producer
            stages.enter_context(keyframes)
            if self.config.pipeline.encodes_ahead:
                encoded = stages.enter_context(ReadAhead(self._encoded_ahead(keyframes), 1, "slam-encoder"))
            while True:
                asked = time.perf_counter()
                try:
                    item = next(keyframes if encoded is None else encoded)
                    item = replace(item, back_end_wait=time.perf_counter() - asked)
                except StopIteration:
                    break
                except RuntimeError as exc:  # the producer's thread gone without its end
                    end.error = exc
                    break
                try:
                    self._back(item)
                except Exception as exc:  # keep everything processed so far; the caller re-raises
                    self.step_error = exc
                    _log_failure(f"keyframe {item.keyframe.id} (frame {item.keyframe.frame_index})", exc)
                    return None
                self._after_step(on_frame)
        if end.error is not None and self.step_error is None:
            self.step_error = end.error
        self.system.sync_front_counts()  # the frames after the last keyframe (all processed)
        if on_frame is not None:
            on_frame(self.state)
        return end.source_error

    def _front_half(
        self, iterator: Iterator[Frame], end: _ProducerEnd, cancelled: Callable[[], bool]
    ) -> Iterator[KeyframeInput]:
        """The keyframes `SlamSystem.front` makes of the frames, in the producer's thread, until the
        source ends, a stop is requested or the consumer has gone; `end` says why it stopped."""
        try:
            while not (self.stop.requested or cancelled()):
                frame, end.source_error = self._next_frame(iterator)
                if frame is None or self.stop.requested:
                    return
                try:
                    item = self.system.front(frame)
                except Exception as exc:  # the consumer re-raises it once the rest is processed
                    end.error = exc
                    _log_failure(f"frame {frame.index}", exc)
                    return
                if item is not None:
                    yield item
        except Exception as exc:  # the source itself failed unexpectedly: ends the run like a frame failing
            end.error = exc
            log.exception("the frame source failed")

    def _encoded_ahead(self, keyframes: Iterator[KeyframeInput]) -> Iterator[KeyframeInput]:
        """The keyframes with their codes, encoded in the encoder's thread while the back half
        recognises the ones before (`LoopDetector.encode_ahead`: the same codes it would compute
        itself, so the same results). One that could not be encoded ahead (the PCA warm-up, a
        failure) goes on without codes: the back half encodes it, and fails on it, in order."""
        detector, told = self.system.detector, False
        for item in keyframes:
            codes = None
            # in real time a keyframe already too late skips recognition: no backbone for it
            if self.clock is None or not self.clock.behind(item.keyframe.frame_index):
                try:
                    codes = detector.encode_ahead(item.image, item.keyframe.id, item.rear_image)
                except Exception as exc:  # noqa: BLE001  # raised again by the back half, naming the keyframe
                    if not told:  # once: the back half then encodes each keyframe that fails here itself
                        log.warning("keyframe %d could not be encoded ahead (%s: %s); the back end encodes it",
                                    item.keyframe.id, type(exc).__name__, exc)  # fmt: skip
                    told = True
            yield item if codes is None else replace(item, encoded=codes)

    def _process(self, frame: Frame) -> None:
        """One frame through both halves (`SlamSystem.process`, with the real-time rule)."""
        if self.clock is None:
            self.system.process(frame)
            return
        item = None
        try:
            item = self.system.front(frame)
        finally:
            if item is None:  # a frame that is no keyframe (or failed) still counts as seen
                self.system.sync_front_counts()
        if item is not None:
            self._back(item)

    def _back(self, item: KeyframeInput) -> None:
        """The back half of a keyframe; in real time, by odometry alone when it came too late."""
        if self.clock is None:
            self.system.back(item)
            return
        late = self.clock.behind(item.keyframe.frame_index)
        self.system.back(item, recognise=not late)
        self.clock.done(item.keyframe.frame_index, late)

    def _after_step(self, on_frame: Callable[[RunState], None] | None) -> None:
        self.heap.after(len(self.state.keyframes))
        if on_frame is not None:
            on_frame(self.state)

    def finish(self) -> RunResult:
        """The system's result, with how the stream ended (optimises once; see SlamSystem.finish)
        and, in real time, how it kept pace."""
        result = self.system.finish(self.ending)
        return result if self.clock is None else replace(result, realtime=self.clock.stats())


def _log_failure(what: str, error: Exception) -> None:
    """A step that ended the run: one line for an error the package raised on purpose (its
    message names the input; the caller re-raises it as the run's one `error:` line), the
    traceback for anything else (a bug to report)."""
    if isinstance(error, SsmvprError):
        log.error("%s failed: %s", what, error)
    else:
        log.exception("%s failed", what)
