"""The simulated world: a Manhattan grid of streets lined by procedurally textured buildings.

Geometry is 2.5D: every obstacle is a set of vertical wall segments standing on the ground
plane z = 0 (building facades, alley back walls, lamp posts, parked cars). Each segment is
oriented so that its outward normal lies on the right of p0 -> p1; a ray d hits the front
side iff cross(d, p1 - p0) < 0, which gives back-face culling for free in the ray caster.

Appearance is procedural and deterministic in (seed, surface id): ``City.wall_albedo`` maps
(surface id, u along the wall in metres, v height in metres) to linear RGB, vectorised;
``City.ground_albedo`` does the same for world (x, y) on the ground plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from frontend.simulation.config import CityConfig

# Surface kinds.
FACADE, POLE, CAR, ALLEY = 0, 1, 2, 3

# Independent hash channels for per-surface parameters (any distinct integers).
(
    _H_PALETTE,
    _H_JITTER_R,
    _H_JITTER_G,
    _H_JITTER_B,
    _H_STOREY,
    _H_GROUND,
    _H_STOREYS,
    _H_PITCH,
    _H_WIN_W,
    _H_WIN_H,
    _H_SHOP,
    _H_SIGN,
    _H_SIGN_POS,
    _H_SIGN_LEN,
    _H_AWNING,
    _H_ACCENT,
    _H_DOOR,
    _H_TRIM,
    _H_GRAIN,
    _H_GLASS,
    _H_LIT,
    _H_LETTER,
    _H_ASPHALT,
    _H_PATCH,
) = range(101, 125)

# Fixed look of the materials (relative proportions, not tunables of the traverse).
_GLASS = np.array([0.10, 0.14, 0.20], np.float32)
_GLASS_SHEEN = np.array([0.30, 0.36, 0.42], np.float32)
_METAL = np.array([0.22, 0.24, 0.25], np.float32)
_LAMP = np.array([0.92, 0.90, 0.80], np.float32)
_TYRE = np.array([0.06, 0.06, 0.07], np.float32)
_WHITE = np.array([0.92, 0.92, 0.90], np.float32)
_ALLEY = np.array([0.30, 0.27, 0.25], np.float32)
_ASPHALT = np.array([0.30, 0.30, 0.32], np.float32)
_SIDEWALK = np.array([0.62, 0.60, 0.56], np.float32)
_PLOT = np.array([0.48, 0.46, 0.42], np.float32)
_MARKING = np.array([0.90, 0.90, 0.86], np.float32)

# Wall materials (index into each surface's colour table) and ground materials.
(
    M_WALL, M_COURSE, M_CORNICE, M_FRAME, M_GLASS, M_MULLION, M_PLINTH, M_SHOP, M_SIGN, M_LETTER,
    M_AWNING_A, M_AWNING_B, M_DOOR, M_DOOR_FRAME, M_POLE, M_LAMP, M_CAR, M_CAR_GLASS, M_TYRE, M_ALLEY,
) = range(20)
N_MATERIALS = 20
_GRAINY = np.zeros(N_MATERIALS, bool)
_GRAINY[[M_WALL, M_COURSE, M_CORNICE, M_PLINTH, M_ALLEY]] = True
G_PLOT, G_ASPHALT, G_SIDEWALK, G_JOINT, G_KERB, G_MARKING = range(6)
_GROUND_COLOURS = np.array(
    [_PLOT, _ASPHALT, _SIDEWALK, _SIDEWALK * 0.8, _SIDEWALK * 1.25, _MARKING], np.float32
)

# Proportions of the procedural textures (metres unless a fraction).
_FRAME_M = 0.12  # window frame width
_COURSE_FRACTION = 0.05  # string course at each floor, fraction of the storey
_MULLION_FRACTION = 0.03  # half width of the vertical glazing bar, fraction of window pitch
_PLINTH_M = 0.35
_LETTER_M = 0.35
_AWNING_STRIPE_M = 0.5
_LAMP_M = 0.45
_GRAIN_U_M, _GRAIN_V_M, _GRAIN_AMPLITUDE = 0.3, 0.15, 0.12
_TILE_M, _JOINT_M, _KERB_M = 1.2, 0.04, 0.25
_DASH_M, _LINE_HALF_WIDTH_M = 6.0, 0.08


_HASH_MULTIPLIERS = tuple(
    np.uint32(m) for m in (0x27D4EB2F, 0x165667B1, 0xC2B2AE3D, 0x9E3779B1, 0x61C88647, 0x7FEB352D, 0x846CA68B)
)


def _mix32(x: np.ndarray) -> np.ndarray:
    """Avalanche a uint32 array (xor-shift-multiply finaliser; wraps modulo 2**32)."""
    with np.errstate(over="ignore"):
        x = x ^ (x >> np.uint32(16))
        x = x * np.uint32(0x7FEB352D)
        x = x ^ (x >> np.uint32(15))
        x = x * np.uint32(0x846CA68B)
        return x ^ (x >> np.uint32(16))


def hash_u32(*keys) -> np.ndarray:
    """Deterministic uint32 hash of integer arrays (broadcast), order-sensitive.

    Keys are combined with distinct odd multipliers (wrapping) and then avalanched twice;
    floats are floored first.
    """
    if len(keys) > len(_HASH_MULTIPLIERS):
        raise ValueError(f"hash_u32 takes at most {len(_HASH_MULTIPLIERS)} keys")
    h = np.uint32(0x9E3779B9)
    with np.errstate(over="ignore"):
        for mult, k in zip(_HASH_MULTIPLIERS, keys):
            k = np.asarray(k)
            if k.dtype.kind == "f":
                k = np.floor(k)
            k = k.astype(np.int32).view(np.uint32)  # two's complement bits of small integers
            h = (h + k * mult) * np.uint32(0x85EBCA77)
    return _mix32(_mix32(np.asarray(h, dtype=np.uint32)))


def hash01(*keys) -> np.ndarray:
    """Uniform float32 in [0, 1) from ``hash_u32``."""
    return (hash_u32(*keys) >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def _lerp(lo_hi: tuple[float, float], t: np.ndarray) -> np.ndarray:
    return (lo_hi[0] + (lo_hi[1] - lo_hi[0]) * t).astype(np.float32)


@dataclass
class City:
    """Wall segments plus per-surface texture parameters; see module docstring."""

    config: CityConfig
    seed: int
    p0: np.ndarray  # (S, 2) float64
    p1: np.ndarray  # (S, 2)
    height: np.ndarray  # (S,) top of each wall
    surface: np.ndarray  # (S,) int surface id
    u0: np.ndarray  # (S,) texture u at p0
    normal: np.ndarray  # (S, 2) outward unit normal
    kind: np.ndarray  # (F,) surface kind
    params: dict[str, np.ndarray]  # per-surface texture parameters, each (F,) or (F, 3)
    street_x: np.ndarray  # x of the streets running along y (route grid, index 0..)
    street_y: np.ndarray  # y of the streets running along x

    @property
    def n_segments(self) -> int:
        return len(self.p0)

    def node(self, i: int, j: int) -> np.ndarray:
        """World xy of the crossing of street_x[i] and street_y[j]."""
        return np.array([self.street_x[i], self.street_y[j]], dtype=np.float64)

    # -- texture -----------------------------------------------------------------------------

    def wall_albedo(self, sid: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Texture of walls: (surface ids, u metres along the wall, v metres above ground).

        Returns (rgb float32 (N, 3) in [0, 1], window_key float32 (N,): a uniform [0, 1) value
        per window / shop front / lamp used to pick which ones are lit, 2.0 elsewhere).
        Each pixel is classified into a material; its colour comes from the per-surface table
        ``params["colours"]`` (built once), times a grain factor, plus a glass sheen.
        """
        cfg = self.config
        P = self.params
        sid = np.asarray(sid, dtype=np.int64)
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        kind = self.kind[sid]
        top, gh, sh = P["top"][sid], P["ground_h"][sid], P["storey_h"][sid]
        pitch, wf, hf = P["pitch"][sid], P["win_w"][sid], P["win_h"][sid]
        mat = np.zeros(len(sid), np.int8)  # M_WALL

        # Facade: storeys with a window per column, string course and cornice.
        upper = (v >= gh) & (v < top - cfg.parapet_m)
        fv = (v - gh) / sh
        storey = np.floor(fv)
        fr = fv - storey
        cu = u / pitch
        col = np.floor(cu)
        fu = np.abs(cu - col - 0.5)
        sill = (1.0 - hf) * 0.45
        fr_u = _FRAME_M / pitch
        fr_v = _FRAME_M / sh
        in_frame = upper & (fu < wf / 2 + fr_u) & (fr > sill - fr_v) & (fr < sill + hf + fr_v)
        in_win = in_frame & (fu < wf / 2) & (fr > sill) & (fr < sill + hf)
        mat[upper & (fr < _COURSE_FRACTION)] = M_COURSE
        mat[v >= top - cfg.parapet_m] = M_CORNICE
        mat[in_frame] = M_FRAME
        mat[in_win] = M_GLASS
        mat[in_win & (fu < _MULLION_FRACTION)] = M_MULLION

        # Ground floor: plinth, shop glazing, sign band with letters, awning, door.
        ground = v < gh
        mat[ground & (v < _PLINTH_M)] = M_PLINTH
        su = u / (2.0 * pitch)
        shop_col = np.floor(su)
        sfu = su - shop_col
        shop = ground & P["shop"][sid] & (v > 0.45) & (v < gh - 1.1) & (sfu > 0.06) & (sfu < 0.94)
        mat[shop] = M_SHOP
        sign = ground & P["sign"][sid] & (u > P["sign_u0"][sid]) & (u < P["sign_u1"][sid])
        sign &= (v > gh - 0.95) & (v < gh - 0.25)
        mat[sign] = M_SIGN
        letter = sign & (v > gh - 0.8) & (v < gh - 0.4)
        letter &= hash01(self.seed, _H_LETTER, sid, np.floor(u / _LETTER_M)) < 0.6
        mat[letter] = M_LETTER
        awn = ground & P["awning"][sid] & P["shop"][sid] & ~sign & (v > gh - 1.7) & (v < gh - 1.0)
        mat[awn] = np.where((np.floor(u / _AWNING_STRIPE_M) % 2) == 0, M_AWNING_A, M_AWNING_B)[awn]
        du = np.abs(u - P["door_u"][sid])
        door = ground & (du < 0.65) & (v < 2.3)
        mat[door] = np.where((du > 0.55) | (v > 2.2), M_DOOR_FRAME, M_DOOR)[door]

        # Other kinds overwrite (their facade classification above is meaningless).
        frac = v / top
        mat = np.where(kind == POLE, np.where(v > top - _LAMP_M, M_LAMP, M_POLE), mat)
        car_mat = np.where(frac < 0.3, M_TYRE, np.where((frac > 0.62) & (frac < 0.92), M_CAR_GLASS, M_CAR))
        mat = np.where(kind == CAR, car_mat, mat)
        mat = np.where(kind == ALLEY, M_ALLEY, mat).astype(np.int64)

        rgb = P["colours"][sid, mat]
        grain = hash01(self.seed, _H_GRAIN, sid, np.floor(u / _GRAIN_U_M), np.floor(v / _GRAIN_V_M))
        factor = np.where(_GRAINY[mat], 1.0 + _GRAIN_AMPLITUDE * (grain - 0.5), 1.0).astype(np.float32)
        rgb *= factor[:, None]
        glassy = (mat == M_GLASS) | (mat == M_SHOP)
        is_shop = mat == M_SHOP
        hw = hash_u32(self.seed, _H_GLASS, sid, np.where(is_shop, shop_col, col), np.where(is_shop, -1, storey))
        sheen = (hw & np.uint32(0xFFFF)).astype(np.float32) * np.float32(1.0 / 65536)
        wkey = (hw >> np.uint32(16)).astype(np.float32) * np.float32(1.0 / 65536)
        wv = np.clip((fr - sill) / np.maximum(hf, 1e-3), 0.0, 1.0)
        rgb += (np.where(glassy, sheen * (1.0 - 0.6 * wv), 0.0)[:, None] * _GLASS_SHEEN).astype(np.float32)
        key = np.where(mat == M_GLASS, wkey, np.where(mat == M_SHOP, 0.5 * wkey, 2.0))
        key = np.where(mat == M_LAMP, 0.0, key).astype(np.float32)
        return np.clip(rgb, 0.0, 1.0), key

    def ground_albedo(self, x: np.ndarray, y: np.ndarray, detail: np.ndarray | None = None):
        """Texture of the ground at world (x, y): asphalt, markings, kerbs, paved sidewalks.

        ``detail`` in [0, 1] scales fine texture (1 near, 0 far) as a cheap anti-aliasing.
        """
        cfg = self.config
        x = np.asarray(x, np.float32)
        y = np.asarray(y, np.float32)
        p = np.float32(cfg.pitch_m)
        lx = x - np.float32(self.street_x[0])
        ly = y - np.float32(self.street_y[0])
        dx = np.abs(lx - np.round(lx / p) * p)
        dy = np.abs(ly - np.round(ly / p) * p)
        rh = np.float32(cfg.road_half_width_m)
        half = np.float32(cfg.street_width_m / 2.0)
        road_v = dx < rh  # road running along y
        road_h = dy < rh
        road = road_v | road_h
        crossing = road_v & road_h
        walk = ~road & ((dx < half) | (dy < half))
        d = np.ones(x.shape, np.float32) if detail is None else detail.astype(np.float32)

        mat = np.where(road, G_ASPHALT, np.where(walk, G_SIDEWALK, G_PLOT)).astype(np.int8)
        tile = np.float32(_TILE_M)
        tx, ty = np.floor(x / tile), np.floor(y / tile)
        jx = np.minimum(x / tile - tx, tx + 1 - x / tile) * tile
        jy = np.minimum(y / tile - ty, ty + 1 - y / tile) * tile
        mat[walk & (np.minimum(jx, jy) < _JOINT_M) & (d > 0.3)] = G_JOINT
        kerb_d = np.minimum(np.where(dx < half, dx, np.inf), np.where(dy < half, dy, np.inf))
        mat[walk & (kerb_d < rh + _KERB_M)] = G_KERB
        # Markings: dashed centre lines, solid edge lines, zebra crossings before junctions.
        dash = np.float32(_DASH_M)
        line = np.float32(_LINE_HALF_WIDTH_M)
        centre_v = road_v & (dx < line) & ((np.abs(ly) % dash) < dash / 2)
        centre_h = road_h & (dy < line) & ((np.abs(lx) % dash) < dash / 2)
        edge_v = road_v & (np.abs(dx - (rh - 0.35)) < line)
        edge_h = road_h & (np.abs(dy - (rh - 0.35)) < line)
        zebra_v = road_v & (dy > rh + 0.6) & (dy < rh + 3.6) & ((dx % 1.0) < 0.5) & (dx < rh - 0.6)
        zebra_h = road_h & (dx > rh + 0.6) & (dx < rh + 3.6) & ((dy % 1.0) < 0.5) & (dy < rh - 0.6)
        mark = (centre_v | centre_h | edge_v | edge_h | zebra_v | zebra_h) & ~crossing
        mat[mark] = G_MARKING
        mat = mat.astype(np.int64)

        fine = hash01(self.seed, _H_ASPHALT, np.floor(x / 0.1), np.floor(y / 0.1)) - 0.5
        tiles = hash01(self.seed, _H_PATCH, tx, ty) - 0.5
        patch = self._value_noise(x / 4.0, y / 4.0, _H_PATCH) - 0.5
        factor = np.where(
            mat == G_ASPHALT,
            1.0 + d * 0.12 * fine + 0.25 * patch,
            np.where(
                (mat == G_SIDEWALK) | (mat == G_JOINT),
                1.0 + d * 0.15 * tiles,
                1.0 - 0.15 * d * (fine + 0.5),
            ),
        ).astype(np.float32)
        return _GROUND_COLOURS[mat] * factor[:, None]

    def _value_noise(self, x: np.ndarray, y: np.ndarray, channel: int) -> np.ndarray:
        """Smooth noise in [0, 1): bilinear blend of hashed lattice values."""
        ix, iy = np.floor(x), np.floor(y)
        fx, fy = x - ix, y - iy
        fx = fx * fx * (3 - 2 * fx)
        fy = fy * fy * (3 - 2 * fy)
        v00 = hash01(self.seed, channel, ix, iy)
        v10 = hash01(self.seed, channel, ix + 1, iy)
        v01 = hash01(self.seed, channel, ix, iy + 1)
        v11 = hash01(self.seed, channel, ix + 1, iy + 1)
        return (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy


def _box_segments(cx, cy, half_len, half_wid, angle):
    """Four outward-facing walls of a rectangle; returns p0 (4,2), p1 (4,2), normals (4,2)."""
    c, s = np.cos(angle), np.sin(angle)
    ax = np.array([c, s]) * half_len
    ay = np.array([-s, c]) * half_wid
    ctr = np.array([cx, cy])
    corners = np.array([ctr - ax - ay, ctr + ax - ay, ctr + ax + ay, ctr - ax + ay])
    # Counter-clockwise corners: walking p0 -> p1 the outside is on the right.
    p0 = corners
    p1 = np.roll(corners, -1, axis=0)
    e = p1 - p0
    n = np.stack([e[:, 1], -e[:, 0]], axis=1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return p0, p1, n


class _Builder:
    def __init__(self):
        self.p0, self.p1, self.h, self.sid, self.u0 = [], [], [], [], []
        self.kind: list[int] = []
        self.storeys: list[int] = []

    def surface(self, kind: int, storeys: int = 0) -> int:
        self.kind.append(kind)
        self.storeys.append(storeys)
        return len(self.kind) - 1

    def wall(self, a, b, normal, height, sid, u0=0.0):
        """Add wall a-b whose outside faces ``normal``; endpoints are ordered to suit."""
        a = np.asarray(a, float)
        b = np.asarray(b, float)
        e = b - a
        if e[1] * normal[0] - e[0] * normal[1] < 0:  # outward normal must be right of a->b
            a, b = b, a
        if np.linalg.norm(b - a) < 1e-6:
            return
        self.p0.append(a)
        self.p1.append(b)
        self.h.append(height)
        self.sid.append(sid)
        self.u0.append(u0)


def build_city(config: CityConfig, seed: int, cover_xy: np.ndarray | None = None) -> City:
    """Lay out the city for ``seed``. ``cover_xy`` (N, 2) widens the street grid to hold a path."""
    cfg = config
    p = cfg.pitch_m
    nx, ny = cfg.streets_x, cfg.streets_y
    ix0 = iy0 = 0
    if cover_xy is not None and len(cover_xy):
        lo = np.floor(cover_xy.min(axis=0) / p).astype(int)
        hi = np.ceil(cover_xy.max(axis=0) / p).astype(int)
        ix0, iy0 = int(lo[0]), int(lo[1])
        nx = max(nx, int(hi[0] - lo[0]) + 1)
        ny = max(ny, int(hi[1] - lo[1]) + 1)
    street_x = (ix0 + np.arange(nx)) * p
    street_y = (iy0 + np.arange(ny)) * p
    rng = np.random.default_rng([seed, 7301])
    B = _Builder()
    w2 = cfg.street_width_m / 2.0
    D = cfg.building_depth_m
    wmin, wmax = cfg.building_width_range_m

    ring = cfg.outer_ring_blocks
    for bi in range(-ring, nx - 1 + ring):
        for bj in range(-ring, ny - 1 + ring):
            bx0 = street_x[0] + bi * p + w2
            by0 = street_y[0] + bj * p + w2
            bx1, by1 = bx0 + cfg.block_size_m, by0 + cfg.block_size_m
            L = cfg.block_size_m
            # (plot corner, along unit, inward unit, span, index of the street it faces, axis)
            sides = [
                ((bx0, by0), (1, 0), (0, 1), (0.0, L), bj, "y"),
                ((bx1, by1), (-1, 0), (0, -1), (0.0, L), bj + 1, "y"),
                ((bx0, by1), (0, -1), (1, 0), (D, L - D), bi, "x"),
                ((bx1, by0), (0, 1), (-1, 0), (D, L - D), bi + 1, "x"),
            ]
            for a, e, m, (s0, s1), street_index, axis in sides:
                n_streets = nx if axis == "x" else ny
                if not (0 <= street_index < n_streets) or s1 - s0 < wmin * 0.5:
                    continue
                a, e, m = np.array(a, float), np.array(e, float), np.array(m, float)
                out = -m
                x = s0
                while x < s1 - 1e-6:
                    w = rng.uniform(wmin, wmax)
                    if s1 - (x + w) < wmin * 0.6:
                        w = s1 - x
                    sb = rng.uniform(*cfg.setback_range_m)
                    storeys = int(rng.integers(cfg.storeys_range[0], cfg.storeys_range[1] + 1))
                    sid = B.surface(FACADE, storeys)
                    fa, fb = a + e * x + m * sb, a + e * (x + w) + m * sb
                    height = -1.0  # filled in after the per-surface parameters are known
                    B.wall(fa, fb, out, height, sid, 0.0)
                    B.wall(fa, fa + m * D, -e, height, sid, w)
                    B.wall(fb, fb + m * D, e, height, sid, w + D)
                    x += w
                    if rng.random() < cfg.gap_probability:
                        g = rng.uniform(*cfg.gap_width_range_m)
                        if x + g < s1 - wmin * 0.6:
                            back = cfg.setback_range_m[1] + cfg.alley_depth_m
                            aid = B.surface(ALLEY)
                            B.wall(a + e * x + m * back, a + e * (x + g) + m * back, out, -2.0, aid)
                            x += g

    # Street furniture along the streets of the grid.
    furniture_sids = []
    rh = cfg.road_half_width_m
    clear = w2 + cfg.intersection_clearance_m
    car_l, car_w, car_h = cfg.car_size_m
    for axis, lines, cross in (("x", street_x, street_y), ("y", street_y, street_x)):
        lo = cross[0] - ring * p
        hi = cross[-1] + ring * p
        for c in lines:
            for side in (-1.0, 1.0):
                # Lamp posts behind the kerb.
                t = lo + rng.uniform(0, cfg.pole_spacing_m)
                while t < hi:
                    tt = t + rng.uniform(-cfg.pole_jitter_m, cfg.pole_jitter_m) * 0.5
                    if np.min(np.abs(cross - tt)) > w2 + 1.0:
                        off = side * (rh + cfg.pole_kerb_offset_m)
                        cx, cy = (c + off, tt) if axis == "x" else (tt, c + off)
                        sid = B.surface(POLE)
                        furniture_sids.append((sid, cfg.pole_height_m))
                        hs = cfg.pole_size_m / 2
                        for q0, q1, n in zip(*_box_segments(cx, cy, hs, hs, 0.0)):
                            B.wall(q0, q1, n, cfg.pole_height_m, sid)
                    t += cfg.pole_spacing_m
                # Parked cars along the kerb, clear of crossings.
                t = lo
                while t + cfg.car_slot_length_m < hi:
                    mid = t + cfg.car_slot_length_m / 2
                    away = np.min(np.abs(cross - mid)) > clear + car_l / 2
                    if away and rng.random() < cfg.parked_car_probability:
                        off = side * (rh - cfg.car_kerb_gap_m - car_w / 2)
                        jitter = rng.uniform(-0.5, 0.5)
                        cx, cy = (c + off, mid + jitter) if axis == "x" else (mid + jitter, c + off)
                        ang = np.pi / 2 if axis == "x" else 0.0
                        sid = B.surface(CAR)
                        furniture_sids.append((sid, car_h))
                        for q0, q1, n in zip(*_box_segments(cx, cy, car_l / 2, car_w / 2, ang)):
                            B.wall(q0, q1, n, car_h, sid)
                    t += cfg.car_slot_length_m

    kind = np.array(B.kind, dtype=np.int8)
    F = len(kind)
    params = _surface_params(cfg, seed, F)
    storeys = np.asarray(B.storeys, np.float32)
    top = params["ground_h"] + storeys * params["storey_h"] + cfg.parapet_m
    for sid, h in furniture_sids:
        top[sid] = h
    params["top"] = top.astype(np.float32)
    height = np.array(B.h, float)
    sids = np.array(B.sid, dtype=np.int64)
    # Walls of buildings take their building's height; alley walls two storeys.
    bld = height == -1.0
    height[bld] = top[sids[bld]]
    alley = height == -2.0
    height[alley] = cfg.ground_floor_height_range_m[1] + cfg.storey_height_range_m[1]
    params["top"][sids[alley]] = height[alley]
    p0 = np.array(B.p0, float)
    p1 = np.array(B.p1, float)
    e = p1 - p0
    normal = np.stack([e[:, 1], -e[:, 0]], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return City(
        config=cfg,
        seed=seed,
        p0=p0,
        p1=p1,
        height=height,
        surface=sids,
        u0=np.array(B.u0, float),
        normal=normal,
        kind=kind,
        params=params,
        street_x=street_x,
        street_y=street_y,
    )


def _surface_params(cfg: CityConfig, seed: int, F: int) -> dict[str, np.ndarray]:
    """Texture parameters of every surface, each a pure function of (seed, surface id)."""
    f = np.arange(F)

    def h(channel):
        return hash01(seed, channel, f)

    pal = np.asarray(cfg.facade_palette, np.float32)
    acc = np.asarray(cfg.accent_palette, np.float32)
    base = pal[(h(_H_PALETTE) * len(pal)).astype(int) % len(pal)]
    jitter = np.stack([h(_H_JITTER_R), h(_H_JITTER_G), h(_H_JITTER_B)], axis=1) - 0.5
    base = np.clip(base * (1.0 + 2.0 * cfg.colour_jitter * jitter), 0.0, 1.0)
    trim_light = h(_H_TRIM) < 0.5
    trim = np.where(trim_light[:, None], np.clip(base * 0.4 + 0.55, 0, 1), base * 0.45).astype(np.float32)
    accent = acc[(h(_H_ACCENT) * len(acc)).astype(int) % len(acc)]
    pitch = _lerp(cfg.window_spacing_range_m, h(_H_PITCH))
    sign_len = _lerp(cfg.sign_length_range_m, h(_H_SIGN_LEN))
    sign_u0 = _lerp(cfg.sign_offset_range_m, h(_H_SIGN_POS))
    base = base.astype(np.float32)
    metal = _METAL[None, :] * (0.9 + 0.2 * h(_H_GRAIN))[:, None]
    colours = np.zeros((F, N_MATERIALS, 3), np.float32)
    colours[:, M_WALL] = base
    colours[:, M_COURSE] = base * 0.75
    colours[:, M_CORNICE] = trim * 0.8
    colours[:, M_FRAME] = trim
    colours[:, M_GLASS] = _GLASS
    colours[:, M_MULLION] = trim
    colours[:, M_PLINTH] = base * 0.55
    colours[:, M_SHOP] = _GLASS * 1.2
    colours[:, M_SIGN] = accent
    colours[:, M_LETTER] = _WHITE
    colours[:, M_AWNING_A] = accent * 0.9
    colours[:, M_AWNING_B] = _WHITE * 0.9
    colours[:, M_DOOR] = accent * 0.35 + 0.05
    colours[:, M_DOOR_FRAME] = trim
    colours[:, M_POLE] = metal
    colours[:, M_LAMP] = _LAMP
    colours[:, M_CAR] = accent
    colours[:, M_CAR_GLASS] = _GLASS * 1.5
    colours[:, M_TYRE] = _TYRE
    colours[:, M_ALLEY] = _ALLEY
    return {
        "colours": colours,
        "base": base,
        "trim": trim,
        "accent": accent.astype(np.float32),
        "storey_h": _lerp(cfg.storey_height_range_m, h(_H_STOREY)),
        "ground_h": _lerp(cfg.ground_floor_height_range_m, h(_H_GROUND)),
        "pitch": pitch,
        "win_w": _lerp(cfg.window_width_fraction_range, h(_H_WIN_W)),
        "win_h": _lerp(cfg.window_height_fraction_range, h(_H_WIN_H)),
        "shop": h(_H_SHOP) < cfg.shop_probability,
        "sign": h(_H_SIGN) < cfg.sign_probability,
        "sign_u0": sign_u0,
        "sign_u1": sign_u0 + sign_len,
        "awning": h(_H_AWNING) < cfg.awning_probability,
        "door_u": _lerp(cfg.door_offset_range_m, h(_H_DOOR)),
    }
