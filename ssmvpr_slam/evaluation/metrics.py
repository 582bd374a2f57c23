"""Trajectory error metrics: ATE, RPE and drift per 100 m, with evo's definitions.

* ATE: translation error |p_ref - p_est| per pose after Umeyama alignment (SE(3) default).
* RPE: for index pairs (i, j), ``E = inv(inv(Ref_i) Ref_j) @ (inv(Est_i) Est_j)``; the
  translation error is |t(E)| (m) and the rotation error the angle of R(E) (deg). Pairs are
  `delta` frames apart, or `delta` metres of reference path apart.
* Drift: the RPE over segments of `segment_m` metres of reference path (every start frame),
  divided by the segment's length and scaled to 100 m; if the traverse is shorter than one
  segment, the whole traverse is the segment.
* KITTI relative error: the KITTI odometry devkit's protocol (Geiger et al. 2012), so numbers
  compare with the KITTI leaderboard: segments of 100, 200, ..., 800 m of ground-truth path
  from every 10th frame, error divided by the nominal length; no alignment (it is relative).
Results are frozen dataclasses with ``to_dict()`` for metrics.json.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ssmvpr_slam.backend.se3 import as_pose_array, invert, rotation_angle
from ssmvpr_slam.evaluation.alignment import Alignment, align_trajectory

PER_100M = 100.0
KITTI_LENGTHS_M = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
"""The devkit's segment lengths."""
KITTI_STEP_FRAMES = 10
"""The devkit takes a first frame every 10 frames (1 s at KITTI's 10 Hz)."""


@dataclass(frozen=True)
class ErrorStats:
    """Summary statistics of a set of errors (the fields evo reports)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    n: int

    def to_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


def error_stats(errors: np.ndarray) -> ErrorStats:
    """Statistics of a non-empty 1-D error array."""
    err = np.asarray(errors, dtype=np.float64).reshape(-1)
    if err.size == 0:
        raise ValueError("errors: no errors to summarise")
    return ErrorStats(
        rmse=float(np.sqrt(np.mean(err**2))),
        mean=float(np.mean(err)),
        median=float(np.median(err)),
        std=float(np.std(err)),
        min=float(np.min(err)),
        max=float(np.max(err)),
        n=int(err.size),
    )


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error after alignment."""

    stats: ErrorStats
    errors: np.ndarray
    alignment: Alignment
    aligned_poses: np.ndarray
    alignment_kind: str

    def to_dict(self) -> dict[str, object]:
        return {
            "alignment": self.alignment_kind,
            **self.stats.to_dict(),
            "transform": self.alignment.to_dict(),
        }


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over the chosen pairs."""

    translation: ErrorStats
    rotation_deg: ErrorStats
    delta: float
    unit: str
    pairs: list[tuple[int, int]]

    def to_dict(self) -> dict[str, object]:
        return {
            "delta": self.delta,
            "unit": self.unit,
            "n_pairs": len(self.pairs),
            "translation_m": self.translation.to_dict(),
            "rotation_deg": self.rotation_deg.to_dict(),
        }


@dataclass(frozen=True)
class DriftResult:
    """Mean relative error per 100 m of travelled reference path."""

    translation_m_per_100m: float
    rotation_deg_per_100m: float
    segment_m: float
    n_segments: int
    path_length_m: float

    def to_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class KittiLengthError:
    """KITTI relative error of the segments of one nominal length (NaN when there are none)."""

    length_m: float
    translation_pct: float
    rotation_deg_per_100m: float
    n_segments: int

    def to_dict(self) -> dict[str, float | int | None]:
        return {k: _json_number(v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class KittiRelativeError:
    """KITTI odometry relative error: means over all segments of all lengths, as the devkit.

    A route shorter than the shortest length has no segment: n_segments is 0 and the means are
    NaN (None in ``to_dict()``, since metrics.json is strict JSON), not an error, so a short run
    still reports its other metrics.
    """

    translation_pct: float
    rotation_deg_per_100m: float
    n_segments: int
    per_length: tuple[KittiLengthError, ...]
    step_frames: int
    path_length_m: float
    pairs: list[tuple[int, int]]
    segment_lengths_m: np.ndarray  # nominal length L of each pair
    translation_errors_pct: np.ndarray  # per pair, |t_err| / L * 100
    rotation_errors_deg_per_100m: np.ndarray  # per pair, angle(R_err) / L * 100

    def to_dict(self) -> dict[str, object]:
        return {
            "translation_pct": _json_number(self.translation_pct),
            "rotation_deg_per_100m": _json_number(self.rotation_deg_per_100m),
            "n_segments": self.n_segments,
            "step_frames": self.step_frames,
            "path_length_m": self.path_length_m,
            "per_length": {f"{e.length_m:g}": e.to_dict() for e in self.per_length},
        }


def _json_number(value: float | int) -> float | int | None:
    """NaN / inf become None: metrics.json is written with allow_nan=False."""
    return None if isinstance(value, float) and not np.isfinite(value) else value


def _mean_or_nan(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def _pair(
    ref: object, est: object, names: tuple[str, str] = ("ref_poses", "est_poses")
) -> tuple[np.ndarray, np.ndarray]:
    ref_name, est_name = names
    ref_arr = as_pose_array(ref_name, ref)
    est_arr = as_pose_array(est_name, est)
    if len(ref_arr) != len(est_arr):
        raise ValueError(f"{est_name}: {len(est_arr)} poses for {len(ref_arr)} reference poses; associate first")
    if len(ref_arr) < 2:
        raise ValueError(f"{ref_name}: need at least 2 poses, got {len(ref_arr)}")
    return ref_arr, est_arr


def path_lengths(poses: np.ndarray) -> np.ndarray:
    """Accumulated travelled distance at each pose (first is 0)."""
    pos = np.asarray(poses)[:, :3, 3]
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    return np.concatenate(([0.0], np.cumsum(steps)))


def ate(
    ref_poses: np.ndarray,
    est_poses: np.ndarray,
    alignment: Literal["se3", "sim3", "none"] = "se3",
) -> AteResult:
    """Absolute trajectory error (translation part) of `est_poses` against `ref_poses`."""
    ref, est = _pair(ref_poses, est_poses)
    if alignment == "none":
        transform = Alignment(np.eye(3), np.zeros(3), 1.0)
        aligned = est
    elif alignment in ("se3", "sim3"):
        aligned, transform = align_trajectory(est, ref, with_scale=alignment == "sim3")
    else:
        raise ValueError(f"alignment: expected 'se3', 'sim3' or 'none', got {alignment!r}")
    errors = np.linalg.norm(aligned[:, :3, 3] - ref[:, :3, 3], axis=1)
    return AteResult(error_stats(errors), errors, transform, aligned, alignment)


def pairs_by_frames(n: int, delta: int, all_pairs: bool = False) -> list[tuple[int, int]]:
    """Index pairs `delta` frames apart: consecutive (0, d), (d, 2d), ... or every start."""
    if delta < 1:
        raise ValueError(f"delta: frame delta must be >= 1, got {delta}")
    starts = range(n - delta) if all_pairs else range(0, n - delta, delta)
    return [(i, i + delta) for i in starts]


def pairs_by_path(lengths: np.ndarray, delta_m: float, all_pairs: bool = False) -> list[tuple[int, int]]:
    """Index pairs whose path distance first reaches `delta_m` metres."""
    if delta_m <= 0:
        raise ValueError(f"delta: path delta must be > 0 m, got {delta_m}")
    pairs = []
    i = 0
    while i < len(lengths) - 1:
        j = int(np.searchsorted(lengths, lengths[i] + delta_m, side="left"))
        if j >= len(lengths):
            break
        pairs.append((i, j))
        i = i + 1 if all_pairs else j
    return pairs


def _relative_errors(ref: np.ndarray, est: np.ndarray, pairs: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray]:
    trans, rot = [], []
    for i, j in pairs:
        rel_ref = invert(ref[i]) @ ref[j]
        rel_est = invert(est[i]) @ est[j]
        err = invert(rel_ref) @ rel_est
        trans.append(np.linalg.norm(err[:3, 3]))
        rot.append(np.degrees(rotation_angle(err[:3, :3])))
    return np.asarray(trans), np.asarray(rot)


def rpe(
    ref_poses: np.ndarray,
    est_poses: np.ndarray,
    delta: float = 1.0,
    unit: Literal["frames", "m"] = "frames",
    all_pairs: bool = False,
) -> RpeResult:
    """Relative pose error; pairs chosen on the reference trajectory."""
    ref, est = _pair(ref_poses, est_poses)
    if unit == "frames":
        if float(delta) != int(delta):
            raise ValueError(f"delta: frame delta must be a whole number, got {delta}")
        pairs = pairs_by_frames(len(ref), int(delta), all_pairs)
    elif unit == "m":
        pairs = pairs_by_path(path_lengths(ref), float(delta), all_pairs)
    else:
        raise ValueError(f"unit: expected 'frames' or 'm', got {unit!r}")
    if not pairs:
        raise ValueError(f"delta: no pose pairs {delta} {unit} apart in {len(ref)} poses")
    trans, rot = _relative_errors(ref, est, pairs)
    return RpeResult(error_stats(trans), error_stats(rot), float(delta), unit, pairs)


def drift_per_100m(ref_poses: np.ndarray, est_poses: np.ndarray, segment_m: float = PER_100M) -> DriftResult:
    """Mean translational (m) and rotational (deg) error per 100 m of reference path."""
    ref, est = _pair(ref_poses, est_poses)
    lengths = path_lengths(ref)
    total = float(lengths[-1])
    if total <= 0.0:
        raise ValueError("ref_poses: the reference trajectory does not move; drift is undefined")
    pairs = pairs_by_path(lengths, segment_m, all_pairs=True)
    if not pairs:
        pairs = [(0, len(ref) - 1)]
    seg_len = np.array([lengths[j] - lengths[i] for i, j in pairs])
    trans, rot = _relative_errors(ref, est, pairs)
    t_rate = float(np.mean(trans / seg_len))
    r_rate = float(np.mean(rot / seg_len))
    return DriftResult(
        translation_m_per_100m=t_rate * PER_100M,
        rotation_deg_per_100m=r_rate * PER_100M,
        segment_m=float(np.mean(seg_len)),
        n_segments=len(pairs),
        path_length_m=total,
    )


def kitti_relative_error(
    gt: np.ndarray,
    est: np.ndarray,
    lengths: tuple[float, ...] = KITTI_LENGTHS_M,
    step_frames: int = KITTI_STEP_FRAMES,
) -> KittiRelativeError:
    """KITTI odometry devkit relative error of `est` against ground truth `gt` ((N, 4, 4) each).

    From every `step_frames`-th first frame i and for each length L, j is the first frame whose
    ground-truth path distance from i is >= L (the devkit uses >, which differs only on exact
    ties); ``E = inv(inv(gt_i) gt_j) @ (inv(est_i) est_j)`` gives |t(E)| / L and angle(R(E)) / L.
    Means are over all segments of all lengths, in % and deg per 100 m.
    """
    ref, estimate = _pair(gt, est, ("gt", "est"))
    lengths_m = tuple(float(length) for length in lengths)
    if not lengths_m or not all(np.isfinite(length) and length > 0 for length in lengths_m):
        raise ValueError(f"lengths: expected positive segment lengths in metres, got {lengths!r}")
    if len(set(lengths_m)) != len(lengths_m):
        raise ValueError(f"lengths: segment lengths repeat, got {lengths!r}")
    if int(step_frames) != step_frames or step_frames < 1:
        raise ValueError(f"step_frames: must be a whole number >= 1, got {step_frames!r}")
    dist = path_lengths(ref)
    pairs: list[tuple[int, int]] = []
    seg_len: list[float] = []
    for i in range(0, len(ref), int(step_frames)):
        for length in lengths_m:
            j = int(np.searchsorted(dist, dist[i] + length, side="left"))
            if j < len(ref):
                pairs.append((i, j))
                seg_len.append(length)
    nominal = np.asarray(seg_len, dtype=np.float64)
    if pairs:
        trans, rot = _relative_errors(ref, estimate, pairs)
        t_pct = trans / nominal * 100.0
        r_rate = rot / nominal * PER_100M
    else:
        t_pct = r_rate = np.zeros(0)
    per_length = tuple(
        KittiLengthError(
            length_m=length,
            translation_pct=_mean_or_nan(t_pct[nominal == length]),
            rotation_deg_per_100m=_mean_or_nan(r_rate[nominal == length]),
            n_segments=int(np.sum(nominal == length)),
        )
        for length in lengths_m
    )
    return KittiRelativeError(
        translation_pct=_mean_or_nan(t_pct),
        rotation_deg_per_100m=_mean_or_nan(r_rate),
        n_segments=len(pairs),
        per_length=per_length,
        step_frames=int(step_frames),
        path_length_m=float(dist[-1]),
        pairs=pairs,
        segment_lengths_m=nominal,
        translation_errors_pct=t_pct,
        rotation_errors_deg_per_100m=r_rate,
    )


def associate(t_ref: np.ndarray, t_est: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Match each estimate stamp to the nearest reference stamp within `max_dt` (one-to-one).

    Returns index arrays (into ref, into est) sorted by estimate time.
    """
    ref = np.asarray(t_ref, dtype=np.float64).reshape(-1)
    est = np.asarray(t_est, dtype=np.float64).reshape(-1)
    if ref.size == 0 or est.size == 0:
        raise ValueError("t_ref, t_est: both timestamp arrays must be non-empty")
    if not (np.all(np.isfinite(ref)) and np.all(np.isfinite(est))):
        raise ValueError("t_ref, t_est: timestamps contain NaN or inf")
    order = np.argsort(ref)
    sorted_ref = ref[order]
    right = np.clip(np.searchsorted(sorted_ref, est), 0, len(sorted_ref) - 1)
    left = np.clip(right - 1, 0, None)
    use_left = np.abs(est - sorted_ref[left]) <= np.abs(est - sorted_ref[right])
    nearest = np.where(use_left, left, right)
    ok = np.abs(est - sorted_ref[nearest]) <= max_dt
    ref_idx, est_idx, used = [], [], set()
    for k in np.argsort(est):
        if ok[k] and int(nearest[k]) not in used:
            used.add(int(nearest[k]))
            ref_idx.append(int(order[nearest[k]]))
            est_idx.append(int(k))
    return np.asarray(ref_idx, dtype=int), np.asarray(est_idx, dtype=int)
