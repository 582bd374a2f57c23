"""Image files in, RGB uint8 out (the one colour convention of Frame); which files are images
is :func:`ssmvpr_common.image_folders.image_files`."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from frontend.errors import FrontendInputError


def read_rgb(path: Path) -> np.ndarray:
    """HxWx3 RGB uint8; grayscale files become three equal channels."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise FrontendInputError(f"{path}: cannot read image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
