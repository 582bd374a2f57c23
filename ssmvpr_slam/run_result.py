"""What a SLAM run produced, as plain frozen records: the input of evaluation and the writers.

`SlamSystem.finish()` builds one `RunResult`; nothing downstream changes it. Evaluation
(`ssmvpr_slam.evaluation.run_report.evaluate`) turns it into a `RunReport`, and the writers
(`ssmvpr_slam.results.writers`) turn both into files. Keeping the result immutable is what lets a
writer run twice, or a checkpoint be written while the run goes on, without side effects.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.kept_scan import KeptScan
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.backend.two_view import ReducedImage

if TYPE_CHECKING:  # only for annotations: the result module stays light to import
    from loopclosure.database import PlaceDatabase
    from ssmvpr_slam.backend.g2o_io import PoseGraphData
    from ssmvpr_slam.prior_map import PriorMap


@dataclass(frozen=True)
class Keyframe:
    """What the back end, the evaluation and the outputs keep of a keyframe for the whole run,
    bounded per keyframe: the voxelised scan (`KeptScan`, packed int16 centimetres) or, without one,
    grey copies of the images within `pipeline.keyframe_image_pixels` for two-view
    registration, and a JPEG thumbnail. Never the full camera images (a KITTI image is 1.4 MB:
    gigabytes over a long drive)."""

    id: int
    frame_index: int
    timestamp: float
    odom_pose: np.ndarray
    gt_pose: np.ndarray | None
    scan: KeptScan | None
    image: ReducedImage | None
    rear_image: ReducedImage | None = None
    thumbnail: bytes | None = None  # JPEG, for trajectory.mcap (results.mcap)

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays and images it holds (the memory a keyframe costs, besides objects)."""
        arrays = [self.odom_pose, self.gt_pose, self.scan]
        images = [self.image, self.rear_image]
        return (sum(a.nbytes for a in arrays if a is not None) + sum(i.nbytes for i in images if i is not None)
                + len(self.thumbnail or b""))  # fmt: skip


@dataclass(frozen=True)
class LoopRecord:
    """One proposal as reported in loop_closures.csv, with what became of it.

    factor_handle: the pose graph's handle when a factor was added; dropped: the final robust
    pass took that factor out again (set only in a finished run's result)."""

    proposal: LoopProposal
    registration: LoopRegistration | None = None
    factor_handle: int | None = None
    dropped: bool = False

    @property
    def in_graph(self) -> bool:
        return self.factor_handle is not None and not self.dropped

    @property
    def spaced(self) -> bool:
        """Not registered: an ICP loop of the same revisit a few keyframes back stands for it
        (`backend.registration.lidar.loop_spacing_keyframes`)."""
        return self.registration is not None and self.registration.method == "spaced"

    @property
    def closed(self) -> bool:
        """The run closed this loop: in the graph, or spaced out by an accepted ICP loop."""
        return self.in_graph or self.spaced


@dataclass
class StageTimes:
    """Seconds per keyframe and stage; the benchmark reads medians from here."""

    rows: list[dict[str, float]] = field(default_factory=list)

    def summary(self) -> dict[str, dict[str, float]]:
        return latency_summary(self.rows)


def latency_summary(rows: Sequence[Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Median, 90th percentile and mean of each stage over the keyframes (the mean is what a stage
    that runs for some keyframes only, such as loop registration, costs the run). A stage is
    summarised over the rows that have it (a run resumed from an older checkpoint lacks the
    stages added since)."""
    names = dict.fromkeys(k for r in rows for k in r)
    columns = {k: np.array([r[k] for r in rows if k in r], dtype=np.float64) for k in names}
    return {
        k: {"median_s": float(np.median(v)), "p90_s": float(np.percentile(v, 90)), "mean_s": float(np.mean(v))}
        for k, v in columns.items()
    }


@dataclass(frozen=True)
class StreamEnd:
    """How the stream of frames ended, as the loop that fed the system saw it."""

    interrupted: bool = False  # a stop request (Ctrl-C, SIGTERM) ended it early
    source_error: str | None = None  # why the source ended early (truncated log, ...)
    error: str | None = None  # an unexpected failure while processing a frame ("Type: message")
    seconds: float = 0.0  # wall time of the loop


@dataclass(frozen=True)
class RunResult:
    """A finished run: keyframes, trajectories, loops with their final status, counters.

    odometry / optimised: (N, 4, 4) keyframe poses in keyframe order; in_map_frame: the
    optimised poses in the map frame (the session's own frame without a prior map, the prior
    map's once a map loop anchored it, None if it never was)."""

    keyframes: tuple[Keyframe, ...]
    loops: tuple[LoopRecord, ...]
    stamps: np.ndarray
    odometry: np.ndarray
    optimised: np.ndarray
    in_map_frame: np.ndarray | None = None
    anchored: bool = False
    frames_seen: int = 0
    frames_skipped: Mapping[str, int] = field(default_factory=dict)
    rear_keyframes: int = 0  # keyframes queried with a rear image too
    timings: tuple[Mapping[str, float], ...] = ()
    odometry_stats: Mapping[str, Any] = field(default_factory=dict)
    ending: StreamEnd = StreamEnd()
    pose_graph: PoseGraphData | None = None  # odometry and session loop factors, for g2o
    database: PlaceDatabase | None = None  # the session's place database (prior places first)
    rear_database: PlaceDatabase | None = None  # rear-image codes by keyframe id (detector.rear.keep_codes)
    session_places: Mapping[int, int] = field(default_factory=dict)  # keyframe id -> database place
    prior_map: PriorMap | None = None  # as loaded; never changed by the run
    graph_recoveries: tuple[str, ...] = ()  # iSAM2 steps the pose graph had to work around (PoseGraph.recoveries)
    # a checkpoint's view only: registrations of loops made in the last `registration_lag_keyframes`
    # keyframes, not applied yet (their record index in `loops`, the registration)
    unapplied_registrations: tuple[tuple[int, LoopRegistration], ...] = ()
    keyframes_judged: int = 0  # keyframes whose winner the loop decision measured (LoopDetector.keyframes_judged)
    realtime: RealtimeStats | None = None  # `run --realtime`: how the run kept pace with its log
    too_short_to_decide: str | None = None  # why none was, when none was (LoopDetector.too_short_to_decide)

    @property
    def session_loops(self) -> tuple[LoopRecord, ...]:
        """Loops between keyframes of this session (not to the prior map)."""
        return tuple(r for r in self.loops if not r.proposal.prior_map)

    def latency(self) -> dict[str, dict[str, float]]:
        return latency_summary(self.timings)


def frozen_array(values: Any, dtype: Any = np.float64) -> np.ndarray:
    """A read-only copy: a result's arrays cannot be changed behind its back."""
    array = np.array(values, dtype=dtype)
    array.setflags(write=False)
    return array


def keyframe_poses(keyframes: Sequence[Keyframe]) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), odometry poses (N, 4, 4)) of keyframes."""
    stamps = frozen_array([k.timestamp for k in keyframes])
    odom = frozen_array(np.array([k.odom_pose for k in keyframes]).reshape(-1, 4, 4))
    return stamps, odom


def has_ground_truth(keyframes: Sequence[Keyframe]) -> np.ndarray:
    """Which keyframes carry a usable ground-truth pose (not None, all finite)."""
    return np.array([k.gt_pose is not None and bool(np.isfinite(k.gt_pose).all()) for k in keyframes], bool)


@dataclass(frozen=True)
class RealtimeStats:
    """How a run kept pace: what `metrics.json`'s `realtime` holds."""

    rate: float  # the log played at this many times its recorded rate
    max_lag_s: float  # lag beyond which a keyframe skips recognition
    keyframes: int  # keyframes that reached the back end
    keyframes_skipped: int  # of them, handled by odometry alone
    lag_median_s: float | None
    lag_p99_s: float | None
    lag_max_s: float | None

    @property
    def kept_up(self) -> bool:
        """No keyframe skipped recognition."""
        return self.keyframes_skipped == 0

    def to_dict(self) -> dict[str, float | int | bool | None]:
        return {
            "rate": self.rate, "max_lag_s": self.max_lag_s, "keyframes": self.keyframes,
            "keyframes_skipped": self.keyframes_skipped, "lag_median_s": self.lag_median_s,
            "lag_p99_s": self.lag_p99_s, "lag_max_s": self.lag_max_s, "kept_up": self.kept_up,
        }  # fmt: skip
