"""Two-view verification of a recognised place from the backbone's own features.

Recognition says two images look alike; geometry says whether they can be two views of one
rigid scene. Dense conv4_2 matches (`dense_matches`) go to OpenCV's USAC MAGSAC, which fits a
fundamental matrix: the pair verifies when enough matches, and a large enough share of them, are
its inliers. The share is what separates: a wrong place still yields a hundred chance inliers on
a textured street, but they are a small part of what matched (docs/loop_verification.md has the
figures on the shared day/night and summer/winter pairs). The rule needs no intrinsics, so it
is the same for VPR folders, which carry none, and for a calibrated log. With intrinsics the
verified matches also give the relative pose: an essential matrix (a rotation and the direction
of the baseline, whose length two views cannot tell), or a rotation alone where a homography
explains them as well (no baseline).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.config import VerifierConfig
from loopclosure.dense_matches import DenseFeatures, dense_features, mutual_matches
from loopclosure.errors import LoopClosureInputError

MIN_MODEL_POINTS = 8
"""Fewer matches than this support neither the 5-point nor the 7/8-point model."""


@dataclass(frozen=True)
class PairVerdict:
    """What the geometry of two views says. rotation / direction (with intrinsics only): camera
    b's orientation in camera a's optical frame (R_ab) and the unit direction from a's centre to
    b's, in a's frame (its length is unknown; None for a rotation only). n_inliers: the
    fundamental matrix's, which decide."""

    accepted: bool
    model: str  # "fundamental" (no pose), "essential", "rotation" (no baseline), "none" (too few matches),
    # "unverifiable" (images too small for geometry: neither verified nor refused by their views)
    n_matches: int
    n_inliers: int
    rotation: np.ndarray | None
    direction: np.ndarray | None
    reason: str

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / self.n_matches if self.n_matches else 0.0

    @property
    def verifiable(self) -> bool:
        """False when the images were too small to tell: not accepted, yet no evidence against."""
        return self.model != "unverifiable"


class PairVerifier:
    """`features(image)` once per image, `verify(a, b)` per pair (or `verify_images`)."""

    def __init__(self, backbone: Backbone, config: VerifierConfig | None = None) -> None:
        self.backbone = backbone
        self.config = config or VerifierConfig()

    def features(self, image: np.ndarray, name: str = "image") -> DenseFeatures:
        cfg = self.config
        return dense_features(self.backbone, image, cfg.layer, cfg.width, name, cfg.grey)

    def verify_images(
        self, image_a: np.ndarray, image_b: np.ndarray, k_a: np.ndarray | None = None, k_b: np.ndarray | None = None
    ) -> PairVerdict:
        return self.verify(self.features(image_a, "image_a"), self.features(image_b, "image_b"), k_a, k_b)

    def verify(
        self, a: DenseFeatures, b: DenseFeatures, k_a: np.ndarray | None = None, k_b: np.ndarray | None = None
    ) -> PairVerdict:
        """Whether the pair verifies (the fundamental matrix, with or without intrinsics: one rule,
        measured on real pairs whatever the calibration), and with both intrinsics (3x3, for the
        images' pixels as given to `features`) the relative pose its inliers hold."""
        if (k_a is None) != (k_b is None):
            raise LoopClosureInputError("verify: give the intrinsics of both images or of neither")
        cfg = self.config
        small = [size for size in (a.image_size, b.image_size) if size[0] < cfg.min_image_width]
        if small:
            width, height = small[0]
            reason = f"a {width}x{height} px image is too small to verify by two views (min_image_width {cfg.min_image_width})"
            return PairVerdict(False, "unverifiable", 0, 0, None, None, reason)
        matches = mutual_matches(a, b, cfg.max_distance_ratio)
        n = len(matches)
        if n < max(MIN_MODEL_POINTS, cfg.min_inliers):
            return PairVerdict(False, "none", n, 0, None, None, f"only {n} mutual matches")
        # in cell units: a match is only as precise as its cell, whatever each image's size
        f, mask = cv2.findFundamentalMat(
            matches.cells_a, matches.cells_b, cv2.USAC_MAGSAC, cfg.threshold_cells, cfg.confidence, cfg.max_iterations
        )
        inliers = mask.ravel().astype(bool) if f is not None and mask is not None else np.zeros(n, bool)
        verdict = self._judged(n, int(inliers.sum()))
        if not verdict.accepted or k_a is None or k_b is None:
            return verdict
        points_a, points_b = a.pixels(matches.cells_a[inliers]), b.pixels(matches.cells_b[inliers])
        cell_px = float(np.mean([*a.scale, *b.scale]))
        return self._posed(verdict, points_a, points_b, _intrinsics(k_a), _intrinsics(k_b), cell_px)

    def _posed(
        self, verdict: PairVerdict, points_a: np.ndarray, points_b: np.ndarray, k_a: np.ndarray, k_b: np.ndarray,
        cell_px: float,
    ) -> PairVerdict:  # fmt: skip
        """The pose the verified matches hold: the essential matrix on normalised coordinates
        (each image with its own K); where a homography explains nearly as many of them and is a
        rotation, the views differ by a rotation only (a revisit from the same spot, where E is
        degenerate), which is read from it and the direction left unknown."""
        cfg = self.config
        norm_a = cv2.undistortPoints(points_a.reshape(-1, 1, 2), k_a, None).reshape(-1, 2)
        norm_b = cv2.undistortPoints(points_b.reshape(-1, 1, 2), k_b, None).reshape(-1, 2)
        focal = float(np.mean([k_a[0, 0], k_a[1, 1], k_b[0, 0], k_b[1, 1]]))
        threshold = cfg.threshold_cells * cell_px / focal
        unit = np.eye(3)
        e, e_mask = cv2.findEssentialMat(
            norm_a, norm_b, unit, cv2.USAC_MAGSAC, cfg.confidence, threshold, cfg.max_iterations
        )
        if e is None or e_mask is None or e.shape[0] < 3:
            return replace(verdict, reason=verdict.reason + "; no essential matrix: no pose")
        e = e[:3]  # several solutions may be stacked; the first is the one MAGSAC scored
        n_e = int(e_mask.sum())
        h, h_mask = cv2.findHomography(norm_a, norm_b, cv2.USAC_MAGSAC, threshold, None, cfg.max_iterations,
                                       cfg.confidence)  # fmt: skip
        n_h = int(h_mask.sum()) if h is not None and h_mask is not None else 0
        if h is not None and n_h >= cfg.homography_share * n_e:
            r_ba = _rotation_of(h, cfg.rotation_tolerance)
            if r_ba is not None:
                words = f"; a rotation only: a homography explains {n_h} of the {n_e} essential-matrix inliers"
                return replace(verdict, model="rotation", rotation=r_ba.T, reason=verdict.reason + words)
        n_pose, r_ba, t_ba, _ = cv2.recoverPose(e, norm_a, norm_b, unit, mask=e_mask.copy())
        if n_pose < cfg.min_inliers // 2:
            return replace(
                verdict, reason=verdict.reason + f"; only {n_pose} matches in front of both cameras: no pose"
            )
        # x_b = R_ba x_a + t_ba: b's centre sits at -R_ba^T t_ba in a's frame
        baseline = -r_ba.T @ t_ba.ravel()
        length = float(np.linalg.norm(baseline))
        direction = baseline / length if length > 0 else None
        words = f"; essential matrix: {n_pose} of them in front of both cameras"
        return replace(verdict, model="essential", rotation=r_ba.T, direction=direction, reason=verdict.reason + words)

    def _judged(self, n: int, inliers: int) -> PairVerdict:
        cfg = self.config
        ratio = inliers / n if n else 0.0
        problems = []
        if inliers < cfg.min_inliers:
            problems.append(f"{inliers} inliers < {cfg.min_inliers}")
        if ratio < cfg.min_inlier_ratio:
            problems.append(f"inlier share {ratio:.2f} < {cfg.min_inlier_ratio:.2f}")
        words = f"fundamental matrix: {inliers} of {n} deep-feature matches are inliers"
        reason = words if not problems else f"{words}; " + "; ".join(problems)
        return PairVerdict(not problems, "fundamental", n, inliers, None, None, reason)


def _rotation_of(h: np.ndarray, tolerance: float) -> np.ndarray | None:
    """R with x_b ~ R x_a if the normalised homography is (close to) a rotation, else None."""
    det = np.linalg.det(h)
    if not np.isfinite(det) or abs(det) < np.finfo(float).tiny:
        return None
    m = h / np.cbrt(det)
    u, sv, vt = np.linalg.svd(m)
    if sv[-1] / sv[0] < 1.0 - tolerance:
        return None
    r = u @ vt
    return r if np.linalg.det(r) > 0 else None


def _intrinsics(k: np.ndarray) -> np.ndarray:
    k = np.asarray(k, dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise LoopClosureInputError(f"intrinsics: expected a finite 3x3 K with positive focal lengths, got {k!r}")
    return k
