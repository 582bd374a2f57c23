"""Loops no geometry verified are checked against earlier loops of their revisit under odometry
(`backend.loop_consistency`): a street driven twice closes the cycle, a wrong match does not;
and such a loop becomes a factor only as `two_view.on_geometry_failure` says."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ssmvpr_slam import loop_policy
from ssmvpr_slam.backend.config import LoopConsistencyConfig, LoopRegistrationConfig, TwoViewConfig
from ssmvpr_slam.backend.loop_consistency import LoopPose, agrees, disagreement, support
from ssmvpr_slam.backend.loop_registration import LoopRegistrar, LoopRegistration
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


class _Detector:
    """What the policy reads of the detector here: place k is keyframe k, driven k metres in."""

    has_encoder = False

    def place_of(self, keyframe_id: int) -> int:
        return keyframe_id

    def travelled_at(self, place: int) -> float:
        return float(place)


def _checked(earlier_method: str, views_refused: bool) -> LoopRegistration:
    """Loop 105 -> 5 on a street driven twice (keyframes 0-20, then 100-120 along the same x,
    odometry 6 m to the side by then), after loops 101 -> 1 and 103 -> 3 registered by
    `earlier_method`; its own views gave no rotation (refused by the deep features, or not)."""
    from loopclosure.detector import LoopProposal
    from ssmvpr_slam.config.slam import SlamConfig
    from ssmvpr_slam.run_result import Keyframe, LoopRecord

    config = SlamConfig()
    assert config.backend.registration.two_view.on_geometry_failure == "consistent"
    policy = loop_policy.LoopPolicy(config, _Detector(), None)  # type: ignore[arg-type]
    drift = street(0.0, y=6.0)
    keyframes = [
        Keyframe(k, k, float(k), street(float(k)) if k < 100 else drift @ street(float(k - 100)), None, None, None)
        for k in range(121)
    ]

    def proposal(q: int, m: int) -> LoopProposal:
        return LoopProposal(q, m, m, 0.5, 0.5, 0, 0.0, True, "accepted")

    prior = policy.registrar.yaw_prior(0.0, "no rotation", views_refused=False)
    earlier = [
        LoopRecord(proposal(q, q - 100), replace(prior, method=earlier_method, accepted=earlier_method != "unverified"))
        for q in (101, 103)
    ]
    now = policy.registrar.yaw_prior(0.0, "the views refused", views_refused=views_refused)
    return policy._checked(keyframes, earlier, keyframes[105], proposal(105, 5), now)


def test_loops_whose_views_were_refused_are_vouched_for_only_by_verified_loops() -> None:
    """Two loops the views refused before it agree with a third under odometry, as a parallel
    look-alike street would: that is not enough. Two loops the views verified are."""
    alone = _checked("unverified", views_refused=True)
    assert alone.method == "unverified" and not alone.accepted
    assert "only loops a scan or two views verified count" in alone.reason
    backed = _checked("two_view_deep", views_refused=True)
    assert backed.accepted and backed.method == "yaw_prior"
    assert "2 earlier loops of the revisit agree" in backed.reason
    # no geometry at all (ORB across light, a keyframe without an image): any earlier loop vouches, as before
    assert _checked("unverified", views_refused=False).accepted
    assert _checked("yaw_prior", views_refused=False).accepted


@pytest.mark.parametrize("bad", [{"min_support": 0}, {"max_translation_m": 0.0}, {"max_rotation_deg": 200.0}])
def test_config_refuses_meaningless_bounds(bad: dict) -> None:
    with pytest.raises(ValueError):
        LoopConsistencyConfig(**bad)
