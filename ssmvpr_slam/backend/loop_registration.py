"""Relative pose of an accepted loop closure between query keyframe q and matched keyframe m.

Convention: ``T_mq = inv(T_m) @ T_q``, the pose of the query keyframe in the matched
keyframe's body frame; it maps query-frame points into the matched frame. Feed it to the
pose graph as ``graph.add_loop(m, q, reg.T_mq, sigmas=reg.sigmas)`` when ``reg.accepted``.
The yaw guess is the yaw of T_mq (rotation of q about the body z axis relative to m, rad);
the caller derives it from the visual spatial matching's dominant column shift.

Which path is used when:
* LiDAR scans available -> `LoopRegistrar.register_scans`: the query scan is aligned to the
  matched keyframe's scan, or to a small local map of keyframes m-k..m+k built with
  `build_local_map`, by kiss-icp's point-to-point ICP from zero translation and each yaw in
  guess + `yaw_seed_offsets_deg`, after a full pose guess when the caller has one (`carry_loop`:
  the previous loop of the same revisit); the best seed (highest inlier ratio, then lowest
  RMSE) wins.
  Accepted only if the inlier ratio and the inlier RMSE pass the config thresholds; rejected
  (with a reason, never an exception) when either cloud is too small after cleaning.
* No LiDAR -> `LoopRegistrar.register_images`: a place prior. Translation is zero with
  `two_view.translation_sigma` (3 m: see its description): the essential matrix gives the direction of
  the baseline but not its length, and the recogniser vouches for the place, not for a distance.
  Rotation comes from two-view geometry when it verifies, with `two_view.rot_sigma` (keypoints)
  or `deep_rot_sigma` (the deep features' cells alone): by default
  the backbone's conv4_2 cells matched across the two images and an essential matrix fitted
  by MAGSAC (`loopclosure.pair_verifier`, which holds across day and night); with
  `two_view.method: orb`, ORB + essential matrix / pure-rotation homography. Otherwise the
  rotation is the yaw guess with the looser yaw-prior sigmas.
  By default a place prior is always accepted: the recogniser and sequence gate already vouched
  for the place, and the wide sigmas plus the graph's robust kernel bound the damage if it is
  wrong. With `two_view.on_geometry_failure: reject` a pair of images that gives no rotation
  is rejected instead, as ICP rejects a poor alignment (a keyframe without a kept image still
  gets the yaw prior: there is nothing to check it against).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ssmvpr_slam.backend.config import LoopRegistrationConfig
from ssmvpr_slam.backend.icp import SeededIcp, clean_points, transform_points
from ssmvpr_slam.backend.noise import sigmas6
from ssmvpr_slam.backend.se3 import as_pose, invert, make_pose, project_to_so3, rot_z, yaw_of
from ssmvpr_slam.backend.two_view import ReducedImage, TwoViewRotation, deep_rotation, estimate_rotation

if TYPE_CHECKING:
    from loopclosure.pair_verifier import PairVerifier


@dataclass(frozen=True)
class LoopRegistration:
    """Result of registering a loop q -> m (see the module docstring for the convention)."""

    T_mq: np.ndarray
    """inv(T_m) @ T_q: query keyframe pose in the matched keyframe's frame."""
    accepted: bool
    reason: str
    inlier_ratio: float
    """ICP: share of query points within inlier_distance of the map; two-view: inliers/matches."""
    rmse: float
    """ICP: RMSE of inlier distances (m); two-view: mean inlier error (px); NaN otherwise."""
    sigmas: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    """Loop factor sigmas (rx, ry, rz, tx, ty, tz) for `PoseGraph.add_loop`."""
    method: str = "icp"
    """'icp', 'two_view_deep' (deep features, essential matrix), 'two_view_essential',
    'two_view_homography' (ORB), 'two_view_failed' (rejected),
    'yaw_prior', 'unverified' (a yaw prior no earlier loop vouched for: rejected), or, not
    registered, 'spaced' and 'implausible' (`LoopRegistrar.spaced`, `.implausible`)."""
    yaw_seed: float = float("nan")
    """ICP: the yaw seed (rad) that won."""
    views_refused: bool = False
    """A yaw prior because the deep features judged the two views and refused them (not merely
    found no geometry): only loops a scan or two views verified may then vouch for it."""

    @property
    def T_qm(self) -> np.ndarray:
        """inv(T_mq): matched keyframe pose in the query keyframe's frame."""
        return invert(self.T_mq)

    def to_dict(self) -> dict[str, object]:
        """JSON-ready record (NaN becomes None) for loop_closures.csv / metrics.json."""

        def num(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)

        return {
            "accepted": self.accepted,
            "reason": self.reason,
            "method": self.method,
            "inlier_ratio": num(self.inlier_ratio),
            "rmse": num(self.rmse),
            "yaw_seed": num(self.yaw_seed),
            "T_mq": self.T_mq.tolist(),
            "sigmas": [num(s) for s in self.sigmas],
        }


def build_local_map(
    scans: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    anchor_pose: np.ndarray,
    max_range: float,
) -> np.ndarray:
    """Concatenate scans (each in its own sensor frame) into the frame of `anchor_pose`.

    `poses` are the scans' odometry poses (body-to-world); the anchor is usually the matched
    keyframe m's odometry pose, so the map is in m's frame as `register_scans` expects. Each
    scan is cleaned (NaN/inf and beyond max_range dropped) before it is moved.
    """
    if len(scans) != len(poses):
        raise ValueError(f"poses: {len(poses)} poses for {len(scans)} scans")
    if len(scans) == 0:
        raise ValueError("scans: need at least one scan to build a local map")
    anchor_inv = invert(as_pose("anchor_pose", anchor_pose))
    parts = []
    for k, (scan, pose) in enumerate(zip(scans, poses)):
        pts = clean_points(f"scans[{k}]", scan, max_range)
        parts.append(transform_points(anchor_inv @ as_pose(f"poses[{k}]", pose), pts))
    return np.concatenate(parts, axis=0)


def carry_loop(
    T_mq: np.ndarray, match_odom: np.ndarray, query_odom: np.ndarray, new_match_odom: np.ndarray,
    new_query_odom: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """A loop q -> m moved to the keyframes q' and m' a little further along both visits: each end
    is carried by its own visit's odometry over a few keyframes, which drifts far less than the
    odometry across the two visits does. Returns the guess for T_m'q'."""
    return invert(new_match_odom) @ match_odom @ T_mq @ invert(query_odom) @ new_query_odom


class LoopRegistrar:
    """Computes `LoopRegistration`s from scans (ICP) or images (place prior)."""

    def __init__(self, config: LoopRegistrationConfig | None = None, verifier: PairVerifier | None = None) -> None:
        """verifier: the deep-feature verifier on the recogniser's backbone, which `two_view.method`
        deep needs (without one, two views are registered by ORB)."""
        self.config = config or LoopRegistrationConfig()
        self.verifier = verifier
        self._icp = SeededIcp(self.config.lidar)

    # ------------------------------------------------------------------ LiDAR
    def register_scans(
        self,
        query_points: np.ndarray,
        map_points: np.ndarray,
        yaw_guess: float = 0.0,
        pose_guess: np.ndarray | None = None,
    ) -> LoopRegistration:
        """Align the query scan (query sensor frame) to `map_points` (matched keyframe frame).

        pose_guess: a full T_mq guess (`carry_loop`), tried first; when it already aligns the
        scans, screening ends there instead of starting from zero translation."""
        cfg = self.config.lidar
        yaw_guess = _finite_yaw(yaw_guess)
        query = self._icp.prepare(clean_points("query_points", query_points, cfg.max_range))
        target = self._icp.prepare(clean_points("map_points", map_points, cfg.max_range))
        for name, cloud in (("query scan", query), ("map", target)):
            n_dense = len(cloud.dense)
            if n_dense < cfg.min_points:
                return self._rejected(
                    f"{name} has {n_dense} points after cleaning and down-sampling (< {cfg.min_points})",
                    yaw_guess,
                )
        seeds_yaw = [yaw_guess + math.radians(off) for off in cfg.yaw_seed_offsets_deg]
        seeds = [make_pose(rot_z(yaw), np.zeros(3)) for yaw in seeds_yaw]
        if pose_guess is not None:
            guess = as_pose("pose_guess", pose_guess)
            seeds_yaw, seeds = [yaw_of(guess), *seeds_yaw], [guess, *seeds]
        best = self._icp.align(query, target, seeds)
        if not np.all(np.isfinite(best.pose)):
            return self._rejected("ICP returned a non-finite pose", yaw_guess)
        pose = make_pose(project_to_so3(best.pose[:3, :3]), best.pose[:3, 3])
        problems = []
        if not best.inlier_ratio >= cfg.min_inlier_ratio:
            problems.append(f"inlier ratio {best.inlier_ratio:.2f} < {cfg.min_inlier_ratio:.2f}")
        if not best.rmse <= cfg.max_rmse:
            problems.append(f"inlier RMSE {best.rmse:.3f} m > {cfg.max_rmse:.3f} m")
        accepted = self._icp.passes(best)  # what ended the seed search; `problems` only words it
        reason = (
            f"ICP converged: inlier ratio {best.inlier_ratio:.2f}, RMSE {best.rmse:.3f} m"
            if accepted
            else "poor alignment: " + "; ".join(problems)
        )
        return LoopRegistration(
            T_mq=pose,
            accepted=accepted,
            reason=reason,
            inlier_ratio=best.inlier_ratio,
            rmse=best.rmse,
            sigmas=sigmas6(cfg.rot_sigma, cfg.trans_sigma),
            method="icp",
            yaw_seed=seeds_yaw[best.seed_index],
        )

    def _rejected(
        self, reason: str, yaw_guess: float, inlier_ratio: float = 0.0, method: str = "icp"
    ) -> LoopRegistration:
        return LoopRegistration(
            T_mq=make_pose(rot_z(yaw_guess), np.zeros(3)),
            accepted=False,
            reason=reason,
            inlier_ratio=inlier_ratio,
            rmse=float("nan"),
            method=method,
        )

    # ------------------------------------------------------------------ images
    def register_images(
        self,
        query_image: np.ndarray | ReducedImage,
        match_image: np.ndarray | ReducedImage,
        yaw_guess: float = 0.0,
        query_yaw_offset: float = 0.0,
    ) -> LoopRegistration:
        """Place prior from the two keyframes' camera images or their kept grey copies
        (`ReducedImage`, intrinsics scaled to them; see the module docstring).

        query_yaw_offset: yaw of the query's camera in its body frame (pi for a rear camera
        matched against the place's forward camera)."""
        cfg = self.config.two_view
        yaw_guess = _finite_yaw(yaw_guess)
        est: TwoViewRotation
        if cfg.method == "deep" and self.verifier is not None:
            est = deep_rotation(match_image, query_image, cfg, self.verifier)
        else:
            est = estimate_rotation(match_image, query_image, cfg)
        if est.rotation_mq is None:
            ratio = est.n_inliers / est.n_matches if est.n_matches else 0.0
            if cfg.on_geometry_failure == "reject":
                return self._rejected(f"two-view geometry failed: {est.reason}", yaw_guess, ratio, "two_view_failed")
            return self.yaw_prior(yaw_guess, est.reason, ratio, views_refused=est.refused)
        body_from_cam = project_to_so3(np.asarray(cfg.body_from_camera, dtype=np.float64))
        rot = project_to_so3(body_from_cam @ est.rotation_mq @ body_from_cam.T @ rot_z(-_finite_yaw(query_yaw_offset)))
        return LoopRegistration(
            T_mq=make_pose(rot, np.zeros(3)),
            accepted=True,
            reason=est.reason,
            inlier_ratio=est.n_inliers / est.n_matches,
            rmse=est.error_px,
            sigmas=sigmas6(cfg.deep_rot_sigma if est.model == "deep" else cfg.rot_sigma, cfg.translation_sigma),
            method="two_view_deep" if est.model.startswith("deep") else f"two_view_{est.model}",
        )

    def yaw_prior(
        self, yaw_guess: float, why: str, inlier_ratio: float = 0.0, views_refused: bool = False
    ) -> LoopRegistration:
        """Place prior from the visual match alone: zero translation within `translation_sigma`,
        yaw from the spatial matching's column shift, loose roll and pitch."""
        cfg = self.config.two_view
        sigmas = np.array(
            [cfg.yaw_prior_tilt_sigma, cfg.yaw_prior_tilt_sigma, cfg.yaw_prior_yaw_sigma] + [cfg.translation_sigma] * 3
        )
        return LoopRegistration(
            T_mq=make_pose(rot_z(_finite_yaw(yaw_guess)), np.zeros(3)),
            accepted=True,
            reason=f"yaw prior from the visual match ({why})",
            inlier_ratio=inlier_ratio,
            rmse=float("nan"),
            sigmas=sigmas,
            method="yaw_prior",
            views_refused=views_refused,
        )


def _finite_yaw(yaw: float) -> float:
    try:
        value = float(yaw)
    except (TypeError, ValueError):
        raise ValueError(f"yaw_guess: expected a number in radians, got {yaw!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"yaw_guess: must be finite, got {value}")
    return value
