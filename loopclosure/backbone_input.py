"""Images in: files or arrays to the square uint8 RGB input the backbone wants."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.image_folders import IMAGE_SUFFIXES, image_files

# Below this many pixels on a side the backbone sees an upsampled blur (the input is 224 or
# more), so the codes say nothing about the place: a stream warns, a benchmark refuses.
MIN_IMAGE_SIDE = 32


def list_images(folder: str | Path) -> list[Path]:
    """Image files of a folder sorted by name, so frame order is the filename order."""
    folder = Path(folder)
    if not folder.is_dir():
        raise LoopClosureInputError(f"image folder not found: {folder}")
    files = image_files(folder)
    if not files:
        raise LoopClosureInputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder {folder}")
    return files


def read_image(path: str | Path) -> np.ndarray:
    """uint8 RGB; an unreadable or corrupt file is an error that names it."""
    data = np.fromfile(str(path), dtype=np.uint8) if Path(path).is_file() else None
    if data is None:
        raise LoopClosureInputError(f"image not found: {path}")
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise LoopClosureInputError(f"cannot decode image (corrupt or unsupported format): {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def as_rgb(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Accept HxW grey, HxWx3 RGB or HxWx4 RGBA uint8; anything else is refused with its shape."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise LoopClosureInputError(f"{name}: expected a uint8 numpy image, got {getattr(image, 'dtype', type(image))}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    if image.ndim == 3 and image.shape[2] == 4:
        return np.ascontiguousarray(image[:, :, :3])
    raise LoopClosureInputError(f"{name}: expected HxW, HxWx3 or HxWx4, got shape {image.shape}")


def too_small(image: np.ndarray, name: str = "image", min_side: int = MIN_IMAGE_SIDE) -> str | None:
    """Why `image` is too small to describe a place, or None if it is not."""
    height, width = image.shape[:2]
    if min(height, width) >= min_side:
        return None
    return f"{name}: image of {width}x{height} pixels is smaller than {min_side} px on a side; its codes are unreliable"


def resize_square(image: np.ndarray, size: int) -> np.ndarray:
    """Anisotropic resize to size x size, as the paper feeds VGG16 (no crop)."""
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise LoopClosureInputError(f"empty image of shape {image.shape}")
    shrinking = image.shape[0] > size or image.shape[1] > size
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
