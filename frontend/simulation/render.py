"""Sensors of the simulator: a pinhole camera and a spinning LiDAR, both ray casters.

The world is 2.5D (vertical walls on a ground plane), so one horizontal ray per image column
(or per LiDAR azimuth) finds every wall the column can see; the nearest ``layers`` front-facing
hits are kept and each pixel row (or beam) takes the first one its elevation actually meets
below the wall's top, falling back to the ground plane or the sky. Everything is vectorised
numpy; float32 is used for the large ray x segment matrices.
"""

from __future__ import annotations

import math

import numpy as np

from frontend.simulation.city import City
from frontend.simulation.config import AppearanceConfig, CameraConfig, LidarConfig

_NEAR = 1e-3  # rays ignore walls closer than this (metres along the ray)
_GROUND_SUN = 0.8  # share of the sun term a horizontal surface receives
_SKY_EXPONENT = 0.7  # shape of the sky gradient from horizon to the top row


def _cull(city: City, ox: float, oy: float, radius: float) -> np.ndarray:
    """Indices of walls within ``radius`` of (ox, oy) whose front faces the point."""
    o = np.array([ox, oy])
    e = city.p1 - city.p0
    w = o - city.p0
    ee = np.einsum("ij,ij->i", e, e)
    f = np.clip(np.einsum("ij,ij->i", w, e) / ee, 0.0, 1.0)
    d = np.linalg.norm(w - e * f[:, None], axis=1)
    facing = np.einsum("ij,ij->i", w, city.normal) > -radius * 1e-3
    return np.nonzero((d < radius) & facing)[0]


def cast_rays(city: City, segs: np.ndarray, ox, oy, dx, dy, layers: int):
    """Nearest ``layers`` front-facing wall hits of horizontal rays o + t d.

    ox, oy: scalars or (R,) origins; dx, dy: (R,) directions (any length; t is in units of |d|).
    Returns t (R, K) sorted ascending (inf = no hit), segment index (R, K) into city arrays, and
    the hit's fractional position along the segment (R, K).
    """
    R = len(dx)
    if len(segs) == 0:
        inf = np.full((R, 1), np.inf, np.float32)
        return inf, np.zeros((R, 1), np.int64), np.zeros((R, 1), np.float32)
    p0 = city.p0[segs].astype(np.float32)
    e = (city.p1[segs] - city.p0[segs]).astype(np.float32)
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
    """Renders RGB uint8 images of ``city`` from planar poses (x, y, yaw)."""

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

    def render(self, x: float, y: float, yaw: float, app: AppearanceConfig, rng: np.random.Generator):
        """RGB uint8 (height, width, 3) image from camera position (x, y) looking along yaw."""
        cfg, city = self.cfg, self.city
        H, W = cfg.height, cfg.width
        h_cam = np.float32(cfg.height_m)
        c, s = math.cos(yaw), math.sin(yaw)
        dx = (c - s * self.lateral).astype(np.float32)
        dy = (s + c * self.lateral).astype(np.float32)
        segs = _cull(city, x, y, self.view_radius)
        tk, sk, uk = cast_rays(city, segs, x, y, dx, dy, cfg.layers)

        # Per pixel, the nearest layer whose wall spans the pixel's height (-1: none).
        slope = self.slope[:, None]
        layer = np.full((H, W), -1, np.int8)
        hk = city.height[sk].astype(np.float32)
        tk_far = np.where(tk < cfg.max_depth_m, tk, np.float32(np.inf))
        for k in range(tk.shape[1] - 1, -1, -1):
            t = tk_far[:, k]
            z = h_cam + t[None, :] * slope
            layer[(z >= 0) & (z <= hk[:, k][None, :])] = k  # inf * slope never passes both tests

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
            k = flat_layer[idx].astype(np.int64)
            t = tk[cols, k]
            seg = sk[cols, k]
            length = np.linalg.norm(city.p1[seg] - city.p0[seg], axis=1)
            u = (city.u0[seg] + uk[cols, k] * length).astype(np.float32)
            v = h_cam + t * self.slope[rows]
            albedo, key = city.wall_albedo(city.surface[seg], u, v)
            shade = app.ambient + app.sun_strength * np.clip(city.normal[seg] @ sun, 0.0, None)
            shade = shade.astype(np.float32)
            lit = (key < app.lit_window_fraction).astype(np.float32)
            finish(idx, albedo, shade[:, None], t * self.ray_norm[cols], lit)

        below = self.slope < 0
        ground_mask = (flat_layer < 0) & np.repeat(below, W)
        idx = np.flatnonzero(ground_mask)
        if len(idx):
            rows, cols = np.divmod(idx, W)
            t = h_cam / -self.slope[rows]
            gx = x + t * dx[cols]
            gy = y + t * dy[cols]
            albedo = city.ground_albedo(gx, gy, np.exp(-t / np.float32(cfg.texture_fade_distance_m)))
            shade = np.float32(app.ambient + app.sun_strength * _GROUND_SUN)
            finish(idx, albedo, shade, t * self.ray_norm[cols])

        idx = np.flatnonzero((flat_layer < 0) & ~ground_mask)
        if len(idx):
            rows = idx // W
            el = np.clip(self.slope[rows] / max(float(self.slope[0]), 1e-6), 0.0, 1.0) ** _SKY_EXPONENT
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
    """

    def __init__(self, city: City, config: LidarConfig, scan_period_s: float):
        self.city = city
        self.cfg = config
        self.period = scan_period_s
        lo, hi = np.radians(config.vfov_deg)
        self.elev = np.linspace(lo, hi, config.beams)
        self.tan_el = np.tan(self.elev).astype(np.float32)
        self.cos_el = np.cos(self.elev)
        n = config.azimuths
        self.frac = (np.arange(n) + 0.5) / n
        self.az = -math.pi + 2.0 * math.pi * self.frac
        self.col_times = self.frac * scan_period_s
        # Unit ray directions in the sensor frame, (beams, azimuths, 3).
        ce, se = np.cos(self.elev)[:, None], np.sin(self.elev)[:, None]
        self.dirs = np.stack(
            [
                ce * np.cos(self.az)[None, :],
                ce * np.sin(self.az)[None, :],
                np.broadcast_to(se, (config.beams, n)),
            ],
            axis=-1,
        )

    def scan(self, xs, ys, yaws, rng: np.random.Generator):
        """One sweep; xs, ys, yaws: scalar or (azimuths,) pose of the sensor at each column.

        Returns (points (N, 3) float64 sensor frame, times (N,) float64 seconds from the sweep
        start).
        """
        cfg, city = self.cfg, self.city
        n = cfg.azimuths
        xs = np.broadcast_to(np.asarray(xs, float), (n,))
        ys = np.broadcast_to(np.asarray(ys, float), (n,))
        yaws = np.broadcast_to(np.asarray(yaws, float), (n,))
        travel = math.hypot(xs[-1] - xs[0], ys[-1] - ys[0])
        segs = _cull(city, xs[-1], ys[-1], cfg.max_range_m + travel)
        ang = yaws + self.az
        tk, sk, _ = cast_rays(city, segs, xs, ys, np.cos(ang), np.sin(ang), cfg.layers)
        h = np.float32(cfg.height_m)
        B = cfg.beams
        t_hit = np.full((B, n), np.inf, np.float32)
        hk = city.height[sk].astype(np.float32)
        tan_el = self.tan_el[:, None]
        for k in range(tk.shape[1] - 1, -1, -1):
            t = tk[:, k][None, :]
            z = h + t * tan_el
            ok = np.isfinite(t) & (z >= 0) & (z <= hk[:, k][None, :])
            t_hit = np.where(ok, t, t_hit)
        down = self.tan_el < 0
        t_ground = np.where(down, h / np.where(down, -self.tan_el, 1.0), np.inf)[:, None]
        t_hit = np.where(np.isinf(t_hit), t_ground, t_hit)
        rng_m = t_hit.astype(np.float64) / self.cos_el[:, None]
        ok = (rng_m >= cfg.min_range_m) & (rng_m <= cfg.max_range_m)
        if cfg.dropout_probability > 0:
            ok &= rng.random(ok.shape) >= cfg.dropout_probability
        # Column-major order: points come out in firing-time order.
        okT = ok.T
        r = rng_m.T[okT]
        if cfg.range_noise_sigma_m > 0:
            r = r + rng.normal(0.0, cfg.range_noise_sigma_m, r.shape)
        pts = self.dirs.transpose(1, 0, 2)[okT] * r[:, None]
        times = np.broadcast_to(self.col_times[:, None], okT.shape)[okT]
        return pts, times.astype(np.float64)
