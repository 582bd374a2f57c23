"""Deterministic 2.5D city traverse simulator (camera + LiDAR + ground truth + drifting odometry).

Exists because no real camera traverse with loops and ground truth is at hand: it feeds the
place recogniser, kiss-icp and the pose graph with recognisable, revisited places.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ssmvpr_common.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from frontend.simulation.city import City
    from frontend.simulation.config import (
        AppearanceConfig,
        CameraConfig,
        CityConfig,
        LidarConfig,
        OdometryDriftConfig,
        RouteConfig,
        SimulationConfig,
        TrafficConfig,
    )
    from frontend.simulation.layout import build_city
    from frontend.simulation.render import CameraRenderer, LidarRenderer
    from frontend.simulation.route import Route, build_route, read_poses_file
    from frontend.simulation.route_files import RouteFile, read_route_file
    from frontend.simulation.simulator import (
        TraverseSimulator,
        default_demo_config,
        ground_truth_revisits,
        pose_matrix,
        simulate_traverse,
    )

# names load their modules on first use: reading the settings (`frontend.simulation.config`)
# does not load the city renderer
_EXPORTS = {
    "City": "frontend.simulation.city",
    "AppearanceConfig": "frontend.simulation.config",
    "CameraConfig": "frontend.simulation.config",
    "CityConfig": "frontend.simulation.config",
    "LidarConfig": "frontend.simulation.config",
    "OdometryDriftConfig": "frontend.simulation.config",
    "RouteConfig": "frontend.simulation.config",
    "SimulationConfig": "frontend.simulation.config",
    "TrafficConfig": "frontend.simulation.config",
    "build_city": "frontend.simulation.layout",
    "CameraRenderer": "frontend.simulation.render",
    "LidarRenderer": "frontend.simulation.render",
    "Route": "frontend.simulation.route",
    "build_route": "frontend.simulation.route",
    "read_poses_file": "frontend.simulation.route",
    "RouteFile": "frontend.simulation.route_files",
    "read_route_file": "frontend.simulation.route_files",
    "TraverseSimulator": "frontend.simulation.simulator",
    "default_demo_config": "frontend.simulation.simulator",
    "ground_truth_revisits": "frontend.simulation.simulator",
    "pose_matrix": "frontend.simulation.simulator",
    "simulate_traverse": "frontend.simulation.simulator",
}
__all__ = [
    "AppearanceConfig",
    "CameraConfig",
    "CameraRenderer",
    "City",
    "CityConfig",
    "LidarConfig",
    "LidarRenderer",
    "OdometryDriftConfig",
    "Route",
    "RouteConfig",
    "RouteFile",
    "SimulationConfig",
    "TrafficConfig",
    "TraverseSimulator",
    "build_city",
    "build_route",
    "default_demo_config",
    "ground_truth_revisits",
    "pose_matrix",
    "read_poses_file",
    "read_route_file",
    "simulate_traverse",
]

__getattr__ = lazy_exports("frontend.simulation", _EXPORTS)
