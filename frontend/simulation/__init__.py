"""Deterministic 2.5D city traverse simulator (camera + LiDAR + ground truth + drifting odometry).

Exists because no real camera traverse with loops and ground truth is at hand: it feeds the
place recogniser, kiss-icp and the pose graph with recognisable, revisited places.
"""

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
    "SimulationConfig",
    "TrafficConfig",
    "RouteFile",
    "read_route_file",
    "TraverseSimulator",
    "build_city",
    "build_route",
    "default_demo_config",
    "ground_truth_revisits",
    "pose_matrix",
    "read_poses_file",
    "simulate_traverse",
]
