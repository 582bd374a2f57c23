"""A merged map judged against one world's ground truth (sessions simulated in one city, or
logs with ground truth in a common frame).

- ATE of the merged map: every keyframe of the map's sessions with one SE(3) alignment for the
  whole map (per-session alignment would hide a session placed wrongly in the map);
- ATE of each session in the map (its own alignment), beside its own run's;
- cross-session loops: precision of those in the graph (a loop is correct within the loop
  metrics' `correct_radius`), and recall over the keyframes that revisit another session's
  place (ground truth within `revisit_radius`): the share with a cross-session loop in the graph;
- the share of sessions merged into the map.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from ssmvpr_slam.backend.graph_optimizer import OptimizerSettings
from ssmvpr_slam.backend.se3 import invert
from ssmvpr_slam.evaluation.config import LoopMetricsConfig
from ssmvpr_slam.evaluation.metrics import ate
from ssmvpr_slam.multi_session.cross_loops import CrossLoop
from ssmvpr_slam.multi_session.merged_graph import CrossEdge, build_map_graph, solve_map_graph
from ssmvpr_slam.multi_session.session_map import SessionMap


def loop_distance(loop: CrossLoop, truth: list[np.ndarray | None]) -> float | None:
    """Ground-truth distance between a cross-session loop's two keyframes (None without it)."""
    q, m = truth[loop.query], truth[loop.match]
    if q is None or m is None:
        return None
    return float(np.linalg.norm(q[loop.query_kf, :3, 3] - m[loop.match_kf, :3, 3]))


def cross_session_revisits(truth: list[np.ndarray | None], radius: float) -> dict[int, np.ndarray]:
    """Session -> which of its keyframes lie within `radius` of another session's keyframe."""
    out = {}
    for s, gt in enumerate(truth):
        if gt is None:
            continue
        others = [g[:, :3, 3] for k, g in enumerate(truth) if k != s and g is not None]
        if not others:
            out[s] = np.zeros(len(gt), bool)
            continue
        tree = cKDTree(np.concatenate(others))
        distance, _ = tree.query(gt[:, :3, 3], k=1)
        out[s] = distance <= radius
    return out


def evaluate_map(
    sessions: list[SessionMap],
    asked: int,
    map_sessions: list[int],
    map_poses: dict[int, np.ndarray],
    loops: list[CrossLoop],
    in_graph: dict[int, bool],
    config: LoopMetricsConfig,
) -> dict[str, Any]:
    """Metrics of the merged map (the component `map_sessions`, poses by session); `asked`: the
    sessions asked for, the failed ones included (what the merged fraction is of)."""
    truth = [s.gt_poses() for s in sessions]
    out: dict[str, Any] = {
        "sessions": asked,
        "sessions_merged": len(map_sessions),
        "merged_fraction": len(map_sessions) / asked if asked else 0.0,
    }
    known = {s: gt for s in map_sessions if (gt := truth[s]) is not None}
    if known and sum(len(gt) for gt in known.values()) >= 3:
        gt_all = np.concatenate(list(known.values()))
        est = np.concatenate([map_poses[s] for s in known])
        out["ate_merged_m"] = ate(gt_all, est, "se3").stats.rmse
        out["ate_per_session_m"] = {
            sessions[s].name: ate(gt, map_poses[s], "se3").stats.rmse for s, gt in known.items()
        }
        out["ate_own_run_m"] = {
            sessions[s].name: ate(gt, sessions[s].poses, "se3").stats.rmse for s, gt in known.items()
        }
    kept = [k for k, yes in in_graph.items() if yes]
    distances = [loop_distance(loops[k], truth) for k in kept]
    judged = [d for d in distances if d is not None]
    out["cross_session_loops"] = {
        "proposed_accepted": len(loops),
        "verified": sum(loop.verified for loop in loops),
        "in_graph": len(kept),
        "correct": sum(d <= config.correct_radius for d in judged),
    }
    out["cross_session_precision"] = sum(d <= config.correct_radius for d in judged) / len(judged) if judged else None
    revisits = cross_session_revisits(truth, config.revisit_radius)
    found = {(loops[k].query, loops[k].query_kf) for k in kept}
    found |= {(loops[k].match, loops[k].match_kf) for k in kept}
    total = sum(int(r.sum()) for r in revisits.values())
    hit = sum(int(r[kf]) for s, r in revisits.items() for kf in range(len(r)) if (s, kf) in found)
    out["cross_session_revisit_keyframes"] = total
    out["cross_session_recall"] = hit / total if total else None
    return out


def oracle_ate(sessions: list[SessionMap], radius: float, rot_sigma: float, trans_sigma: float) -> float | None:
    """ATE of the map with perfect cross-session loops: every keyframe within `radius` of an
    earlier session's keyframe gets a loop to the nearest one, measured from the ground truth
    with the ICP loops' sigmas; each session keeps its own odometry and loops. The bound the
    merged map is measured against (what recognition that missed nothing and registration
    without error would give)."""
    truth = [s.gt_poses() for s in sessions]
    members = [k for k, gt in enumerate(truth) if gt is not None]
    if len(members) < 2:
        return None
    information = np.diag(1.0 / np.square([rot_sigma] * 3 + [trans_sigma] * 3))
    edges = []
    for position, q in enumerate(members):
        earlier = members[:position]
        if not earlier:
            continue
        points = np.concatenate([truth[m][:, :3, 3] for m in earlier])  # type: ignore[index]
        owner = np.concatenate([[(m, k) for k in range(len(truth[m]))] for m in earlier])  # type: ignore[arg-type]
        distance, nearest = cKDTree(points).query(truth[q][:, :3, 3], k=1)  # type: ignore[index]
        for kf in np.flatnonzero(distance <= radius).tolist():
            m, mk = (int(v) for v in owner[nearest[kf]])
            T_mq = invert(truth[m][mk]) @ truth[q][kf]  # type: ignore[index]
            edges.append(CrossEdge(q, kf, m, mk, T_mq, information))
    # each session's frame placed by its ground truth (the initial estimate; the loops then decide)
    first = members[0]
    world_of = {k: truth[k][0] @ invert(sessions[k].poses[0]) for k in members}  # type: ignore[index]
    frames = {k: invert(world_of[first]) @ world_of[k] for k in members}
    graph = build_map_graph(members, sessions, frames, edges)
    result = solve_map_graph(graph, OptimizerSettings(kernel="none", gnc=False, refine_scales=()))
    gt = np.concatenate([truth[k] for k in members])  # type: ignore[misc]
    est = np.concatenate([graph.session_poses(result.poses, k, len(sessions[k])) for k in members])
    return ate(gt, est, "se3").stats.rmse
