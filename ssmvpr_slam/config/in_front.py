"""The settings a user tunes, in front: `config --explain` shows these (about twenty, each with
its unit, value and the shipped default), `config --explain --all` every one of the ~400.
Most of the rest are the simulator's scene and the method's internals, set once by the
presets; kiss-icp likewise shows a dozen."""

from __future__ import annotations

import json
from typing import Any

from pydantic import BaseModel

from ssmvpr_slam.config.slam import SlamConfig

# (key, unit): the unit as the value is read ("" for a choice or a switch)
IN_FRONT: tuple[tuple[str, str], ...] = (
    ("vpr.backbone.weights", "file"),
    ("vpr.backbone.device", ""),
    ("vpr.backbone.precision", ""),
    ("vpr.backbone.input_size", "px"),
    ("vpr.filtering.num_candidates", "places"),
    ("detector.codebooks", "file"),
    ("detector.pca_warmup_keyframes", "keyframes"),
    ("detector.exclusion_keyframes", "keyframes"),
    ("detector.exclusion_distance", "m"),
    ("detector.sequence.length", "keyframes"),
    ("detector.calibrated.accept", "spreads"),
    ("detector.rear.enabled", ""),
    ("frontend.odometry.kind", ""),
    ("frontend.odometry.kiss_icp.max_range", "m"),
    ("frontend.keyframes.min_distance_m", "m"),
    ("frontend.keyframes.min_angle_deg", "deg"),
    ("pipeline.use_lidar_for_loops", ""),
    ("pipeline.realtime_max_lag_s", "s"),
    ("results.out_dir", "folder"),
    ("results.checkpoint_every_keyframes", "keyframes"),
    ("evaluation.loops.correct_radius", "m"),
    ("map.workers", "workers"),
)


def setting(config: BaseModel, key: str) -> tuple[Any, str]:
    """A key's value and description (KeyError for a key the settings do not have)."""
    *parents, name = key.split(".")
    model = config
    for part in parents:
        model = getattr(model, part)
    if name not in type(model).model_fields:
        raise KeyError(key)
    return getattr(model, name), type(model).model_fields[name].description or ""


def explain_in_front(config: SlamConfig, shipped: SlamConfig) -> str:
    """One line per setting in front: `key: value  [unit]  (default: d)  # what it does`."""
    lines = []
    for key, unit in IN_FRONT:
        value, description = setting(config, key)
        default, _ = setting(shipped, key)
        shown = f"{key}: {json.dumps(value)}" + (f"  [{unit}]" if unit else "")
        lines.append(f"{shown}  (default: {json.dumps(default)})  # {description}")
    lines.append("# the settings users tune; `config --explain --all` shows every one")
    return "\n".join(lines)
