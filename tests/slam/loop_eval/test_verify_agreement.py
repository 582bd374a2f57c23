"""`loop-eval --verify`'s agreement rule: a loop the views refuse stands when earlier loops of its
revisit that the views verified agree with it along the path, as a run lets such a loop in when
earlier loops agree under odometry. Streams here are built by hand: frame k is k metres along."""

from __future__ import annotations

import numpy as np

from loopclosure.detector import LoopProposal
from loopclosure.pair_verifier import PairVerdict
from ssmvpr_slam.backend.config import LoopConsistencyConfig
from ssmvpr_slam.loop_eval.stream import StreamOutcome, path_positions, travelled
from ssmvpr_slam.loop_eval.verification import agreeing_loops

RULE = LoopConsistencyConfig()  # min_support 2, window 10, 1.5 m + 0.1 per metre driven


def proposal(q: int, m: int, direction: str = "forward") -> LoopProposal:
    return LoopProposal(q, m, m, 0.5, 0.5, 0, 0.0, True, "accepted", direction=direction)  # type: ignore[arg-type]


def verdict(accepted: bool, model: str = "fundamental") -> PairVerdict:
    return PairVerdict(accepted, model, 300, 200 if accepted else 100, None, None, "test")


def agreed(loops: dict[int, tuple[int, str, bool]], n: int = 100, verdicts_of: dict[int, PairVerdict] | None = None):
    """loops: query frame -> (match frame, direction, verified by the views)."""
    proposals: list[LoopProposal | None] = [None] * n
    verdicts = {}
    for q, (m, direction, ok) in loops.items():
        proposals[q] = proposal(q, m, direction)
        verdicts[q] = verdict(ok)
    verdicts.update(verdicts_of or {})
    outcome = StreamOutcome(tuple(proposals), np.zeros(n))
    return agreeing_loops(outcome, verdicts, travelled(path_positions(n, 1.0)), RULE)


def test_a_refused_loop_in_a_run_of_verified_ones_is_kept() -> None:
    loops = {q: (q - 50, "forward", True) for q in range(60, 70)}
    loops[66] = (16, "forward", False)
    assert agreed(loops) == {66: 6}  # 60-65 lie within the window and moved as the query did


def test_one_verified_neighbour_is_not_enough() -> None:
    loops = {60: (10, "forward", True), 61: (11, "forward", False)}
    assert agreed(loops) == {}


def test_supporters_must_be_verified_by_the_views() -> None:
    """A stretch of look-alikes the views refuse one by one does not vouch for itself."""
    loops = {q: (q - 30, "forward", False) for q in range(60, 68)}
    assert agreed(loops) == {}


def test_a_loop_off_the_revisit_does_not_agree() -> None:
    """Verified loops 60-64 match frames 10-14; frame 65 matched frame 19, 4 m beyond where the
    revisit puts it (and frame 66 matched a place 40 m away)."""
    loops = {q: (q - 50, "forward", True) for q in range(60, 65)}
    loops[65] = (19, "forward", False)
    loops[66] = (56, "forward", False)
    assert agreed(loops) == {}


def test_supporters_come_before_the_loop_and_within_the_window() -> None:
    later = {q: (q - 50, "forward", True) for q in range(61, 70)}
    assert agreed({**later, 60: (10, "forward", False)}) == {}  # only later loops: not yet known to a run
    far = {q: (q - 50, "forward", True) for q in range(40, 48)}
    assert agreed({**far, 60: (10, "forward", False)}) == {}  # 13+ frames before: outside the window


def test_a_reverse_revisit_agrees_backwards() -> None:
    """Walking the street the other way, the match moves back as the query moves on."""
    loops = {q: (90 - q, "reverse", True) for q in range(60, 66)}
    loops[66] = (24, "reverse", False)
    assert agreed(loops) == {66: 6}
    loops[66] = (36, "reverse", False)  # the forward reading of the same frames would be 12 m off
    assert agreed(loops) == {}


def test_unverifiable_and_verified_loops_need_no_agreement() -> None:
    loops = {q: (q - 50, "forward", True) for q in range(60, 66)}
    loops[66] = (16, "forward", True)
    small = {66: verdict(False, model="unverifiable")}
    assert agreed(loops) == {}
    assert agreed(loops, verdicts_of=small) == {}
