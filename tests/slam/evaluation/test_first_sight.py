"""How a run's loops entered the graph (`metrics.json` loops.in_graph_by_method, loops.first_sight):
the loops of one revisit come as a run, and its first loop is in the graph at first sight only
when its own registration verified it (ICP or two views), not when it waited for earlier loops."""

from __future__ import annotations

import numpy as np

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.evaluation.run_report import _first_sight, _verified_by
from ssmvpr_slam.run_result import LoopRecord

AGREE = "yaw prior from the visual match (no geometry); 2 earlier loops of the revisit agree"


def record(q: int, m: int, method: str, *, in_graph: bool = True, reason: str = "ok") -> LoopRecord:
    proposal = LoopProposal(q, m, m, 0.9, 0.5, 0, 0.0, True, "accepted", "forward")
    registration = LoopRegistration(np.eye(4), in_graph, reason, 0.9, 0.1, method=method)
    return LoopRecord(proposal, registration, factor_handle=q if in_graph else None)


def test_a_revisit_verified_by_two_views_is_closed_at_first_sight() -> None:
    run = [record(100 + k, 10 + k, "two_view_deep") for k in range(5)]
    assert _first_sight(run, gap=10) == {"revisits": 1, "first_loop_in_graph": 1}


def test_a_revisit_that_waited_for_agreeing_loops_is_not() -> None:
    run = [record(100, 10, "unverified", in_graph=False), record(101, 11, "unverified", in_graph=False)]
    run += [record(102 + k, 12 + k, "yaw_prior", reason=AGREE) for k in range(3)]
    assert _first_sight(run, gap=10) == {"revisits": 1, "first_loop_in_graph": 0}
    assert _verified_by(run[2]) == "earlier_loops" and _verified_by(run[0]) == "unverified"


def test_revisits_are_told_apart_by_their_queries_and_matches() -> None:
    """Two revisits interleaved (a street driven twice before: matches alternate between the two
    earlier visits), and a third after a gap: three revisits."""
    loops = [record(200, 50, "icp"), record(201, 150, "two_view_deep"), record(202, 51, "icp"),
             record(203, 151, "yaw_prior", reason=AGREE), record(240, 90, "unverified", in_graph=False)]  # fmt: skip
    assert _first_sight(loops, gap=10) == {"revisits": 3, "first_loop_in_graph": 2}
