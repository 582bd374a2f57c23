"""Sensors of the simulator: a pinhole camera and a spinning LiDAR, both ray casters.

The world is 2.5D (vertical walls spanning [z0, z1] over a ground that follows the road's
height), so one horizontal ray per image column (or per LiDAR azimuth) finds every wall the
column can see; the nearest ``layers`` front-facing hits are kept and each pixel row (or
beam) takes the first one its elevation actually meets, falling back to the ground or the
sky. The vehicle pitches with the road; rows and beams tilt with it, and the ground is the
road's local plane (its grade along the heading). Everything is vectorised numpy; float32 is
used for the large ray x segment matrices.

Rendering works on a ``Scene``: the walls present at one instant (parked cars come and go,
traffic moves), taken from the city and the traffic model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from frontend.simulation.city import FACADE, FOLIAGE, City
from frontend.simulation.config import AppearanceConfig, CameraConfig, LidarConfig
from frontend.sources.intrinsics import CameraIntrinsics, pinhole

_NEAR = 1e-3  # rays ignore walls closer than this (metres along the ray)
_GROUND_SUN = 0.8  # share of the sun term a horizontal surface receives
_SKY_EXPONENT = 0.7  # shape of the sky gradient from horizon to the top row
_STREAM_CALIBRATION = 9001
_GROUND_STEPS = 6


@dataclass
class Scene:
    """The walls present at one instant (a subset of the city plus moving vehicles)."""

    p0: np.ndarray
    p1: np.ndarray
    z0: np.ndarray
    z1: np.ndarray
    surface: np.ndarray
    u0: np.ndarray
    normal: np.ndarray

    @classmethod
    def of(cls, city: City, mask: np.ndarray | None = None, extra: Scene | None = None) -> Scene:
        fields = ("p0", "p1", "z0", "z1", "surface", "u0", "normal")
        parts = {f: getattr(city, f) if mask is None else getattr(city, f)[mask] for f in fields}
        if extra is not None and len(extra.p0):
            parts = {f: np.concatenate([parts[f], getattr(extra, f)]) for f in fields}
        return cls(**parts)

    def __len__(self) -> int:
        return len(self.p0)


def _cull(scene: Scene, ox: float, oy: float, radius: float) -> np.ndarray:
    """Indices of walls within ``radius`` of (ox, oy) whose front faces the point."""
    o = np.array([ox, oy])
    e = scene.p1 - scene.p0
    w = o - scene.p0
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-12)
    f = np.clip(np.einsum("ij,ij->i", w, e) / ee, 0.0, 1.0)
    d = np.linalg.norm(w - e * f[:, None], axis=1)
    facing = np.einsum("ij,ij->i", w, scene.normal) > -radius * 1e-3
    return np.nonzero((d < radius) & facing)[0]


def cast_rays(scene: Scene, segs: np.ndarray, ox, oy, dx, dy, layers: int):
    """Nearest ``layers`` front-facing wall hits of horizontal rays o + t d.

    ox, oy: scalars or (R,) origins; dx, dy: (R,) directions (any length; t is in units of |d|).
    Returns t (R, K) sorted ascending (inf = no hit), segment index (R, K) into the scene, and
    the hit's fractional position along the segment (R, K).
    """
    R = len(dx)
    if len(segs) == 0:
        inf = np.full((R, 1), np.inf, np.float32)
        return inf, np.zeros((R, 1), np.int64), np.zeros((R, 1), np.float32)
    p0 = scene.p0[segs].astype(np.float32)
    e = (scene.p1[segs] - scene.p0[segs]).astype(np.float32)
    ox = np.asarray(ox, np.float32).reshape(-1, 1)
    oy = np.asarray(oy, np.float32).reshape(-1, 1)
    dx = np.asarray(dx, np.float32)[:, None]
    dy = np.asarray(dy, np.float32)[:, None]
    wx = p0[None, :, 0] - ox
    wy = p0[None, :, 1] - oy
    ex, ey = e[None, :, 0], e[None, :, 1]
    denom = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.float32(1.0) / denom
        t = (wx * ey - wy * ex) * inv
        u = (wx * dy - wy * dx) * inv
    ok = (denom < 0) & (t > _NEAR) & (u >= 0) & (u <= 1)
    t = np.where(ok, t, np.float32(np.inf))
    K = min(layers, t.shape[1])
    if t.shape[1] > K:
        idx = np.argpartition(t, K - 1, axis=1)[:, :K]
    else:
        idx = np.broadcast_to(np.arange(t.shape[1]), t.shape).copy()
    tk = np.take_along_axis(t, idx, axis=1)
    order = np.argsort(tk, axis=1)
    idx = np.take_along_axis(idx, order, axis=1)
    tk = np.take_along_axis(tk, order, axis=1)
    uk = np.take_along_axis(u, idx, axis=1)
    return tk, segs[idx], uk


class CameraRenderer:
    """Renders RGB uint8 images of ``city`` from poses on the road (x, y, road height, yaw, pitch)."""

    def __init__(self, city: City, config: CameraConfig):
        self.city = city
        self.cfg = config
        W, H = config.width, config.height
        fx = (W / 2.0) / math.tan(math.radians(config.hfov_deg) / 2.0)
        self.fx = fx
        cx, cy = W / 2.0, H / 2.0
        # Body-frame ray per column: (1, lateral) with y to the left; per row: dz per unit forward.
        self.lateral = (-(np.arange(W) + 0.5 - cx) / fx).astype(np.float32)
        self.slope = (-(np.arange(H) + 0.5 - cy) / fx).astype(np.float32)
        self.ray_norm = np.sqrt(1.0 + self.lateral**2).astype(np.float32)  # metres per forward unit
        self.view_radius = config.max_depth_m * math.hypot(1.0, float(np.abs(self.lateral).max()))
        # Pixel noise: a fixed bank of normals read at a per-frame random offset (fast).
        n = W * H * 3
        self._noise_bank = np.random.default_rng([city.seed, 5171]).standard_normal(2 * n, dtype=np.float32)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """K of the rendered images: fx = fy as above, the principal point at the image centre,
        ((W - 1) / 2, (H - 1) / 2) in K's convention (pixel j's centre at j; the rays above put it
        at j + 0.5). On a pitched road the rows tilt by the pitch angle: a pinhole pitched alike,
        to first order."""
        W, H = self.cfg.width, self.cfg.height
        return pinhole(self.fx, self.fx, (W - 1) / 2.0, (H - 1) / 2.0, W, H)

    def render(
        self,
        x: float,
        y: float,
        yaw: float,
        app: AppearanceConfig,
        rng: np.random.Generator,
        *,
        road_z: float = 0.0,
        pitch: float = 0.0,
        grade: float = 0.0,
        scene: Scene | None = None,
        visit: int = 0,
    ):
        """RGB uint8 (height, width, 3) image from the camera above road point (x, y, road_z),
        looking along yaw, pitched nose-up by ``pitch`` on a road rising ``grade`` per metre."""
        cfg, city = self.cfg, self.city
        scene = scene or Scene.of(city)
        H, W = cfg.height, cfg.width
        h_cam = np.float32(cfg.height_m)
        z_cam = np.float32(road_z) + h_cam
        c, s = math.cos(yaw), math.sin(yaw)
        dx = (c - s * self.lateral).astype(np.float32)
        dy = (s + c * self.lateral).astype(np.float32)
        slope = np.tan(np.arctan(self.slope) + np.float32(pitch)).astype(np.float32)  # world dz per forward unit
        segs = _cull(scene, x, y, self.view_radius)
        tk, sk, uk = cast_rays(scene, segs, x, y, dx, dy, cfg.layers)

        # Per pixel, the nearest layer whose wall spans the pixel's height (-1: none).
        layer = np.full((H, W), -1, np.int8)
        z0k = scene.z0[sk].astype(np.float32)
        z1k = scene.z1[sk].astype(np.float32)
        tk_far = np.where(tk < cfg.max_depth_m, tk, np.float32(np.inf))
        for k in range(tk.shape[1] - 1, -1, -1):
            t = tk_far[:, k]
            z = z_cam + t[None, :] * slope[:, None]
            layer[(z >= z0k[:, k][None, :]) & (z <= z1k[:, k][None, :])] = k  # inf never passes both

        gain_tint = np.float32(app.gain) * np.asarray(app.tint, np.float32)
        hor = np.asarray(app.sky_horizon, np.float32)
        top = np.asarray(app.sky_top, np.float32)
        img = np.empty((H * W, 3), np.float32)
        flat_layer = layer.ravel()
        lit_colour = np.float32(app.lit_window_strength) * np.asarray(app.lit_window_colour, np.float32)

        def finish(idx, albedo, shade, dist, emissive=None):
            col = albedo * (shade * gain_tint)
            if emissive is not None:
                col += emissive[:, None] * lit_colour
            fog = (1.0 - np.exp(-dist / np.float32(app.fog_distance_m)))[:, None]
            img[idx] = col * (1.0 - fog) + hor * fog

        sun_az = math.radians(app.sun_azimuth_deg)
        sun = np.array([math.cos(sun_az), math.sin(sun_az)])
        idx = np.flatnonzero(flat_layer >= 0)
        if len(idx):
            rows, cols = np.divmod(idx, W)
            kk = flat_layer[idx].astype(np.int64)
            t = tk[cols, kk]
            seg = sk[cols, kk]
            length = np.linalg.norm(scene.p1[seg] - scene.p0[seg], axis=1)
            u = (scene.u0[seg] + uk[cols, kk] * length).astype(np.float32)
            v = (z_cam + t * slope[rows] - scene.z0[seg]).astype(np.float32)
            sid = scene.surface[seg]
            albedo, key = city.wall_albedo(sid, u, v, visit, app.foliage_tint)
            shade = app.ambient + app.sun_strength * np.clip(scene.normal[seg] @ sun, 0.0, None)
            shade = shade.astype(np.float32)
            lit = (key < app.lit_window_fraction).astype(np.float32)
            finish(idx, albedo, shade[:, None], t * self.ray_norm[cols], lit)

        # Ground: the road's local plane, rising `grade` per metre along the heading.
        drop = np.float32(grade) - slope  # > 0: the row's ray meets the ground ahead
        below = drop > 1e-6
        ground_mask = (flat_layer < 0) & np.repeat(below, W)
        idx = np.flatnonzero(ground_mask)
        if len(idx):
            rows, cols = np.divmod(idx, W)
            t = h_cam / drop[rows]
            gx = x + t * dx[cols]
            gy = y + t * dy[cols]
            albedo = city.ground_albedo(gx, gy, np.exp(-t / np.float32(cfg.texture_fade_distance_m)))
            shade = np.float32(app.ambient + app.sun_strength * _GROUND_SUN)
            finish(idx, albedo, shade, t * self.ray_norm[cols])

        idx = np.flatnonzero((flat_layer < 0) & ~ground_mask)
        if len(idx):
            rows = idx // W
            el = np.clip(slope[rows] / max(float(slope[0]), 1e-6), 0.0, 1.0) ** _SKY_EXPONENT
            img[idx] = hor * (1.0 - el[:, None]) + top * el[:, None]

        if app.gamma != 1.0:
            np.power(np.clip(img, 0.0, None), 1.0 / app.gamma, out=img)
        img *= np.float32(255.0)
        if app.noise_sigma > 0:
            n = img.size
            off = int(rng.integers(0, n))
            img += self._noise_bank[off : off + n].reshape(img.shape) * np.float32(app.noise_sigma)
        img += np.float32(0.5)
        np.clip(img, 0, 255, out=img)
        return img.astype(np.uint8).reshape(H, W, 3)


class LidarRenderer:
    """Spinning LiDAR: ``beams`` x ``azimuths`` rays, one sweep per scan period.

    Column j is fired at time (j + 0.5) / azimuths of the sweep, azimuth sweeping
    counter-clockwise from straight behind. Points are returned in the sensor frame of the
    instant each was measured (a real, motion-distorted scan); the frame's pose is the pose
    at the end of the sweep, matching kiss-icp's deskew-to-end convention.

    The unit is imperfect as real ones are: each beam's true elevation differs from its
    nominal one and each beam has a range offset (fixed per unit, from the seed), the points
    are reported along the nominal directions, and foliage returns from random depths or
    lets the beam through.
    """

    def __init__(self, city: City, config: LidarConfig, scan_period_s: float):
        self.city = city
        self.cfg = config
        self.period = scan_period_s
        lo, hi = np.radians(config.vfov_deg)
        self.elev = np.linspace(lo, hi, config.beams)
        calib = np.random.default_rng([city.seed, _STREAM_CALIBRATION])
        self.elev_true = (
            self.elev
            + np.radians(config.beam_elevation_bias_deg)
            + np.radians(config.beam_elevation_error_deg) * calib.standard_normal(config.beams)
        )
        self.range_bias = config.range_bias_sigma_m * calib.standard_normal(config.beams)
        # each laser fires a little off the azimuth the unit reports (the rotational correction
        # of a multi-laser unit's calibration): its points come out turned by that error
        self.azimuth_error = np.radians(config.beam_azimuth_error_deg) * calib.standard_normal(config.beams)
        n = config.azimuths
        self.frac = (np.arange(n) + 0.5) / n
        self.az = -math.pi + 2.0 * math.pi * self.frac
        self.col_times = self.frac * scan_period_s
        # Unit ray directions in the sensor frame as the unit reports them, (beams, azimuths, 3).
        ce, se = np.cos(self.elev)[:, None], np.sin(self.elev)[:, None]
        self.dirs = np.stack(
            [
                ce * np.cos(self.az)[None, :],
                ce * np.sin(self.az)[None, :],
                np.broadcast_to(se, (config.beams, n)),
            ],
            axis=-1,
        )

    def scan(
        self,
        xs,
        ys,
        yaws,
        rng: np.random.Generator,
        *,
        road_z: float | np.ndarray = 0.0,
        pitch: float = 0.0,
        grade: float = 0.0,
        scene: Scene | None = None,
    ):
        """One sweep; xs, ys, yaws, road_z: scalar or (azimuths,) pose of the sensor at each
        column, above road height ``road_z`` with the vehicle pitched by ``pitch`` on a road of grade
        ``grade``.

        Returns (points (N, 3) float64 sensor frame, times (N,) float64 seconds from the sweep
        start).
        """
        cfg, city = self.cfg, self.city
        scene = scene or Scene.of(city)
        n = cfg.azimuths
        xs = np.broadcast_to(np.asarray(xs, float), (n,))
        ys = np.broadcast_to(np.asarray(ys, float), (n,))
        yaws = np.broadcast_to(np.asarray(yaws, float), (n,))
        travel = math.hypot(xs[-1] - xs[0], ys[-1] - ys[0])
        segs = _cull(scene, xs[-1], ys[-1], cfg.max_range_m + travel)
        ang = yaws + self.az
        tk, sk, uk = cast_rays(scene, segs, xs, ys, np.cos(ang), np.sin(ang), cfg.layers)
        h = np.float32(cfg.height_m)
        # the sensor's height at each column: the vehicle climbs during a sweep as it moves
        z_s = (np.broadcast_to(np.asarray(road_z, np.float32), (n,)) + h)[None, :]
        B = cfg.beams
        # World elevation of each beam at each azimuth: the true elevation tilted by the pitch.
        cos_az = np.cos(self.az)
        tan_w = np.tan(self.elev_true[:, None] + pitch * cos_az[None, :]).astype(np.float32)
        t_hit = np.full((B, n), np.inf, np.float32)
        k_hit = np.full((B, n), -1, np.int64)
        foliage_hit = np.zeros((B, n), bool)
        z0k = scene.z0[sk].astype(np.float32)
        z1k = scene.z1[sk].astype(np.float32)
        leafy = city.kind[scene.surface[sk]] == FOLIAGE
        p_leaf = cfg.foliage_return_probability
        for k in range(tk.shape[1] - 1, -1, -1):
            t = tk[:, k][None, :]
            z = z_s + t * tan_w
            ok = np.isfinite(t) & (z >= z0k[:, k][None, :]) & (z <= z1k[:, k][None, :])
            if leafy[:, k].any():
                passes = leafy[:, k][None, :] & (rng.random((B, n)) >= p_leaf)
                ok &= ~passes
            t_hit = np.where(ok, t, t_hit)
            k_hit = np.where(ok, k, k_hit)
            foliage_hit = np.where(ok, np.broadcast_to(leafy[:, k][None, :], (B, n)), foliage_hit)
        t_hit = self._through_glass(scene, tk, sk, uk, k_hit, t_hit, z_s, tan_w, rng)
        if cfg.foliage_depth_m > 0 and foliage_hit.any():
            t_hit = t_hit + foliage_hit * rng.uniform(0.0, cfg.foliage_depth_m, (B, n)).astype(np.float32)
        # Ground: the road's local plane along each azimuth.
        drop = np.float32(grade) * cos_az[None, :].astype(np.float32) - tan_w
        t_ground = np.where(drop > 1e-6, h / np.where(drop > 1e-6, drop, 1.0), np.inf).astype(np.float32)
        t_ground = self._ground_relief(xs, ys, ang, t_ground, drop, z_s[0], tan_w)
        t_hit = np.where(np.isinf(t_hit), t_ground, np.minimum(t_hit, t_ground))  # NaN (lost) stays NaN
        rng_m = t_hit.astype(np.float64) * np.sqrt(1.0 + tan_w.astype(np.float64) ** 2)
        rng_m = rng_m * (1.0 + cfg.range_scale_error) + self.range_bias[:, None]
        ok = np.isfinite(rng_m) & (rng_m >= cfg.min_range_m) & (rng_m <= cfg.max_range_m)
        if cfg.dropout_probability > 0:
            ok &= rng.random(ok.shape) >= cfg.dropout_probability
        # Column-major order: points come out in firing-time order.
        okT = ok.T
        r = rng_m.T[okT]
        if cfg.range_noise_sigma_m > 0:
            r = r + rng.normal(0.0, cfg.range_noise_sigma_m, r.shape)
        pts = self.dirs.transpose(1, 0, 2)[okT] * r[:, None]
        if cfg.beam_azimuth_error_deg > 0:  # hit along the true azimuth, reported along the nominal one
            delta = self.azimuth_error[np.nonzero(okT)[1]]
            c, s = np.cos(delta), np.sin(delta)
            pts[:, 0], pts[:, 1] = c * pts[:, 0] + s * pts[:, 1], c * pts[:, 1] - s * pts[:, 0]
        times = np.broadcast_to(self.col_times[:, None], okT.shape)[okT]
        return pts, times.astype(np.float64)

    def _through_glass(self, scene: Scene, tk, sk, uk, k_hit, t_hit, z_s, tan_w, rng: np.random.Generator):
        """Beams that meet a window or shop front mostly pass the glass and return from the room
        behind it (or not at all): facades read as walls with holes, as real scans show them."""
        cfg = self.cfg
        if cfg.glass_pass_probability <= 0 and cfg.glass_dropout_probability <= 0:
            return t_hit
        b, c = np.nonzero(k_hit >= 0)
        if not len(b):
            return t_hit
        k = k_hit[b, c]
        seg = sk[c, k]
        facade = self.city.kind[scene.surface[seg]] == FACADE
        b, c, k, seg = b[facade], c[facade], k[facade], seg[facade]
        t = tk[c, k]
        length = np.linalg.norm(scene.p1[seg] - scene.p0[seg], axis=1)
        u = (scene.u0[seg] + uk[c, k] * length).astype(np.float32)
        v = (z_s[0, c] + t * tan_w[b, c] - scene.z0[seg]).astype(np.float32)
        _, key = self.city.wall_albedo(scene.surface[seg], u, v)
        glass = key < 1.0
        b, c, t, key = b[glass], c[glass], t[glass], key[glass]
        draw = rng.random(len(b))
        out = t_hit.copy()
        through = draw < cfg.glass_pass_probability
        # The room behind a window stays where it is: its depth is a property of the window.
        out[b[through], c[through]] = t[through] + np.float32(1.5) + np.float32(4.5) * key[through]
        lost = (draw >= cfg.glass_pass_probability) & (
            draw < cfg.glass_pass_probability + cfg.glass_dropout_probability
        )
        out[b[lost], c[lost]] = np.nan
        return out

    def _ground_relief(self, xs, ys, ang, t_ground, drop, z_s, tan_w):
        """Move ground hits from the road's local plane onto the world's terrain and relief
        (kerbs, camber, undulating verges), by Newton steps along each beam. The ground is then
        the same wherever it is seen from, as a real one is."""
        hit = np.isfinite(t_ground)
        if not hit.any():
            return t_ground
        b, c = np.nonzero(hit)
        t = t_ground[b, c].astype(np.float64)
        slope, d = tan_w[b, c].astype(np.float64), drop[b, c].astype(np.float64)
        ca, sa = np.cos(ang[c]), np.sin(ang[c])
        for _ in range(_GROUND_STEPS):
            gz = self.city.ground_z(xs[c] + t * ca, ys[c] + t * sa)
            t = np.maximum(t + (z_s[c] + t * slope - gz) / d, 0.1)
        out = t_ground.copy()
        out[b, c] = t.astype(np.float32)
        return out
