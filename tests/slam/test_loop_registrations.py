"""Loop registration off the critical path (`LoopRegistrations`): results fall due at a fixed
lag in keyframes, the worker sees what inline registration sees, and a checkpoint's unapplied
registrations come back."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import pytest

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.loop_registrations import LoopRegistrations
from ssmvpr_slam.run_result import LoopRecord


def proposal(query: int, accepted: bool = True) -> LoopProposal:
    return LoopProposal(query, query - 40, query - 40, 0.5, 0.1, 0, 0.0, accepted, "test")


@dataclass
class Kf:
    id: int


class RecordingPolicy:
    """Registers each proposal as 'icp' after `delay` seconds and remembers, per query, what it
    was shown: the registrations of the loops before it and the distance travelled."""

    def __init__(self, delay: float = 0.0) -> None:
        self.delay = delay
        self.seen: dict[int, tuple[list[tuple[int, str | None]], float]] = {}
        self.threads: set[str] = set()

    def register(self, kf, proposal, keyframes, loops, travelled_since):  # noqa: ANN001, ANN201
        time.sleep(self.delay)
        self.threads.add(threading.current_thread().name)
        earlier = [(r.proposal.query_id, None if r.registration is None else r.registration.method) for r in loops]
        self.seen[proposal.query_id] = (earlier, travelled_since)
        return LoopRegistration(np.eye(4), True, f"registered {proposal.query_id}", 0.9, 0.1, method="icp")


def feed(registrations: LoopRegistrations, queries: list[int], accepted: set[int]) -> dict[int, list[int]]:
    """Keyframes 0..max(queries)+lag: a proposal at each of `queries`, the accepted ones submitted;
    returns, per keyframe, the queries whose registrations fell due there."""
    loops: list[LoopRecord] = []
    applied: dict[int, list[int]] = {}
    for k in range(max(queries) + registrations.lag + 1):
        if k in queries:
            loops.append(LoopRecord(proposal(k, k in accepted)))
            if k in accepted:
                registrations.submit(len(loops) - 1, Kf(k), loops[-1].proposal, [], loops, float(k))  # type: ignore[arg-type]
        for done in registrations.due(k):
            loops[done.index] = LoopRecord(done.proposal, done.registration)
            applied.setdefault(k, []).append(done.proposal.query_id)
    return applied


@pytest.mark.parametrize("worker", [False, True])
def test_a_registration_falls_due_lag_keyframes_after_its_proposal(worker: bool) -> None:
    registrations = LoopRegistrations(RecordingPolicy(delay=0.01), lag=3, worker=worker)  # type: ignore[arg-type]
    applied = feed(registrations, [50, 51, 52, 60], {50, 51, 60})
    assert applied == {53: [50], 54: [51], 63: [60]}
    registrations.close()


def test_the_worker_sees_every_earlier_registration_as_inline_registration_does() -> None:
    """The worker registers 51 before 50's result is applied (due at 53): it still sees it, as
    registering inline at the proposal's keyframe would; a proposal that was not accepted it
    sees without a registration."""
    views = {}
    for worker in (False, True):
        policy = RecordingPolicy(delay=0.02)
        registrations = LoopRegistrations(policy, lag=3, worker=worker)  # type: ignore[arg-type]
        feed(registrations, [50, 51, 52, 53], {50, 51, 53})
        registrations.close()
        views[worker] = policy.seen
        assert policy.threads == ({"MainThread"} if not worker else {"loop-registration_0"})
    assert views[True] == views[False]
    assert views[True][53] == ([(50, "icp"), (51, "icp"), (52, None)], 53.0)


def test_lag_zero_registers_inline_at_once() -> None:
    policy = RecordingPolicy()
    registrations = LoopRegistrations(policy, lag=0, worker=True)  # type: ignore[arg-type]
    assert feed(registrations, [50], {50}) == {50: [50]}
    assert policy.threads == {"MainThread"}  # nothing to overlap: no worker


def test_the_registrations_not_yet_due_are_kept_and_restored() -> None:
    policy = RecordingPolicy()
    first = LoopRegistrations(policy, lag=3, worker=True)  # type: ignore[arg-type]
    loops = [LoopRecord(proposal(50)), LoopRecord(proposal(51, accepted=False)), LoopRecord(proposal(52))]
    first.submit(0, Kf(50), loops[0].proposal, [], loops[:1], 1.0)  # type: ignore[arg-type]
    first.submit(2, Kf(52), loops[2].proposal, [], loops, 2.0)  # type: ignore[arg-type]
    [applied] = first.due(53)
    assert applied.proposal.query_id == 50
    loops[0] = LoopRecord(applied.proposal, applied.registration)  # as the system applies it
    unapplied = first.unapplied()
    assert [index for index, _ in unapplied] == [2]
    first.close()
    resumed = LoopRegistrations(RecordingPolicy(), lag=3, worker=True)  # type: ignore[arg-type]
    resumed.restore(loops, unapplied)
    assert resumed.due(54) == []
    [done] = resumed.due(55)
    assert done.index == 2 and done.registration.reason == "registered 52"
    with pytest.raises(RuntimeError, match="fresh"):
        resumed.restore(loops, unapplied)
    resumed.close()


def test_an_error_in_the_worker_surfaces_when_the_registration_falls_due() -> None:
    class Failing(RecordingPolicy):
        def register(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN201
            raise ValueError("scan of keyframe 50 is empty")

    registrations = LoopRegistrations(Failing(), lag=2, worker=True)  # type: ignore[arg-type]
    loops = [LoopRecord(proposal(50))]
    registrations.submit(0, Kf(50), loops[0].proposal, [], loops, 1.0)  # type: ignore[arg-type]
    assert registrations.due(51) == []
    with pytest.raises(ValueError, match="keyframe 50"):
        registrations.due(52)
    registrations.close()


def test_a_negative_lag_is_refused() -> None:
    with pytest.raises(ValueError, match="lag"):
        LoopRegistrations(RecordingPolicy(), lag=-1, worker=True)  # type: ignore[arg-type]
