"""Routes: preset loops with revisits, or a poses file in its own convention.

A route is a dense path parameterised by horizontal arc length s: ``Route.pose_at(s)`` gives
(x, y, yaw) with yaw along the direction of travel, ``Route.height_at(s)`` the road height and
``Route.grade_at(s)`` its slope (the vehicle pitches with it). Preset routes are polylines
through the crossings of a street grid with circular fillets at the corners, shifted into the
driving lane with a slow lateral weave (so later passes do not repeat earlier poses exactly),
over gently rolling terrain (a function of position, so every visit sees the same hills). File
routes keep the file's path and height profile. ``Route.centre`` is the street centre line
the city is laid along. ``Route.arc_length_at(t)`` maps time to s: the vehicle starts from
rest, cruises at a slowly varying speed and slows down for corners with bounded acceleration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from frontend.errors import FrontendInputError
from frontend.simulation.config import RouteConfig
from frontend.simulation.noise import value_noise
from frontend.simulation.route_files import PosesFrame, RouteFile, read_route_file

# Passes of the preset routes as crossings (i, j) of the street grid.
# block_grid: loop A anticlockwise around two blocks (driven `laps` times), then loop B
# clockwise around the right-hand block: a new street, then three of A's in the opposite
# direction.
_LOOP_A = [(1, 0), (2, 0), (2, 1), (0, 1), (0, 0), (1, 0)]
_LOOP_B = [(1, 0), (1, 1), (2, 1), (2, 0), (1, 0)]
# figure_eight: two blocks touching at crossing (1, 1), driven straight through it both ways.
_EIGHT = [(1, 1), (0, 1), (0, 0), (1, 0), (1, 1), (1, 2), (2, 2), (2, 1), (1, 1)]

# Two-harmonic smooth noise (weights sum to 1, so |noise| <= 1); second period ratio.
_HARMONIC_WEIGHTS = (0.6, 0.4)
_HARMONIC_RATIO = 0.37
_TERRAIN_CHANNEL = 881


@dataclass
class Route:
    """Dense path: arc length ``s`` (uniform), positions ``xy``, road height ``z``, unwrapped
    ``yaw``, the time ``t`` at which the vehicle passes each sample (speed profile), and the
    street centre line ``centre`` (M, 3) the city is built along."""

    s: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    t: np.ndarray
    pass_starts: np.ndarray  # arc length at which each pass (loop) begins
    z: np.ndarray
    centre: np.ndarray

    @property
    def length(self) -> float:
        return float(self.s[-1])

    @property
    def length_3d(self) -> float:
        """Length along the road including its slopes (what a poses file's steps add up to)."""
        d = np.diff(np.column_stack([self.xy, self.z]), axis=0)
        return float(np.linalg.norm(d, axis=1).sum())

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    @property
    def n_passes(self) -> int:
        return len(self.pass_starts)

    def pose_at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, y, yaw) at arc length(s) s; clamped to the ends."""
        s = np.asarray(s, float)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        yaw = np.interp(s, self.s, self.yaw)
        return x, y, yaw

    def height_at(self, s) -> np.ndarray:
        return np.interp(np.asarray(s, float), self.s, self.z)

    def grade_at(self, s) -> np.ndarray:
        """dz/ds of the road (rise over run) at s."""
        return np.interp(np.asarray(s, float), self.s, self._grade)

    def __post_init__(self) -> None:
        ds = float(self.s[1] - self.s[0]) if len(self.s) > 1 else 1.0
        # Grade over a wheelbase-like window: a vehicle does not pitch with every bump.
        self._grade = _box_smooth(np.gradient(self.z, ds), max(1, int(round(2.0 / ds))))

    def pass_index(self, s) -> np.ndarray:
        return np.searchsorted(self.pass_starts, np.asarray(s, float), side="right") - 1

    def arc_length_at(self, t) -> np.ndarray:
        """Distance driven at time t (seconds since the start of the route); clamped."""
        return np.interp(np.asarray(t, float), self.t, self.s)


def _box_smooth(v: np.ndarray, half: int) -> np.ndarray:
    k = np.ones(2 * half + 1) / (2 * half + 1)
    return np.convolve(np.pad(v, half, mode="edge"), k, mode="valid")


def read_poses_file(
    path: str | Path, fmt: str = "auto", frame: PosesFrame = "auto"
) -> tuple[np.ndarray | None, np.ndarray]:
    """(timestamps or None, z-up positions (N, 3)) of a TUM or KITTI poses file; see route_files."""
    route = read_route_file(path, fmt, frame)
    return route.timestamps, route.positions


def _fillet_polyline(pts: np.ndarray, radius: float, step: float):
    """Dense polyline through ``pts`` with circular arcs at the corners.

    Returns (dense points (M, 2), index into dense of each waypoint's corner point).
    """
    out = [pts[0]]
    marks = [0]
    for k in range(1, len(pts) - 1):
        a = pts[k] - pts[k - 1]
        b = pts[k + 1] - pts[k]
        la, lb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
        a, b = a / la, b / lb
        cross = a[0] * b[1] - a[1] * b[0]
        theta = math.atan2(cross, float(a @ b))
        if abs(theta) < 1e-6:
            _append_line(out, pts[k], step)
            marks.append(len(out) - 1)
            continue
        if abs(abs(theta) - math.pi) < 1e-6:
            raise FrontendInputError(f"route turns back on itself at waypoint {k} ({pts[k].tolist()})")
        d = min(radius * math.tan(abs(theta) / 2), 0.5 * la, 0.5 * lb)
        r = d / math.tan(abs(theta) / 2)
        t1 = pts[k] - a * d
        _append_line(out, t1, step)
        left = np.array([-a[1], a[0]]) * math.copysign(1.0, theta)
        centre = t1 + left * r
        phi0 = math.atan2(*(t1 - centre)[::-1])
        n = max(2, int(math.ceil(abs(theta) * r / step)))
        phis = phi0 + theta * np.arange(1, n + 1) / n
        arc = centre + r * np.stack([np.cos(phis), np.sin(phis)], axis=1)
        out.extend(arc[: n // 2])
        marks.append(len(out) - 1)
        out.extend(arc[n // 2 :])
    _append_line(out, pts[-1], step)
    marks.append(len(out) - 1)
    return np.asarray(out), np.asarray(marks)


def _append_line(out: list, end: np.ndarray, step: float) -> None:
    start = out[-1]
    L = float(np.linalg.norm(end - start))
    n = int(math.ceil(L / step))
    if n == 0:
        return
    f = np.arange(1, n + 1)[:, None] / n
    out.extend(start + (end - start) * f)


def _arclength(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])


def _smooth_noise(x: np.ndarray, period: float, phases: np.ndarray) -> np.ndarray:
    out = np.zeros_like(x)
    for w, ratio, ph in zip(_HARMONIC_WEIGHTS, (1.0, _HARMONIC_RATIO), phases):
        out += w * np.sin(2.0 * math.pi * x / (period * ratio) + ph)
    return out


def grid_node(cfg_pitch: float, i: int, j: int) -> np.ndarray:
    """World xy of crossing (i, j) of the preset street grid."""
    return np.array([i * cfg_pitch, j * cfg_pitch], dtype=np.float64)


def preset_waypoints(cfg: RouteConfig, pitch_m: float) -> list[np.ndarray]:
    """Crossings of each pass of a preset route (or of `cfg.crossings`), as world xy arrays."""
    if cfg.crossings is not None:
        passes = [[(int(i), int(j)) for i, j in p] for p in cfg.crossings]
    elif cfg.preset == "block_grid":
        passes = [_LOOP_A] * cfg.laps + [_LOOP_B]
    elif cfg.preset == "figure_eight":
        passes = [_EIGHT] * cfg.laps
    else:
        raise FrontendInputError(f"route.preset {cfg.preset!r} is not a preset")
    return [np.array([grid_node(pitch_m, i, j) for i, j in p]) for p in passes]


def terrain_height(cfg: RouteConfig, seed: int, xy: np.ndarray) -> np.ndarray:
    """Rolling terrain of preset routes: smooth noise of position (every visit sees the same hill)."""
    if cfg.terrain_amplitude_m == 0:
        return np.zeros(len(xy))
    w = cfg.terrain_wavelength_m
    n = value_noise(seed, _TERRAIN_CHANNEL, xy[:, 0] / w, xy[:, 1] / w).astype(np.float64)
    n0 = value_noise(seed, _TERRAIN_CHANNEL, np.zeros(1), np.zeros(1)).astype(np.float64)
    return cfg.terrain_amplitude_m * 2.0 * (n - n0)


def build_route(
    cfg: RouteConfig,
    seed: int,
    pitch_m: float,
    route_file: RouteFile | None = None,
    terrain_seed: int | None = None,
) -> Route:
    """Build the dense route. ``pitch_m`` is the street-grid pitch of preset routes;
    ``terrain_seed`` (default ``seed``) shapes the hills, which every session of a city shares.

    A poses file contributes its path and height profile; its orientations and timestamps are
    not used: the heading follows the path and the vehicle drives it with the configured speed
    profile. Lane offset, weaving and corner easing apply to preset routes only (a file's path
    is where a vehicle drove, already in its lane).
    """
    rng = np.random.default_rng([seed, 4409])
    wander_phases = rng.uniform(0, 2 * math.pi, 2)
    speed_phases = rng.uniform(0, 2 * math.pi, 2)
    step = cfg.path_resolution_m
    if cfg.is_file:
        if route_file is None:
            route_file = read_route_file(cfg.preset, cfg.poses_format, cfg.poses_frame)
        pos = route_file.positions
        keep = np.concatenate([[True], np.linalg.norm(np.diff(pos[:, :2], axis=0), axis=1) > 1e-6])
        pts = pos[keep]
        if len(pts) < 2:
            raise FrontendInputError(f"poses file {cfg.preset}: the path does not move")
        s_raw = _arclength(pts[:, :2])
        s = np.arange(0.0, s_raw[-1], step)
        xy = np.stack([np.interp(s, s_raw, pts[:, 0]), np.interp(s, s_raw, pts[:, 1])], axis=1)
        z = np.interp(s, s_raw, pts[:, 2]) * cfg.file_height_scale
        if cfg.file_path_smoothing_m > 0:
            # Recorded poses jitter by centimetres from one to the next; a vehicle's yaw rate
            # does not. Smooth the path (not only its heading) so position and heading agree.
            xyz = _gaussian_smooth(np.column_stack([xy, z]), cfg.file_path_smoothing_m / step)
            s_sm = _arclength(xyz[:, :2])
            s = np.arange(0.0, s_sm[-1], step)
            xy = np.stack([np.interp(s, s_sm, xyz[:, 0]), np.interp(s, s_sm, xyz[:, 1])], axis=1)
            z = np.interp(s, s_sm, xyz[:, 2])
        yaw = _heading(xy, step, cfg.file_heading_smoothing_m)
        t = speed_profile(s, yaw, cfg, speed_phases)
        centre = np.column_stack([xy, z])
        return Route(s=s, xy=xy, yaw=yaw, t=t, pass_starts=np.array([0.0]), z=z, centre=centre)

    if abs(cfg.lane_offset_m) + cfg.lateral_wander_m >= cfg.turn_radius_m:
        raise FrontendInputError(
            "route.turn_radius_m must exceed |route.lane_offset_m| + route.lateral_wander_m "
            f"({cfg.turn_radius_m} <= {abs(cfg.lane_offset_m) + cfg.lateral_wander_m})"
        )
    passes = preset_waypoints(cfg, pitch_m)
    pts = [passes[0]]
    first_index = [0]
    for p in passes[1:]:
        first_index.append(sum(len(q) for q in pts) - 1)
        pts.append(p[1:])
    way = np.concatenate(pts)
    centre, marks = _fillet_polyline(way, cfg.turn_radius_m, step)
    s_c = _arclength(centre)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    offset = cfg.lane_offset_m + cfg.lateral_wander_m * _smooth_noise(s_c, cfg.wander_wavelength_m, wander_phases)
    lane = centre + left * offset[:, None]
    s_l = _arclength(lane)
    s = np.arange(0.0, s_l[-1], step)
    xy = np.stack([np.interp(s, s_l, lane[:, 0]), np.interp(s, s_l, lane[:, 1])], axis=1)
    if cfg.path_smoothing_m > 0:
        # Gaussian smoothing eases curvature in and out of the arcs (like a clothoid), so the
        # yaw rate ramps instead of jumping; then re-sample at uniform arc length.
        xy = _gaussian_smooth(xy, cfg.path_smoothing_m / step)
        s_sm = _arclength(xy)
        s_new = np.arange(0.0, s_sm[-1], step)
        xy = np.stack([np.interp(s_new, s_sm, xy[:, 0]), np.interp(s_new, s_sm, xy[:, 1])], axis=1)
        s_l = s_l * (s_sm[-1] / s_l[-1])
        s = s_new
    yaw = _heading(xy, step, 0.0)
    pass_starts = s_l[marks[first_index]]
    pass_starts[0] = 0.0
    t = speed_profile(s, yaw, cfg, speed_phases)
    hills = seed if terrain_seed is None else terrain_seed
    z = terrain_height(cfg, hills, xy)
    centre_xyz = np.column_stack([centre, terrain_height(cfg, hills, centre)])
    return Route(s=s, xy=xy, yaw=yaw, t=t, pass_starts=pass_starts, z=z, centre=centre_xyz)


def speed_profile(s: np.ndarray, yaw: np.ndarray, cfg: RouteConfig, phases: np.ndarray) -> np.ndarray:
    """Time at each arc-length sample: cruise speed with a slow variation, slowed in curves to
    ``max_lateral_accel_mps2`` and limited in acceleration / braking; starts from rest."""
    ds = float(s[1] - s[0]) if len(s) > 1 else 1.0
    n_smooth = max(1, int(round(cfg.curvature_window_m / ds)))
    kappa = np.abs(np.gradient(yaw, ds))
    box = np.ones(2 * n_smooth + 1) / (2 * n_smooth + 1)
    kappa = np.convolve(np.pad(kappa, n_smooth, mode="edge"), box, "valid")
    wavelength = cfg.speed_mps * cfg.speed_variation_period_s
    v = cfg.speed_mps * (1.0 + cfg.speed_variation * _smooth_noise(s, wavelength, phases))
    v = np.minimum(v, np.sqrt(cfg.max_lateral_accel_mps2 / np.maximum(kappa, 1e-9)))
    v[0] = 0.0
    # Forward (acceleration) and backward (braking) limits: v^2 changes by at most 2 a ds.
    acc2, dec2 = 2.0 * cfg.max_accel_mps2 * ds, 2.0 * cfg.max_decel_mps2 * ds
    v2 = v * v
    for i in range(1, len(v2)):
        v2[i] = min(v2[i], v2[i - 1] + acc2)
    for i in range(len(v2) - 2, -1, -1):
        v2[i] = min(v2[i], v2[i + 1] + dec2)
    v = np.sqrt(v2)
    dt = 2.0 * ds / np.maximum(v[1:] + v[:-1], 1e-9)
    return np.concatenate([[0.0], np.cumsum(dt)])


def _gaussian_smooth(xy: np.ndarray, sigma_samples: float) -> np.ndarray:
    half = int(math.ceil(3 * sigma_samples))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma_samples) ** 2)
    k /= k.sum()
    padded = np.pad(xy, ((half, half), (0, 0)), mode="reflect", reflect_type="odd")
    return np.stack([np.convolve(padded[:, i], k, mode="valid") for i in range(xy.shape[1])], axis=1)


def _heading(xy: np.ndarray, step: float, smoothing_m: float) -> np.ndarray:
    d = np.gradient(xy, axis=0)
    if smoothing_m > step:
        n = int(round(smoothing_m / step)) | 1
        kernel = np.ones(n) / n
        d = np.stack(
            [np.convolve(np.pad(d[:, i], n // 2, mode="edge"), kernel, mode="valid") for i in range(2)],
            axis=1,
        )
    return np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
