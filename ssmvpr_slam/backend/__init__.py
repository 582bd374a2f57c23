"""GTSAM back end: iSAM2 pose graph with robust loop factors, and loop-closure registration.

Heavy modules (gtsam, kiss-icp, OpenCV) load on first use of the names below.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

from ssmvpr_slam.backend.config import (
    BackendConfig,
    LoopRegistrationConfig,
    PoseGraphConfig,
)

_LAZY = {
    "PoseGraph": "ssmvpr_slam.backend.pose_graph",
    "LoopResidual": "ssmvpr_slam.backend.pose_graph",
    "FinalSolve": "ssmvpr_slam.backend.pose_graph",
    "LoopRegistration": "ssmvpr_slam.backend.loop_registration",
    "LoopRegistrar": "ssmvpr_slam.backend.loop_registration",
    "build_local_map": "ssmvpr_slam.backend.loop_registration",
}

__all__ = ["BackendConfig", "LoopRegistrationConfig", "PoseGraphConfig", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
