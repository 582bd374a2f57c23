"""The simulated world: streets along the route, lined by procedurally textured objects.

Geometry is 2.5D: every obstacle is a set of vertical wall segments spanning world heights
[z0, z1] (building facades on sloping ground, alley back walls, lamp posts, tree trunks and
crowns, guard rails, parked cars). Each segment is oriented so that its outward normal lies
on the right of p0 -> p1; a ray d hits the front side iff cross(d, p1 - p0) < 0, which gives
back-face culling for free in the ray caster. Parked cars belong to kerb slots whose
occupancy is re-drawn over time, so two visits of a street see different cars.

Appearance is procedural and deterministic in (seed, surface id): ``City.wall_albedo`` maps
(surface id, u along the wall in metres, v height above the object's base) to linear RGB,
vectorised; ``City.ground_albedo`` does the same for world (x, y) on the ground, using the
distance to the street centre line (``GroundMap``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from frontend.simulation.config import CityConfig
from frontend.simulation.ground import GroundMap
from frontend.simulation.noise import hash01, hash_u32, value_noise

# Surface kinds.
FACADE, POLE, CAR, ALLEY, TRUNK, FOLIAGE, RAIL = 0, 1, 2, 3, 4, 5, 6

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
    _H_LEAF,
    _H_SLOT,
    _H_TERRAIN,
) = range(101, 128)

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
    M_WALL,
    M_COURSE,
    M_CORNICE,
    M_FRAME,
    M_GLASS,
    M_MULLION,
    M_PLINTH,
    M_SHOP,
    M_SIGN,
    M_LETTER,
    M_AWNING_A,
    M_AWNING_B,
    M_DOOR,
    M_DOOR_FRAME,
    M_POLE,
    M_LAMP,
    M_CAR,
    M_CAR_GLASS,
    M_TYRE,
    M_ALLEY,
    M_BARK,
    M_LEAF,
    M_RAIL,
) = range(23)
N_MATERIALS = 23
_GRAINY = np.zeros(N_MATERIALS, bool)
_GRAINY[[M_WALL, M_COURSE, M_CORNICE, M_PLINTH, M_ALLEY]] = True
_BARK = np.array([0.28, 0.20, 0.14], np.float32)
_LEAF = np.array([0.20, 0.38, 0.14], np.float32)
_GRASS = np.array([0.30, 0.42, 0.20], np.float32)
_RAIL = np.array([0.62, 0.64, 0.66], np.float32)
G_PLOT, G_ASPHALT, G_SIDEWALK, G_JOINT, G_KERB, G_MARKING, G_GRASS = range(7)
_GROUND_COLOURS = np.array(
    [_PLOT, _ASPHALT, _SIDEWALK, _SIDEWALK * 0.8, _SIDEWALK * 1.25, _MARKING, _GRASS], np.float32
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


def _lerp(lo_hi: tuple[float, float], t: np.ndarray) -> np.ndarray:
    return (lo_hi[0] + (lo_hi[1] - lo_hi[0]) * t).astype(np.float32)


@dataclass
class City:
    """Wall segments plus per-surface texture parameters; see module docstring."""

    config: CityConfig
    seed: int
    p0: np.ndarray  # (S, 2) float64
    p1: np.ndarray  # (S, 2)
    z0: np.ndarray  # (S,) world height of the bottom of each wall
    z1: np.ndarray  # (S,) world height of its top
    surface: np.ndarray  # (S,) int surface id
    u0: np.ndarray  # (S,) texture u at p0
    normal: np.ndarray  # (S, 2) outward unit normal
    slot: np.ndarray  # (S,) kerb slot of a parked car, -1 for what never moves
    kind: np.ndarray  # (F,) surface kind
    params: dict[str, np.ndarray]  # per-surface texture parameters, each (F,) or (F, 3)
    ground: GroundMap
    district_names: tuple[str, ...] = ()
    turnover_s: float = 45.0
    parked_probability: float = 0.3
    footprints: list[np.ndarray] = field(default_factory=list)  # closed outlines (K, 2) of buildings

    @property
    def n_segments(self) -> int:
        return len(self.p0)

    def slots_occupied(self, t: float) -> np.ndarray:
        """Which kerb slots hold a car at time t: each slot is re-drawn every turnover period,
        with its own phase, so a street driven again a minute later has other cars."""
        n = int(self.slot.max()) + 1 if len(self.slot) else 0
        if n == 0:
            return np.zeros(0, bool)
        ids = np.arange(n)
        phase = hash01(self.seed, _H_SLOT, ids, -1) * self.turnover_s
        epoch = np.floor((t + phase) / self.turnover_s)
        return hash01(self.seed, _H_SLOT, ids, epoch) < self.parked_probability

    def active_segments(self, t: float) -> np.ndarray:
        """Boolean mask of the walls present at time t (parked cars come and go)."""
        occupied = self.slots_occupied(t)
        return (self.slot < 0) | occupied[np.maximum(self.slot, 0)] if len(occupied) else self.slot < 0

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """Distance from each point (N, 2) to the nearest wall, negative inside a building."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        out = np.full(len(xy), np.inf)
        e = self.p1 - self.p0
        ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-12)
        for a in range(0, len(xy), 256):
            q = xy[a : a + 256]
            w = q[:, None, :] - self.p0[None]
            f = np.clip(np.einsum("qij,ij->qi", w, e) / ee, 0.0, 1.0)
            d = np.linalg.norm(w - e[None] * f[..., None], axis=2)
            out[a : a + 256] = d.min(axis=1)
        for outline in self.footprints:
            out[_inside(xy, outline)] *= -1.0
        return out

    # -- texture -----------------------------------------------------------------------------

    def wall_albedo(self, sid: np.ndarray, u: np.ndarray, v: np.ndarray, visit: int = 0, foliage_tint=(1.0, 1.0, 1.0)):
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
        mat = np.where(kind == ALLEY, M_ALLEY, mat)
        mat = np.where(kind == TRUNK, M_BARK, mat)
        mat = np.where(kind == FOLIAGE, M_LEAF, mat)
        mat = np.where(kind == RAIL, np.where((np.floor(v / 0.25) % 2) == 0, M_RAIL, M_POLE), mat).astype(np.int64)

        rgb = P["colours"][sid, mat]
        grain = hash01(self.seed, _H_GRAIN, sid, np.floor(u / _GRAIN_U_M), np.floor(v / _GRAIN_V_M))
        factor = np.where(_GRAINY[mat], 1.0 + _GRAIN_AMPLITUDE * (grain - 0.5), 1.0).astype(np.float32)
        rgb *= factor[:, None]
        leaf = mat == M_LEAF
        if leaf.any():
            # Leaves move and change between visits: the blotches are re-drawn per visit.
            blotch = hash01(self.seed, _H_LEAF, sid[leaf], np.floor(u[leaf] / 0.35), np.floor(v[leaf] / 0.35), visit)
            rgb[leaf] *= (0.55 + 0.7 * blotch)[:, None] * np.asarray(foliage_tint, np.float32)
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
        """Texture of the ground at world (x, y): asphalt with markings, kerbs, paved or grass
        verges, plots. ``detail`` in [0, 1] scales fine texture (1 near, 0 far), a cheap
        anti-aliasing."""
        cfg = self.config
        x = np.asarray(x, np.float32)
        y = np.asarray(y, np.float32)
        dist, along, district = self.ground.lookup(x, y)
        rh = np.float32(cfg.road_half_width_m)
        half = np.float32(cfg.street_width_m / 2.0)
        road = dist < rh
        paved = district <= 1  # dense and suburban streets have sidewalks
        walk = ~road & (dist < half) & paved
        d = np.ones(x.shape, np.float32) if detail is None else detail.astype(np.float32)
        mat = np.where(road, G_ASPHALT, np.where(walk, G_SIDEWALK, np.where(district == 0, G_PLOT, G_GRASS)))
        mat = mat.astype(np.int8)
        tile = np.float32(_TILE_M)
        tx, ty = np.floor(x / tile), np.floor(y / tile)
        jx = np.minimum(x / tile - tx, tx + 1 - x / tile) * tile
        jy = np.minimum(y / tile - ty, ty + 1 - y / tile) * tile
        mat[walk & (np.minimum(jx, jy) < _JOINT_M) & (d > 0.3)] = G_JOINT
        mat[walk & (dist < rh + _KERB_M)] = G_KERB
        # Markings: dashed centre line and solid edge lines along the street.
        dash = np.float32(_DASH_M)
        line = np.float32(_LINE_HALF_WIDTH_M)
        centre = road & (dist < line) & ((along % dash) < dash / 2)
        edge = road & (np.abs(dist - (rh - 0.35)) < line)
        mat[centre | edge] = G_MARKING
        mat = mat.astype(np.int64)

        fine = hash01(self.seed, _H_ASPHALT, np.floor(x / 0.1), np.floor(y / 0.1)) - 0.5
        tiles = hash01(self.seed, _H_PATCH, tx, ty) - 0.5
        patch = value_noise(self.seed, _H_PATCH, x / 4.0, y / 4.0) - 0.5
        factor = np.where(
            mat == G_ASPHALT,
            1.0 + d * 0.12 * fine + 0.25 * patch,
            np.where(
                (mat == G_SIDEWALK) | (mat == G_JOINT),
                1.0 + d * 0.15 * tiles,
                1.0 - 0.15 * d * (fine + 0.5) + 0.3 * patch * (mat == G_GRASS),
            ),
        ).astype(np.float32)
        return _GROUND_COLOURS[mat] * factor[:, None]

    def ground_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """World height of the ground at (x, y): the terrain of the nearest road plus the relief."""
        return self.ground.height_at(x, y) + self.ground_relief(x, y)

    def ground_relief(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the ground above the road surface at world (x, y): a crowned road, raised
        kerbs and verges, and undulating ground beyond the street. A perfectly flat world would
        give a scan matcher a floor that looks the same wherever it stands."""
        cfg = self.config
        dist, _, district = self.ground.lookup(x, y)
        rh = np.float32(cfg.road_half_width_m)
        half = np.float32(cfg.street_width_m / 2.0)
        z = np.where(dist < rh, -np.float32(cfg.road_camber) * dist, np.float32(cfg.kerb_height_m))
        rough = value_noise(self.seed, _H_TERRAIN, np.asarray(x) / 5.0, np.asarray(y) / 5.0) - np.float32(0.5)
        amplitude = np.where(district == 0, np.float32(0.1), np.float32(cfg.verge_relief_m))
        ramp = np.clip((dist - half) / np.float32(3.0), 0.0, 1.0)
        return (z + 2.0 * amplitude * rough * ramp).astype(np.float32)


def _inside(xy: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """Even-odd test of points (N, 2) against a closed polygon (K, 2)."""
    x, y = xy[:, 0:1], xy[:, 1:2]
    a, b = outline, np.roll(outline, -1, axis=0)
    crosses = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
    return (crosses & (x < xint)).sum(axis=1) % 2 == 1


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
    colours[:, M_BARK] = _BARK * (0.8 + 0.4 * h(_H_GRAIN))[:, None]
    colours[:, M_LEAF] = _LEAF * (0.75 + 0.5 * h(_H_JITTER_G))[:, None]
    colours[:, M_RAIL] = _RAIL
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
