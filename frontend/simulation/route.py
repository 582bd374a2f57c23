"""Routes through the simulated streets: preset loops with revisits, or a poses file.

A route is a dense planar path parameterised by arc length s: ``Route.pose_at(s)`` gives
(x, y, yaw) with yaw along the direction of travel. Preset routes are polylines through street
crossings with circular fillets at the corners, then shifted into the driving lane with a slow
lateral weave (so later passes do not repeat earlier poses exactly). ``Route.arc_length_at(t)``
maps time to s: the vehicle starts from rest, cruises at a slowly varying speed and slows
down for corners (lateral acceleration limit) with bounded acceleration and braking.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from frontend.errors import FrontendInputError
from frontend.simulation.city import City
from frontend.simulation.config import RouteConfig

# Passes of the preset routes as crossings (i, j) = (street_x index, street_y index).
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


@dataclass
class Route:
    """Dense path: arc length ``s`` (uniform), positions ``xy``, unwrapped ``yaw`` and the time
    ``t`` at which the vehicle passes each sample (speed profile)."""

    s: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    t: np.ndarray
    pass_starts: np.ndarray  # arc length at which each pass (loop) begins

    @property
    def length(self) -> float:
        return float(self.s[-1])

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

    def pass_index(self, s) -> np.ndarray:
        return np.searchsorted(self.pass_starts, np.asarray(s, float), side="right") - 1

    def arc_length_at(self, t) -> np.ndarray:
        """Distance driven at time t (seconds since the start of the route); clamped."""
        return np.interp(np.asarray(t, float), self.t, self.s)


def read_poses_file(path: str | Path, fmt: str = "auto") -> tuple[np.ndarray | None, np.ndarray]:
    """Read a TUM (``t x y z qx qy qz qw``) or KITTI (12 values of a 3x4) poses file.

    Returns (timestamps or None, positions (N, 3)). Raises FrontendInputError naming the file
    and line on anything unreadable.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FrontendInputError(f"poses file {path}: cannot read: {exc}") from exc
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            vals = [float(v) for v in line.replace(",", " ").split()]
        except ValueError as exc:
            raise FrontendInputError(f"poses file {path}: line {lineno}: not numbers: {line[:60]!r}") from exc
        if rows and len(vals) != len(rows[0]):
            raise FrontendInputError(
                f"poses file {path}: line {lineno}: {len(vals)} values, earlier lines have {len(rows[0])}"
            )
        rows.append(vals)
    if not rows:
        raise FrontendInputError(f"poses file {path}: no poses")
    arr = np.asarray(rows, float)
    if not np.all(np.isfinite(arr)):
        raise FrontendInputError(f"poses file {path}: contains non-finite values")
    ncol = arr.shape[1]
    if fmt == "auto":
        fmt = {8: "tum", 12: "kitti"}.get(ncol, "")
        if not fmt:
            raise FrontendInputError(
                f"poses file {path}: {ncol} values per line; expected 8 (TUM) or 12 (KITTI)"
            )
    if fmt == "tum":
        if ncol != 8:
            raise FrontendInputError(f"poses file {path}: TUM needs 8 values per line, found {ncol}")
        return arr[:, 0], arr[:, 1:4]
    if ncol != 12:
        raise FrontendInputError(f"poses file {path}: KITTI needs 12 values per line, found {ncol}")
    return None, arr[:, [3, 7, 11]]


def _fillet_polyline(pts: np.ndarray, radius: float, step: float):
    """Dense polyline through ``pts`` with circular arcs at the corners.

    Returns (dense points (M, 2), index into dense of each waypoint's corner point).
    """
    out = [pts[0]]
    marks = [0]
    for k in range(1, len(pts) - 1):
        a = pts[k] - pts[k - 1]
        b = pts[k + 1] - pts[k]
        la, lb = np.linalg.norm(a), np.linalg.norm(b)
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


def preset_waypoints(cfg: RouteConfig, city: City) -> list[np.ndarray]:
    """Crossings of each pass of a preset route, as world xy arrays."""
    if cfg.preset == "block_grid":
        passes = [_LOOP_A] * cfg.laps + [_LOOP_B]
    elif cfg.preset == "figure_eight":
        passes = [_EIGHT] * cfg.laps
    else:
        raise FrontendInputError(f"route.preset {cfg.preset!r} is not a preset")
    need_i = max(i for p in passes for i, _ in p)
    need_j = max(j for p in passes for _, j in p)
    if need_i >= len(city.street_x) or need_j >= len(city.street_y):
        raise FrontendInputError(
            f"route.preset {cfg.preset!r} needs city.streets_x >= {need_i + 1} and "
            f"city.streets_y >= {need_j + 1}"
        )
    return [np.array([city.node(i, j) for i, j in p]) for p in passes]


def build_route(
    cfg: RouteConfig,
    city: City,
    seed: int,
    poses_xy: np.ndarray | None = None,
) -> Route:
    """Build the dense route. ``poses_xy`` (N, 2) gives the path of a poses-file route.

    A poses file contributes its positions' x, y only (poses are taken as z-up body poses, as
    kiss-icp and this project write them); its orientations and timestamps are ignored: the
    heading follows the path and the vehicle drives it with the configured speed profile.
    Lane offset, weaving and corner easing apply to preset routes only.
    """
    rng = np.random.default_rng([seed, 4409])
    wander_phases = rng.uniform(0, 2 * math.pi, 2)
    speed_phases = rng.uniform(0, 2 * math.pi, 2)
    step = cfg.path_resolution_m
    if cfg.is_file:
        if poses_xy is None:
            _, xyz = read_poses_file(cfg.preset, cfg.poses_format)
            poses_xy = xyz[:, :2]
        keep = np.concatenate([[True], np.linalg.norm(np.diff(poses_xy, axis=0), axis=1) > 1e-6])
        pts = poses_xy[keep]
        if len(pts) < 2:
            raise FrontendInputError(f"poses file {cfg.preset}: the path does not move")
        s_raw = _arclength(pts)
        s = np.arange(0.0, s_raw[-1], step)
        xy = np.stack([np.interp(s, s_raw, pts[:, 0]), np.interp(s, s_raw, pts[:, 1])], axis=1)
        yaw = _heading(xy, step, cfg.file_heading_smoothing_m)
        _warn_off_road(city, xy, cfg.preset)
        t = speed_profile(s, yaw, cfg, speed_phases)
        return Route(s=s, xy=xy, yaw=yaw, t=t, pass_starts=np.array([0.0]))

    if abs(cfg.lane_offset_m) + cfg.lateral_wander_m >= cfg.turn_radius_m:
        raise FrontendInputError(
            "route.turn_radius_m must exceed |route.lane_offset_m| + route.lateral_wander_m "
            f"({cfg.turn_radius_m} <= {abs(cfg.lane_offset_m) + cfg.lateral_wander_m})"
        )
    passes = preset_waypoints(cfg, city)
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
    offset = cfg.lane_offset_m + cfg.lateral_wander_m * _smooth_noise(
        s_c, cfg.wander_wavelength_m, wander_phases
    )
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
    return Route(s=s, xy=xy, yaw=yaw, t=t, pass_starts=pass_starts)


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
    return np.stack([np.convolve(padded[:, i], k, mode="valid") for i in range(2)], axis=1)


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


def _warn_off_road(city: City, xy: np.ndarray, name: str) -> None:
    cfg = city.config
    p = cfg.pitch_m
    dx = np.abs((xy[:, 0] - city.street_x[0]) - np.round((xy[:, 0] - city.street_x[0]) / p) * p)
    dy = np.abs((xy[:, 1] - city.street_y[0]) - np.round((xy[:, 1] - city.street_y[0]) / p) * p)
    on_road = (dx < cfg.street_width_m / 2) | (dy < cfg.street_width_m / 2)
    if on_road.mean() < 0.95:
        warnings.warn(
            f"poses file {name}: {100 * (1 - on_road.mean()):.0f}% of the path is off the simulated "
            f"streets (grid pitch {p} m through the origin); frames there see the inside of buildings",
            stacklevel=3,
        )
