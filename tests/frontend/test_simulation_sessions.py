"""Sessions of one simulated city (`frontend.simulation.sessions`): one world, other drives."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial import cKDTree

from frontend.simulation.config import RouteConfig, SimulationConfig
from frontend.simulation.sessions import SESSION_LOOPS, city_sessions, session_loop
from frontend.simulation.simulator import TraverseSimulator


@pytest.fixture(scope="module")
def simulators() -> list[TraverseSimulator]:
    base = SimulationConfig(frame_rate_hz=3.0, city={"block_size_m": 30.0})
    return [TraverseSimulator(c) for c in city_sessions(base, 3)]


def test_sessions_share_the_city_and_its_world_frame_but_drive_their_own_loops(simulators):
    a, b, c = simulators
    for other in (b, c):  # the same buildings, where they were
        np.testing.assert_array_equal(a.city.p0, other.city.p0)
        np.testing.assert_array_equal(a.city.z1, other.city.z1)
    starts = [s.gt_positions()[0] for s in simulators]
    assert min(np.linalg.norm(p - q) for p, q in [(starts[0], starts[1]), (starts[0], starts[2])]) > 20.0
    # sessions 0 and 1 share a street: there their ground truth is within a lane of each other
    near, _ = cKDTree(a.gt_positions()).query(b.gt_positions())
    assert np.sum(near < 1.0) > 10 and np.sum(near > 20.0) > 10  # some shared, most not


def test_what_differs_between_sessions_follows_the_session_seed(simulators):
    a, b, _ = simulators
    assert a.config.appearance_schedule != b.config.appearance_schedule  # day, then dusk
    base = a.config
    again = TraverseSimulator(base)
    np.testing.assert_array_equal(again.render_image(5), a.render_image(5))  # deterministic
    other = TraverseSimulator(base.model_copy(update={"session_seed": base.session_seed + 1}))
    np.testing.assert_array_equal(other.city.p0, a.city.p0)
    assert not np.array_equal(other.render_image(5), a.render_image(5))  # pixel noise, traffic
    assert not np.allclose(other.logged_pose(40), a.logged_pose(40))  # odometry drift


def test_session_loops_turn_and_start_further_on_after_a_round():
    assert session_loop(0) == SESSION_LOOPS[0]
    later = session_loop(len(SESSION_LOOPS))
    assert later[0] == SESSION_LOOPS[0][1] and later[0] == later[-1]
    with pytest.raises(ValueError, match="count"):
        city_sessions(SimulationConfig(), 0)


@pytest.mark.parametrize(
    ("crossings", "match"),
    [([[(0, 0), (1, 1)]], "not along one street"), ([[(0, 0), (1, 0)], [(2, 0), (3, 0)]], "where the last ended"),
     ([[(0, 0)]], "at least two")],
)  # fmt: skip
def test_crossings_that_are_not_a_drive_along_the_grid_are_refused(crossings, match):
    with pytest.raises(ValidationError, match=match):
        RouteConfig(crossings=crossings)
