"""A keyframe's thumbnail, made when the keyframe is selected (the run keeps no full image):
the picture `trajectory.mcap` shows for each keyframe, and the live view for the current one.
Its own module so the SLAM core that makes thumbnails loads no MCAP writer."""

from __future__ import annotations

import logging

import cv2
import numpy as np

_JPEG_QUALITY = 80

log = logging.getLogger(__name__)


def thumbnail_jpeg(image: np.ndarray, width: int, name: str = "keyframe image") -> bytes | None:
    """A keyframe's thumbnail: the RGB image area-averaged to `width` pixels (never enlarged),
    as JPEG bytes (a few kB), made once when the keyframe is selected.

    None, with a warning, for an array that is no picture (no pixels, not HxW or HxWxC with 1,
    3 or 4 channels) or that cv2 cannot encode: a thumbnail only decorates trajectory.mcap, so
    it must never be what ends a run."""
    problem = _thumbnail_problem(image)
    if problem is None:
        try:
            return _encode_thumbnail(np.ascontiguousarray(image, np.uint8), width)
        except (cv2.error, ValueError) as error:
            problem = f"cv2 could not encode it ({error})"
    log.warning("%s: no thumbnail in trajectory.mcap, the %s array %s", name, np.shape(image), problem)
    return None


def _thumbnail_problem(image: np.ndarray) -> str | None:
    """Why `image` cannot become a thumbnail, or None."""
    shape = np.shape(image)
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] not in (1, 3, 4)):
        return "is not an HxW or HxWxC (C = 1, 3, 4) picture"
    if shape[0] == 0 or shape[1] == 0:
        return "has no pixels"
    return None


def _encode_thumbnail(image: np.ndarray, width: int) -> bytes:
    """JPEG bytes of a uint8 picture that `_thumbnail_problem` passed, at most `width` wide."""
    h, w = image.shape[:2]
    if w > width:
        image = cv2.resize(image, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    if image.ndim == 2 or image.shape[2] == 1:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    ok, jpeg = cv2.imencode(
        ".jpg", cv2.cvtColor(image[:, :, :3], cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, _JPEG_QUALITY]
    )
    if not ok:
        raise ValueError("imencode returned no data")
    return jpeg.tobytes()
