"""Lay a city along a route: objects on both sides of the street centre line, by district.

Streets follow the driven path itself, so any route (a preset loop or a real vehicle's poses)
gets a world around it. The centre line is walked on both sides; every proposed object must
keep clear of the whole centre line (not only the stretch it was proposed from), which leaves
crossings open where the path meets itself and keeps corners and parallel roads free, and
must not overlap anything placed before, which lays each street once however often it is
driven. District kind is a smooth function of position: dense blocks, suburban houses with
hedges and trees, open fields and parkland (trees and poles only, where scan matching is
weakly constrained along the road) and highway stretches with guard rails.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from frontend.simulation.city import (
    ALLEY,
    CAR,
    FACADE,
    FOLIAGE,
    POLE,
    RAIL,
    TRUNK,
    City,
    _box_segments,
    _surface_params,
)
from frontend.simulation.config import CityConfig, TrafficConfig
from frontend.simulation.ground import GroundMap
from frontend.simulation.noise import hash01, value_noise

DISTRICTS = ("dense", "suburban", "open", "highway")
DENSE, SUBURBAN, OPEN, HIGHWAY = range(4)
_DISTRICT_CHANNEL = 977
_SAMPLE_M = 0.5  # spacing of the centre-line samples used for clearance and districts
_CELL_M = 1.0  # occupancy grid
_FENCE_CHANNEL = 983


class _Builder:
    """Collects walls and surfaces; an occupancy grid keeps objects from overlapping."""

    def __init__(self, tree: cKDTree, centre_z: np.ndarray) -> None:
        self.p0: list[np.ndarray] = []
        self.p1: list[np.ndarray] = []
        self.z0: list[float] = []
        self.z1: list[float] = []
        self.sid: list[int] = []
        self.u0: list[float] = []
        self.slot: list[int] = []
        self.kind: list[int] = []
        self.storeys: list[int] = []
        self.top: dict[int, float] = {}
        self.district: list[int] = []
        self.footprints: list[np.ndarray] = []
        self.n_slots = 0
        self.tree = tree
        self.centre_z = centre_z
        self.occupied: set[tuple[int, int]] = set()

    # -- checks ---------------------------------------------------------------------------------

    def clear_of_streets(self, pts: np.ndarray, distance: float) -> bool:
        d, _ = self.tree.query(pts, distance_upper_bound=distance)
        return bool(np.all(np.isinf(d)))

    def ground_z(self, pts: np.ndarray) -> float:
        _, i = self.tree.query(pts)
        return float(np.min(self.centre_z[np.atleast_1d(i)]))

    def _cells(self, pts: np.ndarray, dilate: int) -> set[tuple[int, int]]:
        c = np.floor(pts / _CELL_M).astype(int)
        if dilate:
            off = np.arange(-dilate, dilate + 1)
            ox, oy = np.meshgrid(off, off)
            c = (c[:, None, :] + np.column_stack([ox.ravel(), oy.ravel()])[None]).reshape(-1, 2)
        return set(map(tuple, c.tolist()))

    def claim(self, pts: np.ndarray, dilate: int = 0) -> bool:
        """Reserve the cells of ``pts`` unless any (dilated) is taken; True when reserved."""
        if self._cells(pts, dilate) & self.occupied:
            return False
        self.occupied |= self._cells(pts, 0)
        return True

    # -- geometry -------------------------------------------------------------------------------

    def surface(self, kind: int, district: int, storeys: int = 0, top: float | None = None) -> int:
        self.kind.append(kind)
        self.storeys.append(storeys)
        self.district.append(district)
        sid = len(self.kind) - 1
        if top is not None:
            self.top[sid] = top
        return sid

    def wall(self, a, b, normal, z0: float, z1: float, sid: int, u0: float = 0.0, slot: int = -1) -> None:
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
        self.z0.append(z0)
        self.z1.append(z1)
        self.sid.append(sid)
        self.u0.append(u0)
        self.slot.append(slot)

    def box(
        self, centre, half_len: float, half_wid: float, angle: float, z0: float, z1: float, sid: int, slot: int = -1
    ):
        for q0, q1, n in zip(*_box_segments(centre[0], centre[1], half_len, half_wid, angle)):
            self.wall(q0, q1, n, z0, z1, sid, slot=slot)


def _fill(quad: np.ndarray, step: float = 1.0) -> np.ndarray:
    """Points covering the quadrilateral (corners in order) at about ``step`` spacing."""
    a, b, c, d = quad
    n_u = max(2, int(math.ceil(np.linalg.norm(b - a) / step)) + 1)
    n_v = max(2, int(math.ceil(np.linalg.norm(d - a) / step)) + 1)
    u = np.linspace(0, 1, n_u)[:, None, None]
    v = np.linspace(0, 1, n_v)[None, :, None]
    pts = (1 - u) * (1 - v) * a + u * (1 - v) * b + u * v * c + (1 - u) * v * d
    return pts.reshape(-1, 2)


def district_codes(cfg: CityConfig, seed: int, centre_xy: np.ndarray) -> np.ndarray:
    """District of each centre-line point: smooth noise of position, cut at the quantiles that
    give each kind its configured share of the route."""
    names = [n for n in DISTRICTS if cfg.district_mix.get(n, 0.0) > 0]  # type: ignore[call-overload]
    shares = np.array([cfg.district_mix[n] for n in names], dtype=np.float64)  # type: ignore[index]
    w = cfg.district_scale_m
    noise = value_noise(seed, _DISTRICT_CHANNEL, centre_xy[:, 0] / w, centre_xy[:, 1] / w)
    cuts = np.quantile(noise, np.cumsum(shares / shares.sum())[:-1]) if len(names) > 1 else np.array([])
    idx = np.searchsorted(cuts, noise, side="right")
    return np.array([DISTRICTS.index(n) for n in names])[idx]


def build_city(config: CityConfig, seed: int, centre: np.ndarray, traffic: TrafficConfig | None = None) -> City:
    """Lay out the city for ``seed`` along the street centre line ``centre`` (M, 3): x, y, z."""
    cfg = config
    traffic = traffic or TrafficConfig()
    centre = np.asarray(centre, float)
    seg = np.linalg.norm(np.diff(centre[:, :2], axis=0), axis=1)
    s_full = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, s_full[-1] + 1e-9, _SAMPLE_M)
    c = np.column_stack([np.interp(s, s_full, centre[:, k]) for k in range(3)])
    xy, z = c[:, :2], c[:, 2]
    district = district_codes(cfg, seed, xy)
    tree = cKDTree(xy)
    B = _Builder(tree, z)
    rng = np.random.default_rng([seed, 7301])
    half = cfg.street_width_m / 2.0
    rh = cfg.road_half_width_m

    def at(a: float) -> np.ndarray:
        return np.array([np.interp(a, s, xy[:, 0]), np.interp(a, s, xy[:, 1])])

    def frame(a0: float, a1: float, side: float):
        p0, p1 = at(a0), at(a1)
        e = p1 - p0
        n = float(np.linalg.norm(e))
        if n < 1e-6:
            return None
        e /= n
        m = side * np.array([-e[1], e[0]])  # away from the road, on this side
        return p0, p1, e, m, n

    length = float(s[-1])
    for side in (-1.0, 1.0):
        _lay_side(cfg, B, rng, s, district, length, side, half, rh, at, frame)
    _lay_furniture(cfg, B, rng, s, district, length, half, rh, frame, seed)

    kind = np.array(B.kind, dtype=np.int8)
    F = len(kind)
    params = _surface_params(cfg, seed, F)
    storeys = np.asarray(B.storeys, np.float32)
    top = params["ground_h"] + storeys * params["storey_h"] + cfg.parapet_m
    for sid, h in B.top.items():
        top[sid] = h
    params["top"] = top.astype(np.float32)
    sd = np.asarray(B.district)
    houses = (sd == SUBURBAN) & (kind == FACADE)
    for key in ("shop", "sign", "awning"):
        params[key] = params[key] & ~houses
    sids = np.array(B.sid, dtype=np.int64)
    z0 = np.array(B.z0, float)
    z1 = np.array(B.z1, float)
    building = z1 < z0  # placeholder: building walls take their surface's height
    z1[building] = z0[building] + top[sids[building]]
    params["base_z"] = np.zeros(F, np.float32)
    params["base_z"][sids] = z0.astype(np.float32)
    p0 = np.array(B.p0, float).reshape(-1, 2)
    p1 = np.array(B.p1, float).reshape(-1, 2)
    e = p1 - p0
    normal = np.stack([e[:, 1], -e[:, 0]], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    ground = GroundMap.build(xy, s, district.astype(np.int8), z)
    return City(
        config=cfg,
        seed=seed,
        p0=p0,
        p1=p1,
        z0=z0,
        z1=z1,
        surface=sids,
        u0=np.array(B.u0, float),
        normal=normal,
        slot=np.array(B.slot, dtype=np.int64),
        kind=kind,
        params=params,
        ground=ground,
        district_names=DISTRICTS,
        turnover_s=traffic.parked_car_turnover_s,
        parked_probability=cfg.parked_car_probability,
        footprints=B.footprints,
    )


def _lay_side(cfg: CityConfig, B: _Builder, rng, s, district, length, side, half, rh, at, frame) -> None:
    """Buildings, houses, hedges and trees on one side of the street, walking its centre line."""
    a = 0.0
    D = cfg.building_depth_m
    while a < length - 2.0:
        d = int(district[min(int(a / _SAMPLE_M), len(district) - 1)])
        if d in (DENSE, SUBURBAN):
            lo, hi = cfg.building_width_range_m if d == DENSE else cfg.house_width_range_m
            w = rng.uniform(lo, hi)
            sb = rng.uniform(*(cfg.setback_range_m if d == DENSE else cfg.house_setback_range_m))
            f = frame(a, min(a + w, length), side)
            if f is None or f[4] < 0.8 * w:
                a += 2.0
                continue
            p0, p1, e, m, n = f
            front0, front1 = p0 + m * (half + sb), p1 + m * (half + sb)
            quad = np.array([front0, front1, front1 + m * D, front0 + m * D])
            pts = _fill(quad)
            if not B.clear_of_streets(pts, half - 0.05) or not B.claim(pts):
                a += 2.0
                continue
            storeys_range = cfg.storeys_range if d == DENSE else cfg.house_storeys_range
            storeys = int(rng.integers(storeys_range[0], storeys_range[1] + 1))
            sid = B.surface(FACADE, d, storeys)
            base = B.ground_z(quad) - 0.2
            _facade(cfg, B, rng, quad[0], e, m, n, base, sid)
            for q0, q1, nrm, u0 in (
                (quad[0], quad[3], -e, n),
                (quad[1], quad[2], e, n + D),
                (quad[3], quad[2], m, 0.0),
            ):
                B.wall(q0, q1, nrm, base, base - 1.0, sid, u0)  # z1 < z0: filled from the surface
            B.footprints.append(quad)
            if d == SUBURBAN and rng.random() < cfg.hedge_probability and sb > 1.8:
                _hedge(cfg, B, rng, p0, p1, e, m, half + 0.3, d)
            a += n
            if rng.random() < cfg.side_street_probability:
                a += rng.uniform(*cfg.side_street_width_range_m)
            elif rng.random() < (cfg.gap_probability if d == DENSE else cfg.house_gap_probability):
                g = rng.uniform(*cfg.gap_width_range_m) * (1.0 if d == DENSE else 2.0)
                if d == DENSE:
                    _alley(cfg, B, a, min(a + g, length), side, half, frame)
                else:
                    _tree(cfg, B, rng, at(a + g / 2) + m * (half + rng.uniform(2.0, 5.0)), d)
                a += g
        else:
            a += rng.uniform(*cfg.tree_spacing_range_m) * (1.0 if d == OPEN else 1.5)
            if rng.random() < (0.7 if d == OPEN else 0.4):
                f = frame(max(a - 1.0, 0.0), min(a + 1.0, length), side)
                if f is not None:
                    offset = rh + (rng.uniform(2.5, 12.0) if d == OPEN else rng.uniform(6.0, 20.0))
                    _tree(cfg, B, rng, f[0] + f[3] * offset, d)


def _facade(cfg: CityConfig, B: _Builder, rng, front0, e, m, width: float, base: float, sid: int) -> None:
    """The street front of a building, in bays: piers flush with the plot line and recessed bays
    between them (real facades have depth; a flat one would leave a LiDAR nothing along the
    street to hold on to). An odd number of bays keeps both ends flush with the side walls."""
    relief = rng.uniform(*cfg.facade_relief_depth_range_m) if rng.random() < cfg.facade_relief_probability else 0.0
    n_bays = int(width / rng.uniform(*cfg.facade_bay_width_range_m)) | 1
    if relief == 0.0 or n_bays < 3:
        B.wall(front0, front0 + e * width, -m, base, base - 1.0, sid, 0.0)
        return
    edges = np.linspace(0.0, width, n_bays + 1)
    depth = np.where(np.arange(n_bays) % 2 == 1, relief, 0.0)
    for i in range(n_bays):
        a, b = front0 + e * edges[i] + m * depth[i], front0 + e * edges[i + 1] + m * depth[i]
        B.wall(a, b, -m, base, base - 1.0, sid, float(edges[i]))
        if i + 1 < n_bays:  # the step between this bay and the next faces into the recess
            at = front0 + e * edges[i + 1]
            facing = -e if depth[i] > depth[i + 1] else e
            B.wall(at + m * depth[i], at + m * depth[i + 1], facing, base, base - 1.0, sid, float(edges[i + 1]))


def _alley(cfg: CityConfig, B: _Builder, a0, a1, side, half, frame) -> None:
    f = frame(a0, a1, side)
    if f is None:
        return
    p0, p1, e, m, _ = f
    back = half + cfg.setback_range_m[1] + cfg.alley_depth_m
    q0, q1 = p0 + m * back, p1 + m * back
    if not B.clear_of_streets(np.array([q0, q1]), half) or not B.claim(np.array([q0, q1])):
        return
    aid = B.surface(ALLEY, DENSE, top=cfg.ground_floor_height_range_m[1] + cfg.storey_height_range_m[1])
    base = B.ground_z(np.array([q0, q1])) - 0.2
    B.wall(q0, q1, -m, base, base + cfg.ground_floor_height_range_m[1] + cfg.storey_height_range_m[1], aid)


def _hedge(cfg: CityConfig, B: _Builder, rng, p0, p1, e, m, offset, d) -> None:
    """A front-garden hedge with a gap for the drive: porous to LiDAR, leafy to the camera."""
    width = float(np.linalg.norm(p1 - p0))
    gap0 = rng.uniform(0.2, 0.6) * width
    height = rng.uniform(1.1, 1.8)
    for u0, u1 in ((0.0, gap0), (gap0 + 3.0, width)):
        if u1 - u0 < 1.0:
            continue
        a, b = p0 + e * u0 + m * offset, p0 + e * u1 + m * offset
        centre = (a + b) / 2 + m * 0.4
        pts = np.array([a, b, a + m * 0.8, b + m * 0.8])
        if not B.clear_of_streets(pts, offset - 0.2):
            continue
        sid = B.surface(FOLIAGE, d, top=height)
        base = B.ground_z(pts)
        B.box(centre, (u1 - u0) / 2, 0.4, math.atan2(e[1], e[0]), base, base + height, sid)


def _tree(cfg: CityConfig, B: _Builder, rng, pos: np.ndarray, d: int) -> None:
    """Trunk and crown; the crown is a porous box that starts above head height."""
    crown = rng.uniform(*cfg.tree_crown_size_range_m) / 2
    height = rng.uniform(*cfg.tree_height_range_m)
    corners = pos + crown * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    if not B.clear_of_streets(np.vstack([corners, pos[None]]), cfg.road_half_width_m + 0.8):
        return
    if not B.claim(_fill(corners[[0, 1, 2, 3]], 1.0)):
        return
    base = B.ground_z(pos[None])
    angle = rng.uniform(0, math.pi / 2)
    trunk = B.surface(TRUNK, d, top=height)
    B.box(pos, 0.2, 0.2, angle, base, base + min(2.6, height), trunk)
    leaves = B.surface(FOLIAGE, d, top=height)
    B.box(pos, crown, crown, angle, base + min(2.4, height * 0.4), base + height, leaves)


def _lay_furniture(cfg: CityConfig, B: _Builder, rng, s, district, length, half, rh, frame, seed: int) -> None:
    """Lamp posts, guard rails and parked-car slots along both kerbs."""
    car_l, car_w, car_h = cfg.car_size_m
    for side in (-1.0, 1.0):
        # Poles: closer in town, sparse on open roads.
        a = rng.uniform(0, cfg.pole_spacing_m)
        while a < length:
            d = int(district[min(int(a / _SAMPLE_M), len(district) - 1)])
            f = frame(max(a - 0.5, 0.0), min(a + 0.5, length), side)
            if f is not None:
                pos = f[0] + f[3] * (rh + cfg.pole_kerb_offset_m)
                hs = cfg.pole_size_m / 2
                if B.clear_of_streets(pos[None], rh + cfg.pole_kerb_offset_m - 0.3) and B.claim(pos[None], dilate=4):
                    sid = B.surface(POLE, d, top=cfg.pole_height_m)
                    base = B.ground_z(pos[None])
                    B.box(pos, hs, hs, 0.0, base, base + cfg.pole_height_m, sid)
            spacing = cfg.pole_spacing_m * (1.0 if d in (DENSE, SUBURBAN) else 2.2)
            a += spacing + rng.uniform(-cfg.pole_jitter_m, cfg.pole_jitter_m) * 0.5
        # Guard rails on highway stretches, in 4 m panels on posts; fences along fields and parks.
        a = 0.0
        while a < length - 4.0:
            d = int(district[min(int(a / _SAMPLE_M), len(district) - 1)])
            if d == HIGHWAY:
                f = frame(a, a + 4.0, side)
                if f is not None:
                    p0, p1, e, m, _ = f
                    q0, q1 = p0 + m * (rh + 0.8), p1 + m * (rh + 0.8)
                    mid = (q0 + q1) / 2
                    if B.clear_of_streets(np.array([q0, q1, mid]), rh + 0.5) and B.claim(
                        np.array([q0, mid, q1]), dilate=1
                    ):
                        sid = B.surface(RAIL, d, top=cfg.guard_rail_height_m)
                        base = B.ground_z(np.array([q0, q1]))
                        B.wall(q0, q1, -m, base + 0.3, base + cfg.guard_rail_height_m, sid)
                        post = B.surface(POLE, d, top=cfg.guard_rail_height_m)  # the rail's post, behind it
                        B.box(q0 + m * 0.25, 0.08, 0.08, 0.0, base, base + cfg.guard_rail_height_m, post)
            elif d == OPEN:  # field and park fences: posts every few metres along the verge
                f = frame(a, a + 4.0, side)
                if f is not None:
                    p0, _, e, m, _ = f
                    offset = rh + 3.0 + 3.0 * (hash01(seed, _FENCE_CHANNEL, int(a // 200), int(side)))
                    pos = p0 + m * offset
                    if B.clear_of_streets(pos[None], offset - 0.5) and B.claim(pos[None], dilate=1):
                        sid = B.surface(POLE, d, top=1.3)
                        base = B.ground_z(pos[None])
                        B.box(pos, 0.07, 0.07, 0.0, base, base + 1.3, sid)
            a += 4.0
        # Parked-car slots along town kerbs; occupancy changes over time (City.slots_occupied).
        a = 0.0
        while a + cfg.car_slot_length_m < length:
            d = int(district[min(int(a / _SAMPLE_M), len(district) - 1)])
            if d in (DENSE, SUBURBAN):
                f = frame(a, a + cfg.car_slot_length_m, side)
                if f is not None:
                    p0, p1, e, m, _ = f
                    off = rh - cfg.car_kerb_gap_m - car_w / 2
                    centre = (p0 + p1) / 2 + m * off
                    angle = math.atan2(e[1], e[0])
                    corners = centre + np.array(
                        [e * sx * car_l / 2 + m * sy * car_w / 2 for sx in (-1, 1) for sy in (-1, 1)]
                    )
                    clear = off - car_w / 2 - 0.05
                    if B.clear_of_streets(corners, clear) and B.clear_of_streets(centre[None], off - 0.3):
                        if B.claim(np.vstack([corners, centre[None]]), dilate=1):
                            slot = B.n_slots
                            B.n_slots += 1
                            sid = B.surface(CAR, d, top=car_h)
                            base = B.ground_z(centre[None])
                            B.box(centre, car_l / 2, car_w / 2, angle, base, base + car_h, sid, slot=slot)
            a += cfg.car_slot_length_m
