"""Loops no geometry verified are checked against earlier loops of their revisit under odometry
(`backend.loop_consistency`): a street driven twice closes the cycle, a wrong match does not;
and such a loop becomes a factor only as `two_view.on_geometry_failure` says."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ssmvpr_slam import loop_policy
from ssmvpr_slam.backend.config import LoopConsistencyConfig, LoopRegistrationConfig, TwoViewConfig
from ssmvpr_slam.backend.loop_consistency import LoopPose, agrees, disagreement, support
from ssmvpr_slam.backend.loop_registration import LoopRegistrar
from ssmvpr_slam.backend.se3 import make_pose, rot_z

CONFIG = LoopConsistencyConfig()


def street(x: float, heading: float = 0.0, y: float = 0.0) -> np.ndarray:
    return make_pose(rot_z(heading), np.array([x, y, 0.0]))


def loop(q: int, m: int, query_pose: np.ndarray, match_pose: np.ndarray, yaw: float = 0.0) -> LoopPose:
    """A place prior: zero translation, the yaw guess; travelled = keyframe index (1 m a keyframe)."""
    return LoopPose(q, m, query_pose, match_pose, make_pose(rot_z(yaw), np.zeros(3)), float(q), float(m))


def test_a_street_driven_twice_closes_the_cycle() -> None:
    # first visit: keyframes 0..20 along x; second visit: keyframes 100..120 along the same street,
    # odometry drifted 6 m sideways and 3 deg by then (the same offset on both loops)
    drift = make_pose(rot_z(math.radians(3.0)), np.array([2.0, 6.0, 0.0]))
    a = loop(105, 5, drift @ street(5.0), street(5.0))
    b = loop(109, 9, drift @ street(9.0), street(9.0))
    metres, degrees = disagreement(a, b)
    assert metres < 0.01 and degrees < 0.01
    assert agrees(a, b, CONFIG)


def test_a_reverse_revisit_closes_the_cycle_with_the_rear_camera_s_half_turn() -> None:
    # the second visit drives the street the other way: keyframe 100 + k at x = 20 - k, heading pi;
    # the rear camera's loop carries the half turn in its yaw
    a = loop(105, 15, street(15.0, math.pi), street(15.0), yaw=math.pi)
    b = loop(109, 11, street(11.0, math.pi), street(11.0), yaw=math.pi)
    assert agrees(a, b, CONFIG)


def test_a_match_to_the_wrong_place_does_not() -> None:
    a = loop(105, 5, street(5.0), street(5.0))
    wrong = loop(109, 9, street(9.0), street(40.0, y=30.0))  # the recogniser matched a place 40 m away
    assert not agrees(a, wrong, CONFIG)
    metres, _ = disagreement(a, wrong)
    assert metres > 30


def test_support_counts_only_loops_of_the_same_revisit_within_the_window() -> None:
    now = loop(110, 10, street(10.0), street(10.0))
    earlier = [
        loop(102, 2, street(2.0), street(2.0)),
        loop(104, 4, street(4.0), street(4.0)),
        loop(106, 6, street(6.0), street(6.0)),
        loop(90, 60, street(10.0), street(10.0)),  # too long ago
        loop(108, 40, street(8.0), street(8.0)),  # another revisit (match far away in keyframes)
        loop(111, 11, street(11.0), street(11.0)),  # after it
    ]
    assert support(now, earlier, CONFIG) == 3
    assert support(now, earlier, LoopConsistencyConfig(window_keyframes=5)) == 1  # only 106 -> 6


def test_unverified_and_confirmed_registrations() -> None:
    registrar = LoopRegistrar(LoopRegistrationConfig(two_view=TwoViewConfig(on_geometry_failure="consistent")))
    prior = registrar.yaw_prior(0.3, "only 3 ORB matches")
    refused = loop_policy.unverified(registrar.config, prior, 1)
    assert not refused.accepted and refused.method == "unverified" and np.isnan(refused.sigmas).all()
    assert refused.reason.startswith("unverified: 1 of the 2 earlier loops of the revisit needed agree")
    np.testing.assert_array_equal(refused.T_mq, prior.T_mq)  # what later loops check against
    kept = loop_policy.confirmed(prior, 2)
    assert kept.accepted and kept.method == "yaw_prior" and kept.reason.endswith("2 earlier loops of the revisit agree")


@pytest.mark.parametrize("bad", [{"min_support": 0}, {"max_translation_m": 0.0}, {"max_rotation_deg": 200.0}])
def test_config_refuses_meaningless_bounds(bad: dict) -> None:
    with pytest.raises(ValueError):
        LoopConsistencyConfig(**bad)
