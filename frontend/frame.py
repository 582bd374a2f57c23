"""The one record that crosses from a data source into the pipeline."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    """One synchronised instant of a traverse; every sensor field is optional.

    image: HxWx3 uint8 RGB from the forward camera. rear_image: the same from a camera looking
    backwards, when the vehicle has one (at a street driven the other way it sees what the
    forward camera saw on the earlier visit). points: Nx3 float64 in the sensor frame. point_times: N
    per-point times (seconds, relative to the sweep) or None. Poses are 4x4 float64
    sensor-to-world transforms.
    """

    index: int
    timestamp: float
    image: np.ndarray | None = None
    rear_image: np.ndarray | None = None
    points: np.ndarray | None = None
    point_times: np.ndarray | None = None
    logged_pose: np.ndarray | None = None
    gt_pose: np.ndarray | None = None

    @property
    def label(self) -> str:
        """How errors and warnings name this frame: its index and its time."""
        return f"frame {self.index} (t={self.timestamp})"
