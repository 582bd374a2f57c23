"""Loop-closure precision / recall against ground-truth positions, counted per query keyframe.

* Revisit: keyframe q is a revisit if some earlier keyframe m with ``q - m >= min_frame_gap``
  lies within ``revisit_radius`` of it (ground truth).
* Accepted loop (q, m) is correct if ``|gt_q - gt_m| <= correct_radius`` (a looser radius is
  allowed so a loop to a neighbouring keyframe of the true place still counts).
* Per query keyframe: a query with accepted loops is a true positive if all of its loops are
  correct and a false positive if any is wrong. precision = TP / (TP + FP).
* recall = revisit keyframes with at least one correct accepted loop / revisit keyframes.
* A revisit is forward when it is driven the way its nearest earlier visit was, reverse
  otherwise; it is camera-visible when some earlier visit within the radius was driven within
  ``view_angle_deg`` of its heading (or, with a rear camera, of the opposite heading). A forward
  camera cannot see a place driven the other way (or crossed at right angles), so
  ``recall_visible`` counts only what the cameras could recognise.
Undefined ratios (no accepted loops, no revisits) are None, which metrics.json stores as null.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ssmvpr_slam.evaluation.config import LoopMetricsConfig


@dataclass(frozen=True)
class LoopEvaluation:
    """Loop-closure quality of one run."""

    precision: float | None
    recall: float | None
    n_revisits: int
    n_query_keyframes: int
    n_true_positive_queries: int
    n_false_positive_queries: int
    n_recalled_revisits: int
    recall_visible: float | None
    n_visible_revisits: int
    n_recalled_visible: int
    by_direction: dict[str, dict[str, float | int | None]]
    n_loops: int
    n_correct_loops: int
    loop_correct: list[bool]
    loop_distance_m: list[float]
    revisit_ids: list[int]

    def to_dict(self, include_lists: bool = False) -> dict[str, object]:
        """Plain dict for metrics.json; the per-loop lists only on request."""
        out = dict(self.__dict__)
        if not include_lists:
            for name in ("loop_correct", "loop_distance_m", "revisit_ids"):
                out.pop(name)
        return out


def gt_positions(name: str, gt: np.ndarray) -> np.ndarray:
    """(N, 3) positions from (N, 3) positions or (N, 4, 4) poses."""
    arr = np.asarray(gt, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        arr = arr[:, :3, 3]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected (N, 3) positions or (N, 4, 4) poses, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    return arr


def find_revisits(gt: np.ndarray, radius: float, min_frame_gap: int) -> np.ndarray:
    """Sorted keyframe indices that are ground-truth revisits."""
    pos = gt_positions("gt", gt)
    if radius <= 0 or min_frame_gap < 1:
        raise ValueError("radius, min_frame_gap: need radius > 0 and min_frame_gap >= 1")
    if len(pos) == 0:
        return np.zeros(0, dtype=int)
    pairs = cKDTree(pos).query_pairs(r=radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros(0, dtype=int)
    lo, hi = pairs.min(axis=1), pairs.max(axis=1)
    return np.unique(hi[hi - lo >= min_frame_gap])


@dataclass(frozen=True)
class RevisitKinds:
    """Per revisit keyframe (ascending ids): its direction and whether a camera could see it."""

    ids: np.ndarray
    forward: np.ndarray  # bool: driven the way the nearest earlier visit was
    visible: np.ndarray  # bool: an earlier visit in the radius looked within the view angle


def classify_revisits(
    gt: np.ndarray,
    revisits: np.ndarray,
    radius: float,
    min_frame_gap: int,
    view_angle_deg: float,
    rear_camera: bool = False,
) -> RevisitKinds:
    """Direction and camera visibility of each revisit, from ground-truth positions alone.

    Headings come from the direction of travel (a central difference of positions), so the
    ground truth may be in any sensor frame; a vehicle's camera looks along its travel. With a
    rear camera, a revisit is also visible when an earlier visit was driven the other way
    (within the view angle of the reversed heading): the rear camera looks where it looked.
    """
    pos = gt_positions("gt", gt)
    ids = np.asarray(revisits, dtype=int)
    forward = np.zeros(len(ids), bool)
    visible = np.zeros(len(ids), bool)
    if len(ids) == 0:
        return RevisitKinds(ids, forward, visible)
    ahead = pos[np.minimum(np.arange(len(pos)) + 1, len(pos) - 1)] - pos[np.maximum(np.arange(len(pos)) - 1, 0)]
    heading = ahead / np.maximum(np.linalg.norm(ahead, axis=1, keepdims=True), 1e-9)
    cos_view = np.cos(np.radians(view_angle_deg))
    tree = cKDTree(pos)
    for k, q in enumerate(ids):
        near = np.array([m for m in tree.query_ball_point(pos[q], r=radius) if q - m >= min_frame_gap], dtype=int)
        if len(near) == 0:  # not a revisit under these settings: neither forward nor visible
            continue
        nearest = near[np.argmin(np.linalg.norm(pos[near] - pos[q], axis=1))]
        forward[k] = float(heading[q] @ heading[nearest]) > 0.0
        alignment = heading[near] @ heading[q]
        visible[k] = bool(np.any(alignment >= cos_view) or (rear_camera and np.any(-alignment >= cos_view)))
    return RevisitKinds(ids, forward, visible)


def evaluate_loops(
    gt: np.ndarray,
    loops: Sequence[tuple[int, int]],
    config: LoopMetricsConfig | None = None,
    rear_camera: bool = False,
) -> LoopEvaluation:
    """Precision / recall of accepted loops (query q, matched m), keyframe indices into `gt`.

    rear_camera: the keyframes also had a rear image, so reverse revisits count as visible."""
    cfg = config or LoopMetricsConfig()
    pos = gt_positions("gt", gt)
    correct_radius = cfg.correct_radius
    revisits = find_revisits(pos, cfg.revisit_radius, cfg.min_frame_gap)
    per_query: dict[int, list[bool]] = defaultdict(list)
    correct_flags, distances = [], []
    for k, loop in enumerate(loops):
        q, m = _loop_ids(k, loop, len(pos))
        dist = float(np.linalg.norm(pos[q] - pos[m]))
        ok = dist <= correct_radius
        correct_flags.append(ok)
        distances.append(dist)
        per_query[q].append(ok)
    tp = sum(all(flags) for flags in per_query.values())
    fp = len(per_query) - tp
    revisit_set = set(revisits.tolist())
    recalled_ids = {q for q, flags in per_query.items() if q in revisit_set and any(flags)}
    recalled = len(recalled_ids)
    kinds = classify_revisits(pos, revisits, cfg.revisit_radius, cfg.min_frame_gap, cfg.view_angle_deg, rear_camera)
    hit = np.array([q in recalled_ids for q in kinds.ids.tolist()], bool)
    n_visible = int(kinds.visible.sum())
    return LoopEvaluation(
        precision=tp / len(per_query) if per_query else None,
        recall=recalled / len(revisit_set) if revisit_set else None,
        n_revisits=len(revisit_set),
        n_query_keyframes=len(per_query),
        n_true_positive_queries=tp,
        n_false_positive_queries=fp,
        n_recalled_revisits=recalled,
        recall_visible=int((hit & kinds.visible).sum()) / n_visible if n_visible else None,
        n_visible_revisits=n_visible,
        n_recalled_visible=int((hit & kinds.visible).sum()),
        by_direction={
            name: _recall_counts(hit[mask], kinds.visible[mask])
            for name, mask in (("forward", kinds.forward), ("reverse", ~kinds.forward))
        },
        n_loops=len(correct_flags),
        n_correct_loops=int(sum(correct_flags)),
        loop_correct=correct_flags,
        loop_distance_m=distances,
        revisit_ids=sorted(revisit_set),
    )


def _recall_counts(hit: np.ndarray, visible: np.ndarray) -> dict[str, float | int | None]:
    n, n_vis = len(hit), int(visible.sum())
    return {
        "revisits": n,
        "recalled": int(hit.sum()),
        "recall": float(hit.sum()) / n if n else None,
        "visible": n_vis,
        "recall_visible": float((hit & visible).sum()) / n_vis if n_vis else None,
    }


def _loop_ids(k: int, loop: tuple[int, int], n: int) -> tuple[int, int]:
    try:
        q, m = (int(v) for v in loop)
    except (TypeError, ValueError):
        raise ValueError(f"loops[{k}]: expected a (query, match) pair of ints, got {loop!r}") from None
    for name, idx in (("query", q), ("match", m)):
        if not 0 <= idx < n:
            raise ValueError(f"loops[{k}]: {name} keyframe {idx} outside 0..{n - 1}")
    return q, m
