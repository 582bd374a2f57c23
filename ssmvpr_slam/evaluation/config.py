"""Tunables of the evaluation: alignment, RPE deltas, drift and KITTI segments, loop-correctness radii."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ssmvpr_common.settings_model import SettingsModel


class TrajectoryMetricsConfig(SettingsModel):
    """ATE / RPE / drift, following evo's definitions; KITTI relative error, the devkit's."""

    alignment: Literal["se3", "sim3", "none"] = Field(
        "se3", description="Umeyama alignment of the estimate to the reference before ATE"
    )
    rpe_delta: float = Field(1.0, gt=0, description="pair distance, in rpe_unit")
    rpe_unit: Literal["frames", "m"] = Field(
        "frames", description="unit of rpe_delta: poses, or metres along the reference path"
    )
    rpe_all_pairs: bool = Field(
        False,
        description="pairs start at every pose, not every rpe_delta-th (evo all_pairs)",
    )
    drift_segment_m: float = Field(100.0, gt=0, description="segment length for drift per 100 m")
    kitti_lengths_m: list[float] = Field(
        default=[100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0],
        min_length=1,
        description="segment lengths of the KITTI relative error (the devkit's by default)",
    )
    kitti_step_frames: int = Field(
        10, ge=1, description="first frames of KITTI segments are this many poses apart (devkit: 10)"
    )


class LoopMetricsConfig(SettingsModel):
    """When a keyframe is a revisit, and when an accepted loop counts as correct."""

    revisit_radius: float = Field(5.0, gt=0, description="m; ground-truth revisit distance")
    correct_radius: float = Field(10.0, gt=0, description="m; an accepted loop within this distance is correct")
    min_frame_gap: int = Field(50, ge=1, description="keyframes; q - m must be at least this")
    view_angle_deg: float = Field(
        45.0,
        gt=0,
        le=180,
        description="deg; a revisit is camera-visible when an earlier visit looked within this of its heading",
    )
    revisit_gap_keyframes: int = Field(
        10, ge=1, description="keyframes; accepted loops whose queries and matches each lie within this of the "
        "previous one's close the same revisit (how first loops of a revisit are counted)"
    )  # fmt: skip

    @model_validator(mode="after")
    def _correct_not_tighter(self) -> LoopMetricsConfig:
        if self.correct_radius < self.revisit_radius:
            raise ValueError("correct_radius must be >= revisit_radius")
        return self


class PlotConfig(SettingsModel):
    """Figure output."""

    dpi: int = Field(120, ge=30, description="dots per inch of a run's PNG plots")
    width_in: float = Field(7.0, gt=0, description="width of a run's plots, in inches")
    height_in: float = Field(6.0, gt=0, description="height of a run's plots, in inches (some plots use a fraction)")


class EvaluationConfig(SettingsModel):
    """Root of the evaluation configuration."""

    trajectory: TrajectoryMetricsConfig = TrajectoryMetricsConfig()
    loops: LoopMetricsConfig = LoopMetricsConfig()
    plots: PlotConfig = PlotConfig()
