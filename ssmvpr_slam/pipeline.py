"""The main loop: frames -> odometry -> keyframes -> SSM-VPR loops -> iSAM2 pose graph.

Mirrors kiss-icp's `OdometryPipeline`: one class owns the loop, the sources and the
results. A stop request (Ctrl-C, SIGTERM) ends the loop after the current frame; what was
processed so far is optimised and written like a finished run, so results are never half
written.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from collections import Counter
from collections.abc import Iterable
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.keyframes import KeyframeSelector
from frontend.odometry.base import Odometry
from loopclosure.backbone import Backbone
from loopclosure.detector import LoopDetector, LoopProposal
from loopclosure.encoder import Encoder
from ssmvpr_slam.backend.loop_registration import LoopRegistrar, LoopRegistration, build_local_map
from ssmvpr_slam.backend.noise import sigmas6
from ssmvpr_slam.backend.pose_graph import PoseGraph
from ssmvpr_slam.config import SlamConfig
from ssmvpr_slam.prior_map import PriorMap

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """What the back end and the evaluation keep of a keyframe (scans voxel-downsampled)."""

    id: int
    frame_index: int
    timestamp: float
    odom_pose: np.ndarray
    gt_pose: np.ndarray | None
    scan: np.ndarray | None
    image: np.ndarray | None
    rear_image: np.ndarray | None = None  # kept only where a loop may need two-view geometry (no scan)


@dataclass
class LoopRecord:
    """One proposal as reported in loop_closures.csv, with what became of it."""

    proposal: LoopProposal
    registration: LoopRegistration | None = None
    factor_handle: int | None = None
    injected: bool = False

    @property
    def in_graph(self) -> bool:
        return self.factor_handle is not None


@dataclass
class StageTimes:
    """Seconds per keyframe and stage; the benchmark reads medians from here."""

    rows: list[dict[str, float]] = field(default_factory=list)

    def summary(self) -> dict[str, dict[str, float]]:
        if not self.rows:
            return {}
        keys = self.rows[0].keys()
        return {
            k: {"median_s": float(np.median([r[k] for r in self.rows])), "p90_s": float(np.percentile([r[k] for r in self.rows], 90))}
            for k in keys
        }


@dataclass
class RunState:
    keyframes: list[Keyframe] = field(default_factory=list)
    loops: list[LoopRecord] = field(default_factory=list)
    frames_seen: int = 0
    frames_skipped: Counter = field(default_factory=Counter)
    rear_keyframes: int = 0  # keyframes queried with a rear image too
    interrupted: bool = False
    source_error: str | None = None  # why the source ended early (truncated log, ...)
    step_error: Exception | None = None  # an unexpected failure while processing a frame
    seconds: float = 0.0
    times: StageTimes = field(default_factory=StageTimes)


class StopFlag:
    """Set by SIGINT/SIGTERM; the loop checks it between frames."""

    def __init__(self) -> None:
        self.requested = False

    @contextmanager
    def installed(self) -> Iterator["StopFlag"]:
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
    def __init__(
        self,
        config: SlamConfig,
        odometry: Odometry,
        backbone: Backbone,
        prior_map: PriorMap | None = None,
        inject_wrong_loops: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.config = config
        self.odometry = odometry
        self.selector = KeyframeSelector(config.frontend.keyframes)
        self.prior_map = prior_map
        # the session grows its own copy: the prior map stays as it was loaded
        database = prior_map.database.copy() if prior_map is not None else None
        self.detector = LoopDetector(config.vpr, config.detector, Encoder(config.vpr, backbone), database)
        self.registrar = LoopRegistrar(config.backend.registration)
        self.graph = PoseGraph(config.backend.pose_graph.for_odometry(config.frontend.odometry.kind))
        self.state = RunState()
        self.stop = StopFlag()
        self.inject_wrong_loops = inject_wrong_loops
        self._rng = np.random.default_rng(seed)

    # ---- the loop -----------------------------------------------------------------------
    def run(self, frames: Iterable[Frame], on_frame=None) -> RunState:  # noqa: ANN001
        """Process every frame (or until a stop request); returns the run state."""
        start = time.perf_counter()
        iterator = iter(frames)
        with self.stop.installed():
            while not self.stop.requested:
                try:
                    frame = next(iterator)
                except StopIteration:
                    break
                except FrontendInputError as exc:  # e.g. a log cut short: keep what came before
                    self.state.source_error = str(exc)
                    log.error("source stopped: %s", exc)
                    break
                if self.stop.requested:  # requested while the source was producing this frame
                    break
                try:
                    self.step(frame)
                except Exception as exc:  # keep everything processed so far; the caller re-raises
                    self.state.step_error = exc
                    log.exception("frame %s failed", frame.index)
                    break
                if on_frame is not None:
                    on_frame(self.state)
            self.state.interrupted = self.stop.requested
        self.state.seconds = time.perf_counter() - start
        return self.state

    def step(self, frame: Frame) -> None:
        self.state.frames_seen += 1
        pose = self.odometry.update(frame)  # every scan feeds the odometry, camera or not
        if pose is None or not np.all(np.isfinite(pose)):
            self.state.frames_skipped["odometry gave no pose"] += 1
            return
        if frame.image is None:
            self.state.frames_skipped["no camera image"] += 1
            return
        if not self.selector.select(pose, frame.timestamp):
            return
        self._keyframe(frame, pose)

    def _keyframe(self, frame: Frame, pose: np.ndarray) -> None:
        kf = Keyframe(
            id=len(self.state.keyframes),
            frame_index=frame.index,
            timestamp=frame.timestamp,
            odom_pose=np.array(pose, dtype=np.float64),
            gt_pose=None if frame.gt_pose is None else np.array(frame.gt_pose, dtype=np.float64),
            scan=self._keep_scan(self._scan_of(frame)) if self.config.pipeline.use_lidar_for_loops else None,
            image=frame.image,
        )
        if kf.scan is None:
            kf.rear_image = frame.rear_image
        if frame.rear_image is not None and self.config.detector.rear.enabled:
            self.state.rear_keyframes += 1
        self.state.keyframes.append(kf)
        t0 = time.perf_counter()
        self.graph.add_keyframe(kf.id, kf.odom_pose)
        proposal = self.detector.process(frame.image, kf.id, kf.odom_pose[:3, 3], frame.timestamp, frame.rear_image)
        t_reg = t_graph = 0.0
        if proposal is not None:
            record = LoopRecord(proposal)
            self.state.loops.append(record)
            if proposal.accepted:
                t1 = time.perf_counter()
                record.registration = self._register(kf, proposal)
                t_reg = time.perf_counter() - t1
                reg = record.registration
                if reg.accepted and proposal.prior_map:
                    pose = self.prior_map.pose(proposal.match_place)
                    record.factor_handle = self.graph.add_map_loop(proposal.match_place, pose, kf.id, reg.T_mq, reg.sigmas)
                elif reg.accepted:
                    record.factor_handle = self.graph.add_loop(proposal.match_id, kf.id, reg.T_mq, sigmas=reg.sigmas)
            self._maybe_inject_wrong_loop(kf)
        t2 = time.perf_counter()
        self.graph.update()
        t_graph = time.perf_counter() - t2
        timings = self.detector.timings
        self.state.times.rows.append({
            "backbone": timings.backbone, "database_query": timings.database_query,
            "spatial_matching": timings.spatial_matching, "sequence_matching": timings.sequence_matching,
            "gate": timings.gate,
            "registration": t_reg, "isam2_update": t_graph, "total": time.perf_counter() - t0,
        })  # fmt: skip

    def _scan_of(self, frame: Frame) -> np.ndarray | None:
        """The odometry's motion-compensated scan when it has one (kiss-icp), else the raw one."""
        deskewed = getattr(self.odometry, "last_scan", None)
        return deskewed if deskewed is not None else frame.points

    def _keep_scan(self, points: np.ndarray | None) -> np.ndarray | None:
        if points is None or len(points) == 0:
            return None
        from kiss_icp.voxelization import voxel_down_sample

        lidar = self.config.backend.registration.lidar
        finite = np.asarray(points, dtype=np.float64)
        finite = finite[np.isfinite(finite).all(axis=1)]
        voxel = lidar.voxel_size * lidar.map_downsample_factor
        return voxel_down_sample(finite, voxel) if len(finite) else None

    def _register(self, kf: Keyframe, proposal: LoopProposal) -> LoopRegistration:
        """ICP against a local map around the match when both have scans, else a place prior."""
        if proposal.prior_map:
            return self._register_to_map(kf, proposal)
        match = self.state.keyframes[proposal.match_id]
        if kf.scan is not None and match.scan is not None:
            half = self.config.backend.registration.lidar.local_map_half_window
            window = self.state.keyframes[max(0, match.id - half) : match.id + half + 1]
            window = [k for k in window if k.scan is not None]
            local_map = build_local_map(
                [k.scan for k in window], [k.odom_pose for k in window], match.odom_pose,
                self.config.backend.registration.lidar.max_range,
            )  # fmt: skip
            return self.registrar.register_scans(kf.scan, local_map, proposal.yaw_guess)
        if proposal.camera == "rear":  # the rear image saw what the match's forward camera saw
            if kf.rear_image is None:
                return self.registrar.yaw_prior(proposal.yaw_guess, "rear camera match: no rear image kept")
            return self.registrar.register_images(kf.rear_image, match.image, proposal.yaw_guess, query_yaw_offset=math.pi)
        return self.registrar.register_images(kf.image, match.image, proposal.yaw_guess)

    def _register_to_map(self, kf: Keyframe, proposal: LoopProposal) -> LoopRegistration:
        """ICP against the prior map's scans around the place, else the visual place prior."""
        place = proposal.match_place
        pose = self.prior_map.pose(place) if self.prior_map is not None else None
        if pose is None:
            reason = "prior place has no pose in its map (its session was never anchored)"
            return LoopRegistration(np.eye(4), False, reason, np.nan, np.nan)
        lidar = self.config.backend.registration.lidar
        parts = self.prior_map.neighbourhood(place, lidar.local_map_half_window)
        if kf.scan is not None and parts:
            scans, poses = zip(*parts)
            local_map = build_local_map(scans, poses, pose, lidar.max_range)
            return self.registrar.register_scans(kf.scan, local_map, proposal.yaw_guess)
        return self.registrar.yaw_prior(proposal.yaw_guess, "prior-map place: no scans to align")

    def _maybe_inject_wrong_loop(self, kf: Keyframe) -> None:
        """Test option: with the given probability per proposal, add a deliberately wrong loop."""
        if self.inject_wrong_loops <= 0.0 or kf.id < 2 or self._rng.random() >= self.inject_wrong_loops:
            return
        wrong = int(self._rng.integers(0, kf.id - 1))
        lidar = self.config.backend.registration.lidar
        sigmas = sigmas6(lidar.rot_sigma, lidar.trans_sigma)  # as confident as a real ICP loop
        proposal = LoopProposal(kf.id, wrong, -1, 0.0, 0.0, 0, 0.0, True, "injected wrong loop (test option)")
        record = LoopRecord(proposal, injected=True)
        record.factor_handle = self.graph.add_loop(wrong, kf.id, np.eye(4), sigmas=sigmas)
        self.state.loops.append(record)

    # ---- outputs ------------------------------------------------------------------------
    def trajectories(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(timestamps, odometry poses, optimised poses) of the keyframes."""
        kfs = self.state.keyframes
        stamps = np.array([k.timestamp for k in kfs])
        odom = np.array([k.odom_pose for k in kfs]).reshape(-1, 4, 4)
        if not kfs:
            return stamps, odom, odom
        optimised = self.graph.finalize()
        return stamps, odom, np.array([optimised[k.id] for k in kfs])
