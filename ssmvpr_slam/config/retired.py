"""Settings that were renamed or removed, so a user's file that still names one is told what
became of it instead of a bare "extra inputs are not permitted"."""

from __future__ import annotations

from typing import Any

RENAMED = {
    "backend.registration.lidar.max_threads": "backend.registration.lidar.max_num_threads",
}
REMOVED = {
    "frontend.pose_files.timestamp_decimals": "never read: TUM files are written with 9 decimals",
    "frontend.pose_files.value_digits": "never read: pose files are written with 10 significant digits",
    "simulation.city.intersection_clearance_m": "never read by the simulator",
    "evaluation.trajectory.association_max_dt": "never read: trajectories are matched keyframe by keyframe",
}


def retired_key(data: dict[str, Any]) -> str | None:
    """What to tell a user whose settings name a retired key (the first found), or None."""
    for key in _keys(data, ""):
        if key in RENAMED:
            return f"{key} was renamed {RENAMED[key]} (one name for one setting, as kiss-icp names it); use that"
        if key in REMOVED:
            return f"{key} was removed ({REMOVED[key]}); delete it"
    return None


def _keys(data: dict[str, Any], prefix: str) -> list[str]:
    keys = []
    for name, value in data.items():
        key = f"{prefix}{name}"
        keys.append(key)
        if isinstance(value, dict):
            keys.extend(_keys(value, key + "."))
    return keys
