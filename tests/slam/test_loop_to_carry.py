"""Which earlier loop seeds the registration of the next one (`system.loop_to_carry`)."""

from __future__ import annotations

import numpy as np

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.loop_policy import loop_to_carry
from ssmvpr_slam.run_result import LoopRecord


def record(q: int, m: int, *, accepted: bool = True, method: str = "icp", prior_map: bool = False) -> LoopRecord:
    proposal = LoopProposal(q, m, m, 0.9, 0.5, 0, 0.0, True, "accepted", "reverse", prior_map=prior_map)
    registration = LoopRegistration(np.eye(4), accepted, "test", 0.9, 0.1, method=method)
    return LoopRecord(proposal, registration)


def test_a_revisit_whose_matches_alternate_between_two_earlier_visits_carries_its_own_loop():
    """The demo's reverse streets, driven twice before: 533 -> 353, 534 -> 115, then 540 looks
    for 348. The latest loop belongs to the other visit; the one before is this revisit's."""
    loops = [record(533, 353), record(534, 115)]
    assert loop_to_carry(loops, 540, 348, reach=8) is loops[0]
    assert loop_to_carry(loops, 541, 109, reach=8) is loops[1]
    assert loop_to_carry(loops, 540, 348, reach=3) is None  # 7 keyframes back: beyond this reach


def test_only_accepted_icp_loops_of_the_session_before_the_query_are_carried():
    earlier = record(10, 100)
    assert loop_to_carry([earlier], 12, 102, reach=3) is earlier
    for unusable in (
        record(11, 101, accepted=False),
        record(11, 101, method="yaw_prior"),
        record(11, 101, prior_map=True),
        record(11, 101, accepted=False, method="spaced"),  # spaced out: never registered
        record(12, 101),  # the query's own proposal, recorded before it is registered
    ):
        assert loop_to_carry([earlier, unusable], 12, 102, reach=3) is earlier
        assert loop_to_carry([unusable], 12, 102, reach=3) is None


def test_the_latest_loop_of_the_revisit_wins_and_the_reach_is_inclusive():
    older, newer = record(10, 100), record(11, 101)
    assert loop_to_carry([older, newer], 12, 102, reach=3) is newer
    assert loop_to_carry([older], 13, 103, reach=3) is older  # exactly `reach` back on both visits
    assert loop_to_carry([older], 13, 97, reach=3) is older  # a reverse revisit: the match runs backwards


def test_nothing_is_carried_past_the_reach_or_with_no_loops():
    assert loop_to_carry([], 5, 1, reach=8) is None
    assert loop_to_carry([record(10, 100)], 19, 100, reach=8) is None  # query 9 keyframes on
    assert loop_to_carry([record(10, 100)], 12, 120, reach=8) is None  # another place
    assert loop_to_carry([record(10, 100)], 12, 102, reach=0) is None  # carrying turned off


def test_loop_spacing_registers_every_fourth_keyframe_of_a_revisit():
    """The system spaces loops out with reach = loop_spacing_keyframes - 1: with 4, the loop
    registered at 10 stands for 11, 12 and 13, and 14 is registered again."""
    loops = [record(10, 100)]
    for q in (11, 12, 13):
        assert loop_to_carry(loops, q, 100 + (q - 10), reach=3) is loops[0]
        loops.append(record(q, 100 + (q - 10), accepted=False, method="spaced"))
    assert loop_to_carry(loops, 14, 104, reach=3) is None
    assert loop_to_carry(loops, 11, 101, reach=0) is None  # spacing 1: every loop is registered
