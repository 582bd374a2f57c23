"""Dense matches between two images from the backbone's own conv maps.

Why deep features: ORB across day and night finds next to nothing to match (on the shared
Gardens Point half, 0-19 SIFT + MAGSAC inliers for true day/night pairs), while the conv4_2
cells of an ImageNet VGG16 describe a patch by what is in it more than by its brightness. Every
cell of one image is matched to its nearest cell (cosine) in the other, and only mutual nearest
neighbours are kept, as DFM (Efe et al., CVPR-W 2021) starts from; the verifier fits geometry
to them. A cell's centre stands for its position: conv4_2 has a stride of 8 pixels at the
working width, so positions are kept in cells and the RANSAC threshold is set in cells
(`VerifierConfig`), the same for a 640 and a 960 pixel image of one pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.backbone_input import as_rgb
from loopclosure.config import LAYER_DOWNSAMPLING
from loopclosure.errors import LoopClosureInputError

MIN_SIDE_CELLS = 4
"""A map with fewer cells than this on a side holds too few positions to fit any geometry."""


@dataclass(frozen=True)
class DenseFeatures:
    """One image's unit-length conv descriptors on their grid, and how cells map to its pixels.

    descriptors: (h * w, C) float16 rows in row-major cell order; scale: pixels of the image given
    per cell, along x and y."""

    descriptors: np.ndarray
    grid: tuple[int, int]
    scale: tuple[float, float]
    image_size: tuple[int, int]  # (width, height) of the image given, in pixels

    def cell_positions(self, cells: np.ndarray) -> np.ndarray:
        """(n, 2) positions (x, y) of flat cell indices in cell units: a cell's centre is at
        (col + 0.5, row + 0.5), whatever the image's size."""
        rows, cols = np.divmod(np.asarray(cells, dtype=np.int64), self.grid[1])
        return np.stack([cols + 0.5, rows + 0.5], axis=1).astype(np.float64)

    def pixels(self, positions: np.ndarray) -> np.ndarray:
        """Cell-unit positions to pixel coordinates of the image given."""
        return positions * np.asarray(self.scale) - 0.5

    @property
    def nbytes(self) -> int:
        return int(self.descriptors.nbytes)


def dense_features(
    backbone: Backbone, image: np.ndarray, layer: str, width: int | None, name: str, grey: bool = True
) -> DenseFeatures:
    """The `layer` map of `image` (grey, RGB or RGBA uint8) resized to `width` pixels wide with
    its aspect kept (None: as given), each cell's descriptor scaled to unit length. grey: the
    image's luminance in all three channels, so that colour cast (sodium light at night, a
    colour camera against a grey one) is not a difference to match across."""
    rgb = as_rgb(image, name)
    if grey and rgb.ndim == 3:
        rgb = cv2.cvtColor(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
    height0, width0 = rgb.shape[:2]
    stride = LAYER_DOWNSAMPLING[layer]
    if width is not None and width != width0:
        height = max(stride, int(round(height0 * width / width0)))
        shrinking = width < width0
        rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)
    work_h, work_w = rgb.shape[:2]
    if min(work_h, work_w) < MIN_SIDE_CELLS * stride:
        raise LoopClosureInputError(
            f"{name}: {work_w}x{work_h} pixels give fewer than {MIN_SIDE_CELLS} {layer} cells on a side"
        )
    fmap = backbone.feature_map(rgb, layer)
    channels, rows, cols = fmap.shape
    flat = fmap.reshape(channels, rows * cols).T
    norms = np.linalg.norm(flat, axis=1, keepdims=True)
    unit = flat / np.maximum(norms, np.finfo(np.float32).tiny)
    # the map's cells tile the working image at `stride` px; back to the given image's pixels
    scale = (stride * width0 / work_w, stride * height0 / work_h)
    return DenseFeatures(unit.astype(np.float16), (rows, cols), scale, (width0, height0))


@dataclass(frozen=True)
class DenseMatches:
    """Mutual nearest-neighbour cells of two images, as positions in cell units in each
    (`DenseFeatures.cell_positions`; `.pixels` turns them into pixels)."""

    cells_a: np.ndarray  # (n, 2) float64
    cells_b: np.ndarray  # (n, 2) float64
    similarity: np.ndarray  # (n,) cosine of each pair

    def __len__(self) -> int:
        return len(self.cells_a)


def mutual_matches(a: DenseFeatures, b: DenseFeatures, max_distance_ratio: float = 1.0) -> DenseMatches:
    """Cells of a and b that are each other's nearest neighbour by cosine; with
    max_distance_ratio < 1 also Lowe's test in descriptor distance (nearest over second nearest)."""
    desc_a = a.descriptors.astype(np.float32)
    desc_b = b.descriptors.astype(np.float32)
    if desc_a.shape[1] != desc_b.shape[1]:
        raise LoopClosureInputError(
            f"dense features of {desc_a.shape[1]} and {desc_b.shape[1]} channels cannot be matched (different layers)"
        )
    sim = desc_a @ desc_b.T
    best_b = sim.argmax(axis=1)
    best_a = sim.argmax(axis=0)
    ia = np.nonzero(best_a[best_b] == np.arange(len(best_b)))[0]
    ib = best_b[ia]
    if max_distance_ratio < 1.0 and len(ia) and sim.shape[1] > 1:
        top2 = -np.partition(-sim[ia], 1, axis=1)[:, :2]
        nearest = np.sqrt(np.maximum(2.0 - 2.0 * top2[:, 0], 0.0))
        second = np.sqrt(np.maximum(2.0 - 2.0 * top2[:, 1], 0.0))
        keep = nearest < max_distance_ratio * second
        ia, ib = ia[keep], ib[keep]
    return DenseMatches(a.cell_positions(ia), b.cell_positions(ib), sim[ia, ib].astype(np.float64))
