"""A short simulated camera log and a config that runs a small backbone on it, for the tests of
what a run does around recognition (real time, disk full, the live view); tests/conftest.py puts
this folder on sys.path."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

SMALL_BACKBONE = (
    "vpr: {backbone: {input_size: 112, device: cpu}, filtering: {pca: {dim: 8}}, spatial: {pca: {dim: 8}}}\n"
)
EVERY_FRAME = "frontend: {keyframes: {min_distance_m: null, min_angle_deg: null, max_interval_s: 0.1}}\n"


def small_camera_log(folder: Path, settings: str, name: str = "small", **simulation: Any) -> SimpleNamespace:
    """`folder/<name>.mcap`: frames of a simulated street without LiDAR (logged odometry), 96 x 64
    images (`simulation` overrides the rest); `folder/small.yaml`: the small backbone and `settings`."""
    from frontend.simulation.config import SimulationConfig
    from frontend.simulation.simulator import TraverseSimulator
    from frontend.sources import write_frames

    log = folder / f"{name}.mcap"
    sim = SimulationConfig(**{"lidar": {"enabled": False}, "camera": {"width": 96, "height": 64}, **simulation})
    write_frames(TraverseSimulator(sim).frames(), log)
    config = folder / "small.yaml"
    config.write_text(SMALL_BACKBONE + settings)
    return SimpleNamespace(log=log, config=config)
