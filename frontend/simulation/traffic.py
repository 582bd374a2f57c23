"""Oncoming traffic: vehicles driving the street centre line the other way, on their own lane.

Moving objects are what a real scan matcher has to ignore, and they differ on every visit.
Vehicle k sits at arc length (s_k - v_k t) mod L of the centre line at time t, offset to the
oncoming lane; a vehicle that would come within reach of the ego vehicle (where the route
crosses itself) is left out of that instant rather than driven through it.
"""

from __future__ import annotations

import math

import numpy as np

from frontend.simulation.city import CAR, City, _box_segments
from frontend.simulation.config import TrafficConfig
from frontend.simulation.render import Scene

_STREAM_TRAFFIC = 7919
_EGO_CLEARANCE_M = 4.0


class Traffic:
    def __init__(self, city: City, centre: np.ndarray, config: TrafficConfig, lane_offset_m: float, seed: int):
        self.city = city
        self.config = config
        xy = np.asarray(centre, float)[:, :2]
        z = np.asarray(centre, float)[:, 2]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        self._s, self._xy, self._z = s, xy, z
        self.length = float(s[-1])
        self.lane_offset = lane_offset_m
        rng = np.random.default_rng([seed, _STREAM_TRAFFIC])
        n = int(round(config.oncoming_vehicles_per_km * self.length / 1000.0))
        self.start = rng.uniform(0, self.length, n)
        self.speed = rng.uniform(*config.speed_range_mps, n)
        cars = np.flatnonzero(city.kind == CAR)
        # Vehicles borrow the textures of parked-car surfaces (colours of the city's palette).
        self.surface = cars[rng.integers(0, len(cars), n)] if len(cars) else np.zeros(n, np.int64)

    def __len__(self) -> int:
        return len(self.start)

    def scene_part(self, t: float, ego_xy: np.ndarray) -> Scene:
        """Walls of the vehicles at time t, minus any too close to the ego vehicle."""
        if len(self) == 0 or self.length <= 0:
            return _empty()
        length, width, height = self.config.vehicle_size_m
        a = np.mod(self.start - self.speed * t, self.length)
        x = np.interp(a, self._s, self._xy[:, 0])
        y = np.interp(a, self._s, self._xy[:, 1])
        ahead = np.minimum(a + 1.0, self.length)
        hx = np.interp(ahead, self._s, self._xy[:, 0]) - x
        hy = np.interp(ahead, self._s, self._xy[:, 1]) - y
        norm = np.maximum(np.hypot(hx, hy), 1e-9)
        hx, hy = hx / norm, hy / norm
        cx = x - hy * self.lane_offset
        cy = y + hx * self.lane_offset
        base = np.interp(a, self._s, self._z)
        keep = np.hypot(cx - ego_xy[0], cy - ego_xy[1]) > _EGO_CLEARANCE_M + length / 2
        parts: dict[str, list[np.ndarray]] = {k: [] for k in ("p0", "p1", "z0", "z1", "surface", "u0", "normal")}
        for k in np.flatnonzero(keep):
            p0, p1, nrm = _box_segments(cx[k], cy[k], length / 2, width / 2, math.atan2(hy[k], hx[k]))
            parts["p0"].append(p0)
            parts["p1"].append(p1)
            parts["normal"].append(nrm)
            parts["z0"].append(np.full(4, base[k]))
            parts["z1"].append(np.full(4, base[k] + height))
            parts["surface"].append(np.full(4, self.surface[k], np.int64))
            parts["u0"].append(np.zeros(4))
        if not parts["p0"]:
            return _empty()
        return Scene(**{k: np.concatenate(v) for k, v in parts.items()})


def _empty() -> Scene:
    z2 = np.zeros((0, 2))
    z1 = np.zeros(0)
    return Scene(p0=z2, p1=z2, z0=z1, z1=z1, surface=np.zeros(0, np.int64), u0=z1, normal=z2)
