"""Deterministic simulated traverses: ``simulate_traverse(config)`` streams ``Frame`` objects.

Each frame carries rendered camera images (forward, and rear unless switched off), a motion-distorted LiDAR sweep with per-point times,
the ground-truth pose (LiDAR/body frame, x forward, y left, z up, at the end of the sweep; the
vehicle pitches with the road) and a drifting "wheel odometry" pose. Parked cars, traffic and
foliage change with time, so two visits of a place differ for both sensors. Everything is a pure function of the config (and its seed):
frame k can be regenerated alone with ``TraverseSimulator.frame(k)``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.simulation.city import ALLEY, FACADE, City
from frontend.simulation.config import RouteConfig, SimulationConfig
from frontend.simulation.layout import build_city
from frontend.simulation.render import CameraRenderer, LidarRenderer, Scene
from frontend.simulation.route import Route, build_route
from frontend.simulation.route_files import RouteFile, read_route_file
from frontend.simulation.traffic import Traffic
from frontend.sources.intrinsics import CameraIntrinsics

# Independent random streams derived from the seed.
_STREAM_IMAGE, _STREAM_LIDAR, _STREAM_ODOM = 11, 12, 13
_FOLIAGE_EPOCH_S = 60.0  # leaves look different from one minute to the next
_FILE_ONCOMING_LANE_M = 3.2


def pose_matrix(x: float, y: float, z: float, yaw: float, pitch: float = 0.0) -> np.ndarray:
    """4x4 sensor-to-world transform: heading ``yaw``, nose up by ``pitch`` (rad)."""
    c, s = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    T = np.eye(4)
    # Rz(yaw) @ Ry(-pitch): a positive pitch turns the x axis upwards.
    T[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]]
    )
    T[:3, 3] = [x, y, z]
    return T


def _route_file(route: RouteConfig) -> RouteFile | None:
    """The poses file a route drives, read (None for a grid route)."""
    return read_route_file(route.preset, route.poses_format, route.poses_frame) if route.is_file else None


class TraverseSimulator:
    """A city, a route through it, and sensors; builds everything eagerly (errors surface here)."""

    def __init__(self, config: SimulationConfig):
        if not isinstance(config, SimulationConfig):
            raise FrontendInputError(f"simulation config must be a SimulationConfig, got {type(config).__name__}")
        self.config = config
        cfg = config
        self.route_file = _route_file(cfg.route)
        self.session_seed = cfg.seed if cfg.session_seed is None else cfg.session_seed
        self.route: Route = build_route(
            cfg.route, self.session_seed, cfg.city.pitch_m, self.route_file, terrain_seed=cfg.seed
        )
        streets = self.route.centre if cfg.city_route is None else self._city_streets(cfg)
        self.city: City = build_city(cfg.city, cfg.seed, streets, cfg.traffic)
        lane = cfg.traffic.oncoming_lane_offset_m
        if lane is None:
            lane = _FILE_ONCOMING_LANE_M if self.route_file is not None else -cfg.route.lane_offset_m
        self.traffic = Traffic(self.city, self.route.centre, cfg.traffic, lane, self.session_seed)
        # Frame k ends its LiDAR sweep at route time scan_period + k / frame_rate (the first
        # sweep starts when the vehicle sets off); frames run until the route ends.
        dt = 1.0 / cfg.frame_rate_hz
        t0 = cfg.scan_period_s
        n = int(np.floor((self.route.duration - t0) / dt)) + 1 if self.route.duration >= t0 else 0
        if cfg.max_frames is not None:
            n = min(n, cfg.max_frames)
        if n < 1:
            raise FrontendInputError("route is too short for a single frame (route.preset / route.speed_mps)")
        self.route_times = t0 + np.arange(n) * dt
        self.times = np.arange(n) * dt
        self.arc = self.route.arc_length_at(self.route_times)
        x, y, yaw = self.route.pose_at(self.arc)
        self.xy_yaw = np.stack([x, y, yaw], axis=1)
        self.road_z = self.route.height_at(self.arc)
        self.grade = self.route.grade_at(self.arc)
        self.pitch = np.arctan(self.grade)
        self.passes = self.route.pass_index(self.arc)
        self.camera = CameraRenderer(self.city, cfg.camera) if cfg.camera.enabled else None
        self.lidar = LidarRenderer(self.city, cfg.lidar, cfg.scan_period_s) if cfg.lidar.enabled else None
        self._logged = self._integrate_odometry()

    def __len__(self) -> int:
        return len(self.times)

    @property
    def intrinsics(self) -> dict[str, CameraIntrinsics]:
        """Each rendered camera's calibration, by role as a Source gives it (the rear camera is
        the forward one turned round), for `write_frames(..., intrinsics=...)`."""
        if self.camera is None:
            return {}
        k = self.camera.intrinsics
        return {"camera": k, "rear_camera": k} if self.config.camera.rear else {"camera": k}

    @staticmethod
    def _city_streets(cfg: SimulationConfig) -> np.ndarray:
        """The centre line of `city_route`: the streets every session of the city drives among."""
        assert cfg.city_route is not None
        return build_route(cfg.city_route, cfg.seed, cfg.city.pitch_m, _route_file(cfg.city_route)).centre

    # -- poses ---------------------------------------------------------------------------------

    def gt_pose(self, k: int) -> np.ndarray:
        x, y, yaw = self.xy_yaw[k]
        return pose_matrix(x, y, self.road_z[k] + self.config.lidar.height_m, yaw, self.pitch[k])

    def gt_positions(self) -> np.ndarray:
        """(N, 2) ground-truth xy of every frame."""
        return self.xy_yaw[:, :2].copy()

    def logged_pose(self, k: int) -> np.ndarray:
        """Wheel odometry: drifting in x, y and heading; height and pitch as a barometer and an
        inclinometer would give them."""
        x, y, yaw = self._logged[k]
        return pose_matrix(x, y, self.road_z[k] + self.config.lidar.height_m, yaw, self.pitch[k])

    def _integrate_odometry(self) -> np.ndarray:
        """Dead-reckoned planar poses from the true increments with the configured errors."""
        od = self.config.odometry
        rng = np.random.default_rng([self.session_seed, _STREAM_ODOM])
        g = self.xy_yaw
        out = np.empty_like(g)
        out[0] = g[0]
        bias = 0.0
        for k in range(1, len(g)):
            c, s = math.cos(g[k - 1, 2]), math.sin(g[k - 1, 2])
            dxw, dyw = g[k, 0] - g[k - 1, 0], g[k, 1] - g[k - 1, 1]
            dx, dy = c * dxw + s * dyw, -s * dxw + c * dyw
            dth = g[k, 2] - g[k - 1, 2]
            dist = math.hypot(dx, dy)
            sq = math.sqrt(dist)
            bias += rng.normal(0.0, od.yaw_bias_walk_rad_per_m_sqrt_m * sq)
            noise = rng.normal(0.0, 1.0, 3)
            dth_l = dth + (od.yaw_drift_rad_per_m + bias) * dist + od.yaw_noise_rad_per_sqrt_m * sq * noise[0]
            dx_l = (1.0 + od.scale_error) * dx + od.translation_noise_m_per_sqrt_m * sq * noise[1]
            dy_l = (1.0 + od.scale_error) * dy + od.translation_noise_m_per_sqrt_m * sq * noise[2]
            cl, sl = math.cos(out[k - 1, 2]), math.sin(out[k - 1, 2])
            out[k, 0] = out[k - 1, 0] + cl * dx_l - sl * dy_l
            out[k, 1] = out[k - 1, 1] + sl * dx_l + cl * dy_l
            out[k, 2] = out[k - 1, 2] + dth_l
        return out

    # -- sensors -------------------------------------------------------------------------------

    def appearance_name(self, k: int) -> str:
        sched = self.config.appearance_schedule
        return sched[min(int(self.passes[k]), len(sched) - 1)]

    def scene(self, k: int) -> Scene:
        """What stands in the street at frame k: the city's walls with the parked cars of that
        moment, plus the oncoming traffic."""
        t = float(self.route_times[k])
        parked_at = self.config.start_time_s + t  # the clock of the city: sessions at other hours see other cars
        return Scene.of(self.city, self.city.active_segments(parked_at), self.traffic.scene_part(t, self.xy_yaw[k, :2]))

    def render_image(self, k: int, scene: Scene | None = None, rear: bool = False) -> np.ndarray | None:
        """The forward camera's image of frame k, or the rear camera's (None when it has none)."""
        if self.camera is None or (rear and not self.config.camera.rear):
            return None
        x, y, yaw = self.xy_yaw[k]
        app = self.config.appearances[self.appearance_name(k)]
        # the rear camera's noise is its own stream, so adding it leaves the forward images as they were
        rng = np.random.default_rng(
            [self.session_seed, _STREAM_IMAGE, k, 1] if rear else [self.session_seed, _STREAM_IMAGE, k]
        )
        sign = -1.0 if rear else 1.0  # looking backwards, the road ahead of the lens falls as the car climbs
        return self.camera.render(
            x,
            y,
            yaw + (math.pi if rear else 0.0),
            app,
            rng,
            road_z=float(self.road_z[k]),
            pitch=sign * float(self.pitch[k]),
            grade=sign * float(self.grade[k]),
            scene=scene or self.scene(k),
            visit=int(self.route_times[k] // _FOLIAGE_EPOCH_S),
        )

    def render_scan(self, k: int, scene: Scene | None = None) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
        if self.lidar is None:
            return None, None
        rng = np.random.default_rng([self.session_seed, _STREAM_LIDAR, k])
        zs: float | np.ndarray
        if self.config.lidar.motion_distortion:  # every column from where the vehicle was then
            t = self.route_times[k] - self.lidar.period + self.lidar.col_times
            arc = self.route.arc_length_at(t)
            xs, ys, yaws = self.route.pose_at(arc)
            zs = self.route.height_at(arc)
        else:
            xs, ys, yaws = self.xy_yaw[k]
            zs = float(self.road_z[k])
        return self.lidar.scan(
            xs,
            ys,
            yaws,
            rng,
            road_z=zs,
            pitch=float(self.pitch[k]),
            grade=float(self.grade[k]),
            scene=scene or self.scene(k),
        )

    def building_clearance(self) -> np.ndarray:
        """Per frame, the distance from the sensors to the nearest building wall (negative
        inside a building): the check that no frame looks into a building."""
        walls = np.isin(self.city.kind[self.city.surface], (FACADE, ALLEY))
        sub = City(**{**self.city.__dict__, "p0": self.city.p0[walls], "p1": self.city.p1[walls]})
        return sub.clearance(self.xy_yaw[:, :2])

    def frame(self, k: int) -> Frame:
        if not 0 <= k < len(self):
            raise IndexError(f"frame {k} outside 0..{len(self) - 1}")
        scene = self.scene(k)
        points, times = self.render_scan(k, scene)
        return Frame(
            index=k,
            timestamp=float(self.config.start_time_s + self.times[k]),
            image=self.render_image(k, scene),
            rear_image=self.render_image(k, scene, rear=True),
            points=points,
            point_times=times,
            logged_pose=self.logged_pose(k),
            gt_pose=self.gt_pose(k),
        )

    def frames(self) -> Iterator[Frame]:
        for k in range(len(self)):
            yield self.frame(k)

    def stats(self, revisit_radius_m: float = 5.0, min_gap_frames: int | None = None) -> dict:
        """Length, frame count, passes and ground-truth revisit count of the traverse."""
        xy = self.gt_positions()
        rev = ground_truth_revisits(xy, revisit_radius_m, min_gap_frames or self.default_min_gap())
        rev_same = ground_truth_revisits(
            xy, revisit_radius_m, min_gap_frames or self.default_min_gap(), self.xy_yaw[:, 2], math.pi / 4
        )
        return {
            "frames": len(self),
            "duration_s": float(self.times[-1]),
            "length_m": float(self.arc[-1] - self.arc[0]),
            "route_length_3d_m": self.route.length_3d,
            "height_range_m": float(np.ptp(self.road_z)),
            "passes": int(self.passes.max()) + 1,
            "revisit_frames": int((rev >= 0).sum()),
            "revisit_frames_same_direction": int((rev_same >= 0).sum()),
            "segments": self.city.n_segments,
        }

    def default_min_gap(self) -> int:
        """Frames driven over two city blocks: closer frames are one visit, not a revisit."""
        spacing = self.config.route.speed_mps / self.config.frame_rate_hz
        return max(1, int(round(2 * self.config.city.pitch_m / spacing)))


def simulate_traverse(config: SimulationConfig) -> Iterator[Frame]:
    """Stream the frames of the traverse described by ``config`` (deterministic per seed).

    Configuration and route errors are raised here, before the first frame is rendered.
    """
    return TraverseSimulator(config).frames()


def ground_truth_revisits(
    positions: np.ndarray,
    radius_m: float = 5.0,
    min_gap_frames: int = 30,
    yaws: np.ndarray | None = None,
    max_yaw_difference_rad: float | None = None,
) -> np.ndarray:
    """For each frame, the nearest earlier frame within ``radius_m`` and at least
    ``min_gap_frames`` older (optionally heading within ``max_yaw_difference_rad``), or -1.
    """
    xy = np.asarray(positions, float)[:, :2]
    n = len(xy)
    out = np.full(n, -1, np.int64)
    chunk = 512
    for a in range(0, n, chunk):
        q = xy[a : a + chunk]
        d = np.linalg.norm(q[:, None, :] - xy[None, :, :], axis=2)
        idx = np.arange(a, a + len(q))[:, None]
        ok = (np.arange(n)[None, :] <= idx - min_gap_frames) & (d <= radius_m)
        if yaws is not None and max_yaw_difference_rad is not None:
            dy = np.angle(np.exp(1j * (yaws[a : a + len(q), None] - yaws[None, :])))
            ok &= np.abs(dy) <= max_yaw_difference_rad
        d = np.where(ok, d, np.inf)
        best = np.argmin(d, axis=1)
        has = np.isfinite(d[np.arange(len(q)), best])
        out[a : a + len(q)][has] = best[has]
    return out


def default_demo_config(**overrides) -> SimulationConfig:
    """The demo traverse: loop A around two blocks twice by day, then loop B at dusk.

    676 frames at 5 Hz over about 1.19 km (135 s) with same-direction revisits (lap 2) and
    opposite-direction revisits (loop B drives three of A's streets the other way).
    Keyword arguments override top-level config fields. SimulationConfig's defaults are this
    traverse, so `simulate`, `demo` and a config that changes only some fields (a seed) agree.
    """
    return SimulationConfig.model_validate(overrides)
