"""metrics.json of a run, as one typed model: the writer validates against it, the summary
table and the tests read it.

Each part is made where its numbers are (the run's counters in `writers.run_metrics`, the
inputs in `runner.run_description`, the evaluation in `RunReport.metrics`); this module says
what the file holds, once, so a key renamed or added in one place and not the others fails
when the run is written (every model forbids keys it does not declare), not in a reader later.
A part that does not apply is absent (no ground truth: no ATE), and a number that is not
finite is null (the file is strict JSON)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, NonNegativeInt


class _Part(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StageLatency(_Part):
    """One stage's seconds a keyframe (a stage that runs for some keyframes only has median 0)."""

    median_s: float
    p90_s: float
    mean_s: float


class ErrorStatistics(_Part):
    rmse: float | None
    mean: float | None
    median: float | None
    std: float | None
    min: float | None
    max: float | None
    n: NonNegativeInt


class Alignment(_Part):
    rotation: list[list[float]]
    translation: list[float]
    scale: float


class AbsoluteError(ErrorStatistics):
    """ATE after aligning the estimate onto the ground truth."""

    alignment: str
    transform: Alignment


class RelativeError(_Part):
    delta: float
    unit: str
    n_pairs: NonNegativeInt
    translation_m: ErrorStatistics
    rotation_deg: ErrorStatistics


class Drift(_Part):
    translation_m_per_100m: float | None
    rotation_deg_per_100m: float | None
    segment_m: float
    n_segments: NonNegativeInt
    path_length_m: float


class KittiLengthError(_Part):
    length_m: float
    translation_pct: float | None
    rotation_deg_per_100m: float | None
    n_segments: NonNegativeInt


class KittiError(_Part):
    translation_pct: float | None
    rotation_deg_per_100m: float | None
    n_segments: NonNegativeInt
    step_frames: NonNegativeInt
    path_length_m: float
    per_length: dict[str, KittiLengthError]


class KittiErrors(_Part):
    odometry: KittiError
    optimised: KittiError


class DirectionLoops(_Part):
    """Revisits driven in one direction (forward: as before; reverse: the other way round)."""

    revisits: NonNegativeInt
    recalled: NonNegativeInt
    recall: float | None
    visible: NonNegativeInt  # revisits a camera could see (ahead, or behind with a rear camera)
    recall_visible: float | None
    loops_in_graph_by_sequence_direction: NonNegativeInt


class Loops(_Part):
    """The session's loops against ground truth (precision over loops in the graph, and spaced
    ones; recall over revisit keyframes)."""

    precision: float | None
    recall: float | None
    n_revisits: NonNegativeInt
    n_query_keyframes: NonNegativeInt
    n_true_positive_queries: NonNegativeInt
    n_false_positive_queries: NonNegativeInt
    n_recalled_revisits: NonNegativeInt
    recall_visible: float | None
    n_visible_revisits: NonNegativeInt
    n_recalled_visible: NonNegativeInt
    by_direction: dict[str, DirectionLoops]
    n_loops: NonNegativeInt
    n_correct_loops: NonNegativeInt
    proposed: NonNegativeInt
    gate_accepted: NonNegativeInt
    in_graph: NonNegativeInt
    spaced: NonNegativeInt = 0  # gate-accepted, not registered (loop_spacing_keyframes); absent when none
    rear_camera_keyframes: NonNegativeInt
    in_graph_by_camera: dict[str, NonNegativeInt]
    in_graph_by_method: dict[str, NonNegativeInt] = {}  # how each loop in the graph was verified
    first_sight: dict[str, NonNegativeInt] = {}  # revisits, and those whose first loop entered on its own registration
    judged_in_graph: NonNegativeInt | None = None  # loops in graph with both ends covered; absent when all are


class PriorMapLoops(_Part):
    """Loops to the places of a prior map (`--map`), and the map as loaded."""

    places: NonNegativeInt
    places_with_pose: NonNegativeInt
    places_with_scan: NonNegativeInt
    loops_proposed: NonNegativeInt
    loops_gate_accepted: NonNegativeInt
    loops_in_graph: NonNegativeInt
    anchored: bool
    loops_correct: NonNegativeInt | None = None  # judged where both ends have ground truth
    precision: float | None = None
    ate_rmse: float | None = None  # the map's own error, which a session corrected onto it inherits


class Realtime(_Part):
    """`run --realtime`: the log played at `rate` times its recorded rate; a keyframe later than
    `max_lag_s` skipped recognition (odometry alone). Lag: from a keyframe's frame being due to
    the end of its back-end step."""

    rate: float
    max_lag_s: float
    keyframes: NonNegativeInt
    keyframes_skipped: NonNegativeInt
    lag_median_s: float | None
    lag_p99_s: float | None
    lag_max_s: float | None
    kept_up: bool  # no keyframe skipped recognition


class ResumedFrom(_Part):
    checkpoint: str
    frames: NonNegativeInt
    keyframes: NonNegativeInt


class RunInputs(_Part):
    """What the run read: the log, its source, the odometry, a prior map, a checkpoint resumed."""

    log: str
    source: str
    # frames yielded, skips and notes by reason, each source its own: what the source read, which after a
    # stop includes the frames it had read ahead (pipeline.read_ahead_frames, and those handed to kiss-icp's
    # process early, pipeline.odometry_ahead_frames) beyond `frames`
    source_stats: dict[str, Any]
    odometry_kind: str
    prior_map: str | None
    resumed_from: ResumedFrom | None


class RunMetrics(_Part):
    """metrics.json: the run's counters, its inputs, and its evaluation where there is ground truth."""

    # the run (writers.run_metrics)
    frames: NonNegativeInt
    frames_skipped: dict[str, NonNegativeInt]
    keyframes: NonNegativeInt
    recognition_started: bool  # False: the run ended inside the PCA warm-up, nothing was matched
    # keyframes whose best match the loop decision measured; none: the run was too short to decide
    # anything, and too_short_to_decide says why (absent from files written before it)
    keyframes_judged: NonNegativeInt | None = None
    too_short_to_decide: str | None = None
    interrupted: bool
    source_error: str | None
    error: str | None
    seconds: float
    frames_per_second: float | None
    latency_per_keyframe: dict[str, StageLatency]
    odometry: dict[str, Any]  # the odometry's own counters (updates, skips, notes): each kind has its own
    pose_graph_recoveries: list[str]
    realtime: Realtime | None = None  # `run --realtime` only
    # its inputs (`RunInputs`, runner.run_description)
    log: str
    source: str
    source_stats: dict[str, Any]
    odometry_kind: str
    prior_map: str | None
    resumed_from: ResumedFrom | None
    # the evaluation (RunReport.metrics), present where it applies
    ground_truth: bool
    ate_odometry: AbsoluteError | None = None
    ate_optimised: AbsoluteError | None = None
    ate_ratio: float | None = None  # optimised / odometry; null when the odometry's ATE is 0
    rpe_odometry: RelativeError | None = None
    rpe_optimised: RelativeError | None = None
    drift_odometry: Drift | None = None
    kitti_rel_error: KittiErrors | None = None
    loops: Loops | None = None
    stream_pr_auc: float | None = None
    stream_pr_auc_sequence: float | None = None
    ground_truth_coverage: float | None = None
    ground_truth_keyframes: NonNegativeInt | None = None
    prior_map_loops: PriorMapLoops | None = None

    def to_json_dict(self) -> dict[str, Any]:
        """The file's content: the parts that apply, as they were given."""
        return self.model_dump(mode="json", exclude_unset=True)

    @classmethod
    def read(cls, path: str | Path) -> RunMetrics:
        """A run's metrics.json (a results folder's, or the file itself)."""
        path = Path(path)
        return cls.model_validate_json((path / "metrics.json" if path.is_dir() else path).read_text(encoding="utf-8"))
