"""The SLAM core: frames in, a `RunResult` out; no files, no signals, no progress bars.

As kiss-slam separates `KissSLAM` from its pipeline, `SlamSystem` holds the method
(odometry -> keyframes -> SSM-VPR loops -> iSAM2 pose graph) and nothing else:
``process(frame)`` per frame, ``finish()`` once at the end. The loop that feeds it
(`ssmvpr_slam.app.pipeline`), the files (`ssmvpr_slam.results.writers`, `ssmvpr_slam.checkpoint.saving`) and
the command line (`ssmvpr_slam.app.runner`) live elsewhere, so the core can be driven by a test,
a benchmark or a resumed run alike.

``process`` is two halves that share nothing but the configuration: ``front(frame)`` (odometry,
keyframe selection, what a keyframe keeps) and ``back(item)`` (recognition, registration, the
pose graph). The pipeline may run the front half in a thread of its own, ahead of the back half
(`pipeline.overlap`); the back half sees the same keyframes in the same order either way.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, replace

import numpy as np

from frontend.frame import Frame
from frontend.keyframes import KeyframeSelector
from frontend.odometry.base import Odometry
from loopclosure.backbone import Backbone
from loopclosure.database import PlaceDatabase
from loopclosure.detector import LoopDetector
from loopclosure.encoder import Encoder
from ssmvpr_slam.backend.pose_graph import PoseGraph, PoseGraphError
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.kept_keyframe import keep_keyframe
from ssmvpr_slam.loop_policy import LoopPolicy
from ssmvpr_slam.loop_registrations import AppliedRegistration, LoopRegistrations
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.result_assembly import assemble_result, odometry_stats_of
from ssmvpr_slam.run_result import (
    Keyframe,
    LoopRecord,
    RunResult,
    StreamEnd,
)
from ssmvpr_slam.run_state import FrontCounts, KeyframeInput, RunState

log = logging.getLogger(__name__)


class SlamSystem:
    """Streaming SLAM with SSM-VPR loop closures: ``process(frame)``, then ``finish()``.

    graph: the pose graph to build (default: a `PoseGraph` for the configured odometry); tests
    hand in a wrapper (e.g. one that injects wrong loops) through it."""

    def __init__(
        self,
        config: SlamConfig,
        odometry: Odometry,
        backbone: Backbone,
        prior_map: PriorMap | None = None,
        graph: PoseGraph | None = None,
    ) -> None:
        self.config = config
        self.odometry = odometry
        self.selector = KeyframeSelector(config.frontend.keyframes)
        self.prior_map = prior_map
        # the session grows its own copy: the prior map stays as it was loaded
        database = prior_map.database.copy() if prior_map is not None else None
        self.detector = build_detector(config, backbone, database)
        if prior_map is not None:  # no sequence runs from one session of a merged map into the next
            self.detector.mark_segments([*prior_map.session_starts(), len(prior_map)])
        self.detector.links_from_decisions = False  # a loop's places become one once it is registered (`back`)
        self.loop_policy = LoopPolicy(config, self.detector, prior_map)
        pipeline = config.pipeline
        self.registrations = LoopRegistrations(
            self.loop_policy, pipeline.registration_lag_keyframes, pipeline.registers_in_worker
        )
        self.graph = (
            graph
            if graph is not None
            else PoseGraph(config.backend.pose_graph.for_odometry(config.frontend.odometry.kind))
        )
        self.state = RunState()
        self.front_counts = FrontCounts()
        self._result: RunResult | None = None
        self.recoveries_told = 0  # the graph's recoveries already warned about

    # ---- per frame ------------------------------------------------------------------------
    def process(self, frame: Frame) -> None:
        """Odometry for every frame; a keyframe also gets recognised, registered and graphed."""
        item = None
        try:
            item = self.front(frame)
        finally:
            if item is None:  # a frame that is no keyframe (or failed) still counts as seen
                self.sync_front_counts()
        if item is not None:
            self.back(item)

    def front(self, frame: Frame) -> KeyframeInput | None:
        """Odometry and keyframe selection: the keyframe's input for `back`, or None.

        Touches only the odometry, the keyframe selector and the front counters, so it may run
        in another thread than `back` (one frame at a time, in order)."""
        if self._result is not None:
            raise RuntimeError("SlamSystem.process: the run is finished (finish() was called)")
        start = time.perf_counter()
        counts = self.front_counts
        counts.frames_seen += 1
        try:
            pose = self.odometry.update(frame)  # every scan feeds the odometry, camera or not
            counts.odometry_done(time.perf_counter() - start, self.odometry)
            if pose is None or not np.all(np.isfinite(pose)):
                counts.frames_skipped["odometry gave no pose"] += 1
                return None
            if frame.image is None:
                counts.frames_skipped["no camera image"] += 1
                return None
            if not _has_pixels(frame.image):  # a source that let one through: nothing downstream copes
                counts.frames_skipped["empty camera image"] += 1
                return None
            if frame.rear_image is not None and not _has_pixels(frame.rear_image):
                frame = replace(frame, rear_image=None)  # the forward image still recognises the place
            if not self.selector.select(pose, frame.timestamp):
                return None
            kept = time.perf_counter()
            keyframe = keep_keyframe(frame, pose, counts.keyframes, self.config, self.odometry)
            counts.parts["keyframe_keeping"] += time.perf_counter() - kept
            counts.keyframes += 1
        finally:
            counts.seconds += time.perf_counter() - start
        seconds, counts.seconds = counts.seconds, 0.0
        assert frame.image is not None  # checked above
        return KeyframeInput(keyframe, frame.image, frame.rear_image, counts.frames_seen,
                             dict(counts.frames_skipped), seconds, counts.take_parts())  # fmt: skip

    def sync_front_counts(self) -> None:
        """Bring the state's frame counters up to the front's (frames after the last keyframe)."""
        self.state.frames_seen = self.front_counts.frames_seen
        self.state.frames_skipped = Counter(self.front_counts.frames_skipped)

    def back(self, item: KeyframeInput, recognise: bool = True) -> None:
        """Recognise, register and graph a keyframe from `front` (in the order they came).

        recognise False: the keyframe enters the graph by its odometry alone, without the
        backbone, a proposal or a place (a live run that fell behind its sensor catches up so);
        loops registered earlier still fall due at it."""
        if self._result is not None:
            raise RuntimeError("SlamSystem.process: the run is finished (finish() was called)")
        kf = item.keyframe
        if kf.id != len(self.state.keyframes):
            raise RuntimeError(f"SlamSystem.back: keyframe {kf.id} out of order ({len(self.state.keyframes)} expected)")
        self.state.frames_seen = item.frames_seen
        self.state.frames_skipped = Counter(item.frames_skipped)
        if item.rear_image is not None and self.config.detector.rear.enabled:
            self.state.rear_keyframes += 1
        self.state.keyframes.append(kf)
        t0 = time.perf_counter()
        self.graph.add_keyframe(kf.id, kf.odom_pose)
        proposal = None
        if recognise:
            at = kf.odom_pose[:3, 3]
            proposal = self.detector.process(item.image, kf.id, at, kf.timestamp, item.rear_image, item.encoded)
        else:
            self.detector.skip(kf.odom_pose[:3, 3])
            self.state.recognition_skipped.append(kf.id)
        t1 = time.perf_counter()
        if proposal is not None:
            self.state.loops.append(LoopRecord(proposal))  # recorded even if registration fails
            if proposal.accepted:  # registered now or in the worker, applied `registration_lag_keyframes` on
                travelled = math.nan if proposal.prior_map else self.detector.travelled_since(proposal.match_place)
                self.registrations.submit(len(self.state.loops) - 1, kf, proposal, self.state.keyframes,
                                          self.state.loops, travelled)  # fmt: skip
        worked = sum(self._apply(done) for done in self.registrations.due(kf.id))
        t_reg = time.perf_counter() - t1
        t2 = time.perf_counter()
        self._update_graph(kf)
        t_graph = time.perf_counter() - t2
        self.state.times.rows.append({
            **asdict(self.detector.timings),  # backbone, stage I, stage II, sequences, gate, backbone_ahead
            "registration": t_reg, "registration_work": worked, "isam2_update": t_graph,
            "total": time.perf_counter() - t0, "back_end_wait": item.back_end_wait, "front_end": item.front_seconds,
            **item.front_parts,
        })  # fmt: skip

    def _apply(self, done: AppliedRegistration) -> float:
        """A registration that fell due: its factor into the graph, its places joined; the
        seconds it took to compute."""
        self.state.loops[done.index] = self.add_loop_factor(LoopRecord(done.proposal, done.registration))
        if done.registration.accepted or done.registration.method == "spaced":
            self.detector.join(done.proposal)
        return done.seconds

    def _update_graph(self, kf: Keyframe) -> None:
        """One iSAM2 step (see `_graph_step`)."""
        with self._graph_step(kf.id):
            self.graph.update()

    @contextmanager
    def _graph_step(self, kf_id: int) -> Iterator[None]:
        """Around anything that may solve the graph (an update; the first prior-map loop, which
        solves to place the map): a recovery is warned about naming its frames, a failure is a
        PoseGraphError naming this keyframe's frame."""
        try:
            yield
        except PoseGraphError as error:
            kf = self.state.keyframes[kf_id]
            raise PoseGraphError(f"frame {kf.frame_index} (keyframe {kf.id}): {error}") from None
        finally:
            self._tell_recoveries()

    def _tell_recoveries(self) -> None:
        """Warn once about each recovery of the pose graph (see `PoseGraph.update`)."""
        recoveries = self.graph.recoveries
        for recovery in recoveries[self.recoveries_told :]:
            log.warning("%s: %s", self._frames_of(recovery.keyframes), recovery.what)
        self.recoveries_told = len(recoveries)

    def _frames_of(self, keyframe_ids: Sequence[int]) -> str:
        """'frame 5 (keyframe 1)' for the warnings (the user knows frames, the graph keyframes)."""
        kfs = self.state.keyframes
        named = [f"frame {kfs[k].frame_index} (keyframe {k})" for k in keyframe_ids if k < len(kfs)]
        return ", ".join(named) or "pose graph"

    def add_loop_factor(self, record: LoopRecord) -> LoopRecord:
        """The record with its factor handle, once an accepted registration became a factor."""
        reg, proposal = record.registration, record.proposal
        if reg is None or not reg.accepted:
            return record
        if proposal.prior_map:
            assert self.prior_map is not None  # a prior-map proposal needs a prior map
            place_pose = self.prior_map.pose(proposal.match_place)
            assert place_pose is not None  # a place without a pose never registers (see _register_to_map)
            with self._graph_step(proposal.query_id):
                handle = self.graph.add_map_loop(
                    proposal.match_place, place_pose, proposal.query_id, reg.T_mq, reg.sigmas
                )
        else:
            handle = self.graph.add_loop(proposal.match_id, proposal.query_id, reg.T_mq, sigmas=reg.sigmas)
        return replace(record, factor_handle=handle)

    # ---- the end --------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        return self._result is not None

    def finish(self, ending: StreamEnd | None = None) -> RunResult:
        """Final optimisation (GNC when configured) and the run's result.

        Runs once: the final pass may remove loops from the graph, so a second call returns
        the same result instead of optimising again (and ignores its `ending`). An odometry in
        a process of its own (`OdometryProcess`) is ended here: nothing feeds it afterwards."""
        if self._result is None:
            try:
                self._result = self._final_result(ending or StreamEnd())
            finally:
                self.registrations.close()
                close = getattr(self.odometry, "close", None)
                if close is not None:
                    close()
        return self._result

    def _final_result(self, ending: StreamEnd) -> RunResult:
        remaining = self.registrations.remaining()  # loops made in the last `lag` keyframes
        if remaining and self.state.keyframes:
            for done in remaining:
                self._apply(done)
            self._update_graph(self.state.keyframes[-1])
        optimised = self.graph.finalize() if self.state.keyframes else {}
        self._tell_recoveries()  # a final robust pass that failed or could not run
        return self.result_with(optimised, set(self.graph.loop_handles), ending)

    def result_with(self, by_id: dict[int, np.ndarray], final: set[int], ending: StreamEnd,
                    odometry_stats: bool = True) -> RunResult:  # fmt: skip
        """The run's result with poses `by_id`. odometry_stats: False while the front half may
        still be updating them (a checkpoint, which does not save them)."""
        self.detector.annotate_database()  # a map saved from this result seeds the next session's decisions
        recoveries = tuple(
            f"{self._frames_of(r.keyframes)}: {r.what}" if r.keyframes else r.what for r in self.graph.recoveries
        )
        stats = odometry_stats_of(self.odometry) if odometry_stats else {}
        return assemble_result(self.state, self.detector, self.graph, self.prior_map, by_id, final, ending, stats,
                               recoveries)  # fmt: skip


def build_detector(config: SlamConfig, backbone: Backbone, database: PlaceDatabase | None = None) -> LoopDetector:
    """The loop detector a run uses (`loop-eval` benchmarks this same one)."""
    return LoopDetector(config.vpr, config.detector, Encoder(config.vpr, backbone), database)


def _has_pixels(image: np.ndarray) -> bool:
    """An image with at least one row and one column (a 0xN array makes every stage fail)."""
    shape = np.shape(image)
    return len(shape) >= 2 and shape[0] > 0 and shape[1] > 0
