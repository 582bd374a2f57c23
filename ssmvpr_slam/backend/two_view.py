"""Relative camera rotation between two images of the same place (no LiDAR available).

By default from the backbone's deep features (`deep_rotation`, `loopclosure.pair_verifier`);
with `two_view.method: orb`: ORB features, Lowe-ratio matching, then two models fitted with RANSAC:
* the essential matrix (`cv2.findEssentialMat` + `cv2.recoverPose`), valid with a baseline;
* a homography; if it explains (nearly) as many matches as E does and ``K^-1 H K`` is a
  scaled rotation, the views differ by a pure rotation (a revisit from the same spot), where
  E is degenerate, and the rotation is read from H instead.
The translation direction of E is discarded: its scale is unknown, so the caller uses a
place prior (zero translation with a radius-sized sigma).

Keyframes keep a `ReducedImage` (grey, down-sampled to a pixel budget) rather than the camera
image: a full image held for the whole run costs megabytes per keyframe. The intrinsics are
those of the full image (from the config, or from hfov_deg and the full width) scaled to the
kept pixels, so a calibration given for the camera's resolution stays valid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ssmvpr_slam.backend.config import TwoViewConfig
from ssmvpr_slam.backend.se3 import project_to_so3, rotation_angle

if TYPE_CHECKING:
    from loopclosure.pair_verifier import PairVerifier

MIN_MODEL_POINTS = 8
"""Fewer matches than this cannot support either RANSAC model (5-point E, 4-point H)."""
UINT8_MAX = 255.0


@dataclass(frozen=True)
class ReducedImage:
    """What a keyframe keeps of a camera image for two-view registration: a grey copy
    area-averaged to a pixel budget and held as lossless PNG bytes (about half the raw size;
    decoded only when a loop is registered), with the size it was taken at, from which K is
    scaled (see `intrinsics`). A checkpoint writes the bytes as they are, so a resume is exact."""

    png: bytes
    width: int
    height: int
    full_width: int
    full_height: int

    @property
    def gray(self) -> np.ndarray:
        """The kept (height, width) uint8 pixels."""
        pixels = cv2.imdecode(np.frombuffer(self.png, np.uint8), cv2.IMREAD_UNCHANGED)
        if pixels is None or pixels.shape != (self.height, self.width):
            raise ValueError(f"kept keyframe image: not a {self.width}x{self.height} grey PNG")
        return pixels

    @property
    def scale(self) -> tuple[float, float]:
        """(kept / full) along x and y."""
        return self.width / self.full_width, self.height / self.full_height

    @property
    def nbytes(self) -> int:
        return len(self.png)

    @classmethod
    def from_png(cls, png: bytes, full_width: int, full_height: int) -> ReducedImage:
        """Read back from its PNG bytes (a checkpoint); ValueError if they are not a grey image."""
        pixels = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED) if png else None
        if pixels is None or pixels.ndim != 2 or pixels.dtype != np.uint8:
            raise ValueError("not a grey 8-bit PNG image")
        return cls(bytes(png), pixels.shape[1], pixels.shape[0], int(full_width), int(full_height))


def reduce_image(image: np.ndarray, max_pixels: int | None, name: str = "image") -> ReducedImage:
    """The `ReducedImage` of a camera image: grey, area-averaged down to at most `max_pixels`
    pixels with its aspect kept (None, or an image within the budget: full size)."""
    gray = to_gray(name, image)
    h, w = gray.shape
    if max_pixels is not None and h * w > max_pixels:
        f = float(np.sqrt(max_pixels / (h * w)))
        size = (max(1, int(w * f)), max(1, int(h * f)))  # rounded down: within the budget
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    ok, png = cv2.imencode(".png", gray)
    if not ok:
        raise ValueError(f"{name}: cv2 could not encode its grey copy as PNG")
    return ReducedImage(png.tobytes(), gray.shape[1], gray.shape[0], w, h)


@dataclass(frozen=True)
class TwoViewRotation:
    """Rotation of the query camera in the matched camera's frame (optical axes), or None."""

    rotation_mq: np.ndarray | None
    model: str  # essential, homography (ORB); deep, deep_orb (deep features verified, rotation from ORB); none
    n_matches: int
    n_inliers: int
    error_px: float
    reason: str
    refused: bool = False
    """The deep features judged the pair and found no common rigid scene: evidence against the
    loop, not merely no geometry (ORB finding nothing across light, images too small to judge)."""


def to_gray(name: str, image: object) -> np.ndarray:
    """uint8 grayscale from (H, W), (H, W, 1), (H, W, 3) RGB or (H, W, 4) RGBA arrays."""
    if not isinstance(image, np.ndarray):
        raise ValueError(f"{name}: expected a numpy image array, got {type(image).__name__}")
    img = image
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, :3]
    elif img.ndim != 2:
        raise ValueError(f"{name}: expected (H, W) or (H, W, 3) image, got shape {image.shape}")
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"{name}: image is empty, shape {image.shape}")
    if img.dtype != np.uint8:
        data = img.astype(np.float64)
        if not np.all(np.isfinite(data)):
            raise ValueError(f"{name}: image contains NaN or inf")
        if data.max(initial=0.0) <= 1.0:
            data = data * UINT8_MAX
        img = np.clip(np.rint(data), 0, UINT8_MAX).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)


def intrinsics(config: TwoViewConfig, width: int, height: int, scale: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Pinhole K from the config for a (width, height) image; unset entries come from the image
    size and hfov_deg. scale: the kept image's size over that one (`ReducedImage.scale`); pixel
    centres map as x' = (x + 0.5) s - 0.5, as cv2.resize samples them."""
    fx = config.fx
    if fx is None:
        fx = width / (2.0 * np.tan(np.radians(config.hfov_deg) / 2.0))
    fy = config.fy if config.fy is not None else fx
    cx = config.cx if config.cx is not None else (width - 1) / 2.0
    cy = config.cy if config.cy is not None else (height - 1) / 2.0
    sx, sy = scale
    return np.array([[fx * sx, 0.0, (cx + 0.5) * sx - 0.5], [0.0, fy * sy, (cy + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])


def _matches(gray_m: np.ndarray, gray_q: np.ndarray, cfg: TwoViewConfig) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of ORB matches that pass Lowe's ratio test."""
    orb = cv2.ORB_create(nfeatures=cfg.orb_features)  # type: ignore[attr-defined]  # absent from cv2's stubs
    kp_m, des_m = orb.detectAndCompute(gray_m, None)
    kp_q, des_q = orb.detectAndCompute(gray_q, None)
    if des_m is None or des_q is None or len(kp_m) < 2 or len(kp_q) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(des_m, des_q, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < cfg.ratio_test * p[1].distance]
    pts_m = np.array([kp_m[g.queryIdx].pt for g in good], dtype=np.float64).reshape(-1, 2)
    pts_q = np.array([kp_q[g.trainIdx].pt for g in good], dtype=np.float64).reshape(-1, 2)
    return pts_m, pts_q


def _rotation_from_homography(h: np.ndarray, k: np.ndarray, tol: float) -> np.ndarray | None:
    """R_qm with x_q ~ K R_qm K^-1 x_m if H is (close to) such an infinite homography."""
    m = np.linalg.inv(k) @ h @ k
    det = np.linalg.det(m)
    if not np.isfinite(det) or abs(det) < np.finfo(float).tiny:
        return None
    m = m / np.cbrt(det)
    sv = np.linalg.svd(m, compute_uv=False)
    if sv[-1] / sv[0] < 1.0 - tol:
        return None
    return project_to_so3(m)


def _transfer_error(h: np.ndarray, pts_m: np.ndarray, pts_q: np.ndarray) -> np.ndarray:
    proj = cv2.perspectiveTransform(pts_m.reshape(-1, 1, 2), h).reshape(-1, 2)
    return np.linalg.norm(proj - pts_q, axis=1)


def _sampson(e_px: np.ndarray, pts_m: np.ndarray, pts_q: np.ndarray) -> np.ndarray:
    """Sampson distance (px) of matches to the epipolar geometry F (pixel coordinates)."""
    x1 = np.c_[pts_m, np.ones(len(pts_m))]
    x2 = np.c_[pts_q, np.ones(len(pts_q))]
    fx1 = x1 @ e_px.T
    ftx2 = x2 @ e_px
    num = np.sum(x2 * fx1, axis=1) ** 2
    den = fx1[:, 0] ** 2 + fx1[:, 1] ** 2 + ftx2[:, 0] ** 2 + ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, np.finfo(float).tiny))


def _gray_and_size(
    name: str, image: np.ndarray | ReducedImage
) -> tuple[np.ndarray, tuple[int, int], tuple[float, float]]:
    """(grey pixels, full (width, height), kept/full scale) of a camera image or a kept copy."""
    if isinstance(image, ReducedImage):
        return to_gray(name, image.gray), (image.full_width, image.full_height), image.scale
    gray = to_gray(name, image)
    return gray, (gray.shape[1], gray.shape[0]), (1.0, 1.0)


def _same_camera(
    image_m: np.ndarray | ReducedImage, image_q: np.ndarray | ReducedImage, config: TwoViewConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """(grey m, grey q, K of the pixels as kept), or why the two cannot be one camera's views."""
    gray_m, full_m, scale = _gray_and_size("match_image", image_m)
    gray_q, full_q, _ = _gray_and_size("query_image", image_q)
    if gray_m.shape != gray_q.shape or full_m != full_q:
        return f"image sizes differ: {gray_m.shape} vs {gray_q.shape} (from {full_m} vs {full_q})"
    return gray_m, gray_q, intrinsics(config, full_m[0], full_m[1], scale)


def estimate_rotation(
    image_m: np.ndarray | ReducedImage, image_q: np.ndarray | ReducedImage, config: TwoViewConfig
) -> TwoViewRotation:
    """Rotation of camera q in camera m's optical frame (R_mq), or None with a reason.

    Either image may be a `ReducedImage`; both must then come from the same camera size and
    be kept at the same size."""
    pair = _same_camera(image_m, image_q, config)
    if isinstance(pair, str):
        return _failed(0, 0, pair)
    gray_m, gray_q, k = pair
    pts_m, pts_q = _matches(gray_m, gray_q, config)
    n = len(pts_m)
    if n < max(MIN_MODEL_POINTS, config.min_inliers):
        return _failed(n, 0, f"only {n} ORB matches")
    e, e_mask = cv2.findEssentialMat(
        pts_m,
        pts_q,
        k,
        method=cv2.RANSAC,
        prob=config.ransac_confidence,
        threshold=config.ransac_threshold_px,
    )
    h, h_mask = cv2.findHomography(
        pts_m,
        pts_q,
        cv2.RANSAC,
        config.homography_threshold_px,
        confidence=config.ransac_confidence,
    )
    n_e = int(e_mask.sum()) if e is not None and e.shape == (3, 3) else 0
    n_h = int(h_mask.sum()) if h is not None else 0
    if h is not None and n_h >= config.min_inliers and n_h >= config.homography_share * n_e:
        r_qm = _rotation_from_homography(h, k, config.rotation_singular_tol)
        if r_qm is not None:
            inl = h_mask.ravel().astype(bool)
            err = float(np.mean(_transfer_error(h, pts_m[inl], pts_q[inl])))
            reason = f"pure rotation: {n_h}/{n} homography inliers"
            return TwoViewRotation(r_qm.T, "homography", n, n_h, err, reason)
    if n_e < config.min_inliers:
        return _failed(n, n_e, f"only {n_e} essential-matrix inliers of {n} matches")
    e = e[:3]  # findEssentialMat may stack several solutions; RANSAC picked the first
    n_pose, r_qm, _, pose_mask = cv2.recoverPose(e, pts_m, pts_q, k, mask=e_mask.copy())
    if n_pose < config.min_inliers:
        return _failed(n, int(n_pose), f"only {n_pose} matches pass the cheirality check")
    k_inv = np.linalg.inv(k)
    f_px = k_inv.T @ e @ k_inv
    inl = pose_mask.ravel().astype(bool)
    err = float(np.mean(_sampson(f_px, pts_m[inl], pts_q[inl])))
    reason = f"essential matrix: {n_pose}/{n} inliers"
    return TwoViewRotation(project_to_so3(r_qm).T, "essential", n, int(n_pose), err, reason)


def deep_rotation(
    image_m: np.ndarray | ReducedImage,
    image_q: np.ndarray | ReducedImage,
    config: TwoViewConfig,
    verifier: PairVerifier,
) -> TwoViewRotation:
    """As `estimate_rotation`, from the backbone's deep features and an essential matrix with the
    intrinsics of the images as kept (`loopclosure.pair_verifier`). The deep features decide
    (they hold across light); their positions are conv4_2 cells, so where ORB gives a rotation
    too and it agrees within `orb_agreement_deg`, ORB's sub-pixel keypoints give the rotation
    (on the demo's loops: median error 0.6 deg against 1.3; docs/loop_verification.md). error_px
    is NaN: MAGSAC scores its inliers by a marginalised threshold, not one residual."""
    pair = _same_camera(image_m, image_q, config)
    if isinstance(pair, str):
        return _failed(0, 0, pair)
    gray_m, gray_q, k = pair
    verdict = verifier.verify(verifier.features(gray_m, "match_image"), verifier.features(gray_q, "query_image"), k, k)
    if not verdict.accepted or verdict.rotation is None:
        refused = not verdict.accepted and verdict.verifiable
        return _failed(verdict.n_matches, verdict.n_inliers, verdict.reason, refused)
    rotation, reason = project_to_so3(verdict.rotation), verdict.reason
    if config.orb_refines_deep:
        orb = estimate_rotation(image_m, image_q, config)
        if orb.rotation_mq is not None:
            apart = math.degrees(rotation_angle(orb.rotation_mq.T @ rotation))
            if apart <= config.orb_agreement_deg:
                reason += f"; rotation from ORB ({orb.reason}), {apart:.1f} deg from the deep features'"
                return TwoViewRotation(orb.rotation_mq, "deep_orb", verdict.n_matches, verdict.n_inliers,
                                       float("nan"), reason)  # fmt: skip
    return TwoViewRotation(rotation, "deep", verdict.n_matches, verdict.n_inliers, float("nan"), reason)


def _failed(n_matches: int, n_inliers: int, reason: str, refused: bool = False) -> TwoViewRotation:
    return TwoViewRotation(None, "none", n_matches, n_inliers, float("nan"), reason, refused)
