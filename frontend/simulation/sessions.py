"""Several sessions in one simulated city: different routes, starts, light and traffic.

A fleet logs the same streets on different days along different routes. Every session here
shares the city (its seed, terrain and the streets it is laid along, `CITY_TOUR`) and the
world frame of its ground truth; each drives its own loop of the street grid (`SESSION_LOOPS`),
starting from its own crossing, at its own time of day, with its own traffic, sensor noise
and odometry drift (`session_seed`). Loops overlap in part, some streets the same way and some
the other way, so sessions meet only through the places they share.
"""

from __future__ import annotations

from frontend.simulation.config import RouteConfig, SimulationConfig

Crossing = tuple[int, int]

CITY_TOUR: list[list[Crossing]] = [
    [(0, 0), (3, 0), (3, 2), (0, 2), (0, 0)],
    [(0, 0), (1, 0), (1, 2), (2, 2), (2, 0), (3, 0), (3, 1), (0, 1)],
]
"""Every street of a 3 x 2 block grid (crossings 0..3 by 0..2), driven without a U-turn: the
centre line the city's buildings are laid along."""

SESSION_LOOPS: list[list[Crossing]] = [
    [(0, 0), (3, 0), (3, 1), (0, 1), (0, 0)],  # the lower row of blocks, anticlockwise
    [(3, 1), (0, 1), (0, 2), (3, 2), (3, 1)],  # the upper row, clockwise: its first street is the first's
    [(1, 0), (1, 2), (3, 2), (3, 0), (1, 0)],  # the right-hand blocks, clockwise
    [(0, 2), (0, 0), (2, 0), (2, 2), (0, 2)],  # the left-hand blocks, anticlockwise
    [(0, 0), (3, 0), (3, 2), (0, 2), (0, 0)],  # the outer streets, anticlockwise
]
"""Each session's loop of the grid (closed, one lap): every one shares streets with others."""

SESSION_LIGHT = ["day", "dusk"]
"""Appearance of session k: day and dusk in turn."""


def session_loop(index: int) -> list[Crossing]:
    """Session `index`'s loop: `SESSION_LOOPS` in turn, started one crossing further on each round."""
    loop = SESSION_LOOPS[index % len(SESSION_LOOPS)][:-1]
    shift = (index // len(SESSION_LOOPS)) % len(loop)
    turned = loop[shift:] + loop[:shift]
    return [*turned, turned[0]]


def city_sessions(base: SimulationConfig, count: int, start: int = 0) -> list[SimulationConfig]:
    """`count` sessions (numbered from `start`) of `base`'s city: its seed, city and sensors;
    each with its own loop, light, start time and `session_seed`."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    city_route = base.route.model_copy(update={"crossings": CITY_TOUR, "laps": 1})
    sessions = []
    for k in range(start, start + count):
        route: RouteConfig = base.route.model_copy(update={"crossings": [session_loop(k)], "laps": 1})
        light = SESSION_LIGHT[k % len(SESSION_LIGHT)]
        sessions.append(
            base.model_copy(
                update={
                    "route": route,
                    "city_route": city_route,
                    "session_seed": (base.seed * 7919 + 1 + k) % 2**32,
                    "appearance_schedule": [light],
                    "start_time_s": base.start_time_s + 3600.0 * k,  # another hour: other parked cars
                }
            )
        )
    return sessions
