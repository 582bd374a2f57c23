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
from dataclasses import dataclass

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
        dist, _ = self.tree.query(pts, distance_upper_bound=distance)
        return bool(np.all(np.isinf(dist)))

    def ground_z(self, pts: np.ndarray) -> float:
        _, i = self.tree.query(pts)
        return float(np.min(self.centre_z[np.atleast_1d(i)]))

    def _cells(self, pts: np.ndarray, dilate: int) -> set[tuple[int, int]]:
        cells = np.floor(pts / _CELL_M).astype(int)
        if dilate:
            off = np.arange(-dilate, dilate + 1)
            ox, oy = np.meshgrid(off, off)
            cells = (cells[:, None, :] + np.column_stack([ox.ravel(), oy.ravel()])[None]).reshape(-1, 2)
        return set(map(tuple, cells.tolist()))

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
        edge = b - a
        if edge[1] * normal[0] - edge[0] * normal[1] < 0:  # outward normal must be right of a->b
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
        for q0, q1, normal in zip(*_box_segments(centre[0], centre[1], half_len, half_wid, angle)):
            self.wall(q0, q1, normal, z0, z1, sid, slot=slot)


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
    scale = cfg.district_scale_m
    noise = value_noise(seed, _DISTRICT_CHANNEL, centre_xy[:, 0] / scale, centre_xy[:, 1] / scale)
    cuts = np.quantile(noise, np.cumsum(shares / shares.sum())[:-1]) if len(names) > 1 else np.array([])
    idx = np.searchsorted(cuts, noise, side="right")
    return np.array([DISTRICTS.index(n) for n in names])[idx]


@dataclass(frozen=True)
class _Stretch:
    """A straight piece of one side of the street: objects are placed off its start along
    ``outward``, so the same frame serves buildings, hedges, poles, rails and parked cars."""

    start: np.ndarray  # centre-line point at the first arc length
    end: np.ndarray  # centre-line point at the second
    along: np.ndarray  # unit direction start -> end
    outward: np.ndarray  # unit normal away from the road, on the chosen side
    length: float  # straight-line distance start -> end


@dataclass(frozen=True, eq=False)
class _Street:
    """The resampled centre line being walked, with what every placement on it needs; one value
    instead of a dozen positional arguments threaded through the layout helpers."""

    arc_m: np.ndarray  # (N,) arc length of each centre-line sample, _SAMPLE_M apart
    xy: np.ndarray  # (N, 2) the samples themselves
    districts: np.ndarray  # (N,) district code of each sample
    half_width: float  # half the street width: building plots start this far from the centre line
    road_half_width: float  # half the carriageway: kerb furniture and verge trees start here

    @property
    def length(self) -> float:
        return float(self.arc_m[-1])

    def district_at(self, arc: float) -> int:
        return int(self.districts[min(int(arc / _SAMPLE_M), len(self.districts) - 1)])

    def point_at(self, arc: float) -> np.ndarray:
        return np.array([np.interp(arc, self.arc_m, self.xy[:, 0]), np.interp(arc, self.arc_m, self.xy[:, 1])])

    def stretch(self, arc0: float, arc1: float, side: float) -> _Stretch | None:
        """The chord between two arc lengths on ``side`` (-1 or 1); None where it is too short
        to give a direction."""
        start, end = self.point_at(arc0), self.point_at(arc1)
        along = end - start
        length = float(np.linalg.norm(along))
        if length < 1e-6:
            return None
        along /= length
        outward = side * np.array([-along[1], along[0]])
        return _Stretch(start, end, along, outward, length)


def build_city(config: CityConfig, seed: int, centre: np.ndarray, traffic: TrafficConfig | None = None) -> City:
    """Lay out the city for ``seed`` along the street centre line ``centre`` (M, 3): x, y, z."""
    cfg = config
    traffic = traffic or TrafficConfig()
    centre = np.asarray(centre, float)
    seg_len = np.linalg.norm(np.diff(centre[:, :2], axis=0), axis=1)
    vertex_arc_m = np.concatenate([[0.0], np.cumsum(seg_len)])
    # Resample at a fixed spacing so clearance and district lookups do not depend on how densely
    # the route was given.
    arc_m = np.arange(0.0, vertex_arc_m[-1] + 1e-9, _SAMPLE_M)
    samples = np.column_stack([np.interp(arc_m, vertex_arc_m, centre[:, k]) for k in range(3)])
    xy, road_z = samples[:, :2], samples[:, 2]
    district = district_codes(cfg, seed, xy)
    builder = _Builder(cKDTree(xy), road_z)
    rng = np.random.default_rng([seed, 7301])
    street = _Street(
        arc_m=arc_m,
        xy=xy,
        districts=district,
        half_width=cfg.street_width_m / 2.0,
        road_half_width=cfg.road_half_width_m,
    )
    for side in (-1.0, 1.0):
        _lay_side(cfg, builder, rng, street, side)
    _lay_furniture(cfg, builder, rng, street, seed)

    kind = np.array(builder.kind, dtype=np.int8)
    n_surfaces = len(kind)
    params = _surface_params(cfg, seed, n_surfaces)
    storeys = np.asarray(builder.storeys, np.float32)
    top = params["ground_h"] + storeys * params["storey_h"] + cfg.parapet_m
    for sid, height in builder.top.items():
        top[sid] = height
    params["top"] = top.astype(np.float32)
    surface_district = np.asarray(builder.district)
    houses = (surface_district == SUBURBAN) & (kind == FACADE)
    for key in ("shop", "sign", "awning"):
        params[key] = params[key] & ~houses
    wall_sid = np.array(builder.sid, dtype=np.int64)
    z0 = np.array(builder.z0, float)
    z1 = np.array(builder.z1, float)
    building = z1 < z0  # placeholder: building walls take their surface's height
    z1[building] = z0[building] + top[wall_sid[building]]
    params["base_z"] = np.zeros(n_surfaces, np.float32)
    params["base_z"][wall_sid] = z0.astype(np.float32)
    p0 = np.array(builder.p0, float).reshape(-1, 2)
    p1 = np.array(builder.p1, float).reshape(-1, 2)
    edge = p1 - p0
    normal = np.stack([edge[:, 1], -edge[:, 0]], axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    ground = GroundMap.build(xy, arc_m, district.astype(np.int8), road_z)
    return City(
        config=cfg,
        seed=seed,
        p0=p0,
        p1=p1,
        z0=z0,
        z1=z1,
        surface=wall_sid,
        u0=np.array(builder.u0, float),
        normal=normal,
        slot=np.array(builder.slot, dtype=np.int64),
        kind=kind,
        params=params,
        ground=ground,
        district_names=DISTRICTS,
        turnover_s=traffic.parked_car_turnover_s,
        parked_probability=cfg.parked_car_probability,
        footprints=builder.footprints,
    )


def _lay_side(cfg: CityConfig, builder: _Builder, rng: np.random.Generator, street: _Street, side: float) -> None:
    """Buildings, houses, hedges and trees on one side of the street, walking its centre line."""
    arc = 0.0
    length = street.length
    half_width = street.half_width
    depth = cfg.building_depth_m
    while arc < length - 2.0:
        district = street.district_at(arc)
        if district in (DENSE, SUBURBAN):
            lo, hi = cfg.building_width_range_m if district == DENSE else cfg.house_width_range_m
            width = rng.uniform(lo, hi)
            setback = rng.uniform(*(cfg.setback_range_m if district == DENSE else cfg.house_setback_range_m))
            plot = street.stretch(arc, min(arc + width, length), side)
            if plot is None or plot.length < 0.8 * width:  # a bend too tight for this plot
                arc += 2.0
                continue
            along, outward, frontage = plot.along, plot.outward, plot.length
            front0 = plot.start + outward * (half_width + setback)
            front1 = plot.end + outward * (half_width + setback)
            quad = np.array([front0, front1, front1 + outward * depth, front0 + outward * depth])
            pts = _fill(quad)
            if not builder.clear_of_streets(pts, half_width - 0.05) or not builder.claim(pts):
                arc += 2.0
                continue
            storeys_range = cfg.storeys_range if district == DENSE else cfg.house_storeys_range
            storeys = int(rng.integers(storeys_range[0], storeys_range[1] + 1))
            sid = builder.surface(FACADE, district, storeys)
            base = builder.ground_z(quad) - 0.2
            _facade(cfg, builder, rng, quad[0], plot, base, sid)
            for q0, q1, wall_normal, u0 in (
                (quad[0], quad[3], -along, frontage),
                (quad[1], quad[2], along, frontage + depth),
                (quad[3], quad[2], outward, 0.0),
            ):
                builder.wall(q0, q1, wall_normal, base, base - 1.0, sid, u0)  # z1 < z0: filled from the surface
            builder.footprints.append(quad)
            if district == SUBURBAN and rng.random() < cfg.hedge_probability and setback > 1.8:
                _hedge(builder, rng, plot, half_width + 0.3, district)
            arc += frontage
            if rng.random() < cfg.side_street_probability:
                arc += rng.uniform(*cfg.side_street_width_range_m)
            elif rng.random() < (cfg.gap_probability if district == DENSE else cfg.house_gap_probability):
                gap = rng.uniform(*cfg.gap_width_range_m) * (1.0 if district == DENSE else 2.0)
                if district == DENSE:
                    _alley(cfg, builder, street, arc, min(arc + gap, length), side)
                else:
                    garden = street.point_at(arc + gap / 2) + outward * (half_width + rng.uniform(2.0, 5.0))
                    _tree(cfg, builder, rng, garden, district)
                arc += gap
        else:
            arc += rng.uniform(*cfg.tree_spacing_range_m) * (1.0 if district == OPEN else 1.5)
            if rng.random() < (0.7 if district == OPEN else 0.4):
                verge = street.stretch(max(arc - 1.0, 0.0), min(arc + 1.0, length), side)
                if verge is not None:
                    spread = rng.uniform(2.5, 12.0) if district == OPEN else rng.uniform(6.0, 20.0)
                    offset = street.road_half_width + spread
                    _tree(cfg, builder, rng, verge.start + verge.outward * offset, district)


def _facade(
    cfg: CityConfig,
    builder: _Builder,
    rng: np.random.Generator,
    front0: np.ndarray,
    plot: _Stretch,
    base: float,
    sid: int,
) -> None:
    """The street front of a building, in bays: piers flush with the plot line and recessed bays
    between them (real facades have depth; a flat one would leave a LiDAR nothing along the
    street to hold on to). An odd number of bays keeps both ends flush with the side walls."""
    along, outward, width = plot.along, plot.outward, plot.length
    relief = rng.uniform(*cfg.facade_relief_depth_range_m) if rng.random() < cfg.facade_relief_probability else 0.0
    n_bays = int(width / rng.uniform(*cfg.facade_bay_width_range_m)) | 1
    if relief == 0.0 or n_bays < 3:
        builder.wall(front0, front0 + along * width, -outward, base, base - 1.0, sid, 0.0)
        return
    edges = np.linspace(0.0, width, n_bays + 1)
    recess = np.where(np.arange(n_bays) % 2 == 1, relief, 0.0)
    for i in range(n_bays):
        a = front0 + along * edges[i] + outward * recess[i]
        b = front0 + along * edges[i + 1] + outward * recess[i]
        builder.wall(a, b, -outward, base, base - 1.0, sid, float(edges[i]))
        if i + 1 < n_bays:  # the step between this bay and the next faces into the recess
            step = front0 + along * edges[i + 1]
            facing = -along if recess[i] > recess[i + 1] else along
            builder.wall(
                step + outward * recess[i],
                step + outward * recess[i + 1],
                facing,
                base,
                base - 1.0,
                sid,
                float(edges[i + 1]),
            )


def _alley(cfg: CityConfig, builder: _Builder, street: _Street, arc0: float, arc1: float, side: float) -> None:
    """The back wall seen through a gap between dense blocks, so a gap is not an open view."""
    gap = street.stretch(arc0, arc1, side)
    if gap is None:
        return
    back = street.half_width + cfg.setback_range_m[1] + cfg.alley_depth_m
    q0, q1 = gap.start + gap.outward * back, gap.end + gap.outward * back
    if not builder.clear_of_streets(np.array([q0, q1]), street.half_width) or not builder.claim(np.array([q0, q1])):
        return
    ground_floor, storey = cfg.ground_floor_height_range_m[1], cfg.storey_height_range_m[1]
    aid = builder.surface(ALLEY, DENSE, top=ground_floor + storey)
    base = builder.ground_z(np.array([q0, q1])) - 0.2
    builder.wall(q0, q1, -gap.outward, base, base + ground_floor + storey, aid)


def _hedge(builder: _Builder, rng: np.random.Generator, plot: _Stretch, offset: float, district: int) -> None:
    """A front-garden hedge with a gap for the drive: porous to LiDAR, leafy to the camera."""
    start, along, outward = plot.start, plot.along, plot.outward
    width = float(np.linalg.norm(plot.end - start))
    gap0 = rng.uniform(0.2, 0.6) * width
    height = rng.uniform(1.1, 1.8)
    for u0, u1 in ((0.0, gap0), (gap0 + 3.0, width)):
        if u1 - u0 < 1.0:
            continue
        a, b = start + along * u0 + outward * offset, start + along * u1 + outward * offset
        centre = (a + b) / 2 + outward * 0.4
        pts = np.array([a, b, a + outward * 0.8, b + outward * 0.8])
        if not builder.clear_of_streets(pts, offset - 0.2):
            continue
        sid = builder.surface(FOLIAGE, district, top=height)
        base = builder.ground_z(pts)
        builder.box(centre, (u1 - u0) / 2, 0.4, math.atan2(along[1], along[0]), base, base + height, sid)


def _tree(cfg: CityConfig, builder: _Builder, rng: np.random.Generator, pos: np.ndarray, district: int) -> None:
    """Trunk and crown; the crown is a porous box that starts above head height."""
    crown = rng.uniform(*cfg.tree_crown_size_range_m) / 2
    height = rng.uniform(*cfg.tree_height_range_m)
    corners = pos + crown * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    if not builder.clear_of_streets(np.vstack([corners, pos[None]]), cfg.road_half_width_m + 0.8):
        return
    if not builder.claim(_fill(corners[[0, 1, 2, 3]], 1.0)):
        return
    base = builder.ground_z(pos[None])
    angle = rng.uniform(0, math.pi / 2)
    trunk = builder.surface(TRUNK, district, top=height)
    builder.box(pos, 0.2, 0.2, angle, base, base + min(2.6, height), trunk)
    leaves = builder.surface(FOLIAGE, district, top=height)
    builder.box(pos, crown, crown, angle, base + min(2.4, height * 0.4), base + height, leaves)


def _lay_furniture(cfg: CityConfig, builder: _Builder, rng: np.random.Generator, street: _Street, seed: int) -> None:
    """Lamp posts, guard rails and parked-car slots along both kerbs."""
    car_length, car_width, car_height = cfg.car_size_m
    length = street.length
    road_half_width = street.road_half_width
    for side in (-1.0, 1.0):
        # Poles: closer in town, sparse on open roads.
        arc = rng.uniform(0, cfg.pole_spacing_m)
        while arc < length:
            district = street.district_at(arc)
            kerb = street.stretch(max(arc - 0.5, 0.0), min(arc + 0.5, length), side)
            if kerb is not None:
                pos = kerb.start + kerb.outward * (road_half_width + cfg.pole_kerb_offset_m)
                pole_half = cfg.pole_size_m / 2
                if builder.clear_of_streets(
                    pos[None], road_half_width + cfg.pole_kerb_offset_m - 0.3
                ) and builder.claim(pos[None], dilate=4):
                    sid = builder.surface(POLE, district, top=cfg.pole_height_m)
                    base = builder.ground_z(pos[None])
                    builder.box(pos, pole_half, pole_half, 0.0, base, base + cfg.pole_height_m, sid)
            spacing = cfg.pole_spacing_m * (1.0 if district in (DENSE, SUBURBAN) else 2.2)
            arc += spacing + rng.uniform(-cfg.pole_jitter_m, cfg.pole_jitter_m) * 0.5
        # Guard rails on highway stretches, in 4 m panels on posts; fences along fields and parks.
        arc = 0.0
        while arc < length - 4.0:
            district = street.district_at(arc)
            if district == HIGHWAY:
                panel = street.stretch(arc, arc + 4.0, side)
                if panel is not None:
                    outward = panel.outward
                    q0 = panel.start + outward * (road_half_width + 0.8)
                    q1 = panel.end + outward * (road_half_width + 0.8)
                    mid = (q0 + q1) / 2
                    if builder.clear_of_streets(np.array([q0, q1, mid]), road_half_width + 0.5) and builder.claim(
                        np.array([q0, mid, q1]), dilate=1
                    ):
                        sid = builder.surface(RAIL, district, top=cfg.guard_rail_height_m)
                        base = builder.ground_z(np.array([q0, q1]))
                        builder.wall(q0, q1, -outward, base + 0.3, base + cfg.guard_rail_height_m, sid)
                        post = builder.surface(
                            POLE, district, top=cfg.guard_rail_height_m
                        )  # the rail's post, behind it
                        builder.box(q0 + outward * 0.25, 0.08, 0.08, 0.0, base, base + cfg.guard_rail_height_m, post)
            elif district == OPEN:  # field and park fences: posts every few metres along the verge
                panel = street.stretch(arc, arc + 4.0, side)
                if panel is not None:
                    offset = road_half_width + 3.0 + 3.0 * (hash01(seed, _FENCE_CHANNEL, int(arc // 200), int(side)))
                    pos = panel.start + panel.outward * offset
                    if builder.clear_of_streets(pos[None], float(offset - 0.5)) and builder.claim(pos[None], dilate=1):
                        sid = builder.surface(POLE, district, top=1.3)
                        base = builder.ground_z(pos[None])
                        builder.box(pos, 0.07, 0.07, 0.0, base, base + 1.3, sid)
            arc += 4.0
        # Parked-car slots along town kerbs; occupancy changes over time (City.slots_occupied).
        arc = 0.0
        while arc + cfg.car_slot_length_m < length:
            district = street.district_at(arc)
            if district in (DENSE, SUBURBAN):
                bay = street.stretch(arc, arc + cfg.car_slot_length_m, side)
                if bay is not None:
                    along, outward = bay.along, bay.outward
                    kerb_offset = road_half_width - cfg.car_kerb_gap_m - car_width / 2
                    centre = (bay.start + bay.end) / 2 + outward * kerb_offset
                    angle = math.atan2(along[1], along[0])
                    corners = centre + np.array(
                        [along * sx * car_length / 2 + outward * sy * car_width / 2 for sx in (-1, 1) for sy in (-1, 1)]
                    )
                    clear = kerb_offset - car_width / 2 - 0.05
                    if builder.clear_of_streets(corners, clear) and builder.clear_of_streets(
                        centre[None], kerb_offset - 0.3
                    ):
                        if builder.claim(np.vstack([corners, centre[None]]), dilate=1):
                            slot = builder.n_slots
                            builder.n_slots += 1
                            sid = builder.surface(CAR, district, top=car_height)
                            base = builder.ground_z(centre[None])
                            builder.box(
                                centre, car_length / 2, car_width / 2, angle, base, base + car_height, sid, slot=slot
                            )
            arc += cfg.car_slot_length_m
