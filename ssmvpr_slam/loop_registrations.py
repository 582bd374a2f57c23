"""Loop registration off the critical path: accepted proposals registered in a worker while
later keyframes are recognised, each result entering the graph at a fixed lag.

Why: verifying a loop (ICP against a local map, two views of the images) takes as long as
recognising a keyframe, and done inline it sets the pace. ORB-SLAM3 closes loops in a thread of
its own beside tracking; here the worker registers proposal k while keyframes k+1, k+2, ... are
recognised, and its result is applied (the loop factor, the places joined) at keyframe
k + `pipeline.registration_lag_keyframes`, before that keyframe's iSAM2 step. The lag is fixed in
keyframes, not in time: a run gives the same loops and the same trajectory whatever the
machine's timing, with the worker or inline (`pipeline.registration_worker`), and a resumed run
the same as an uninterrupted one. With lag 0 a loop is applied at its own keyframe.

The worker registers the proposals one at a time in their order, against its own copy of the
loop records (each with the registrations before it), so every registration sees what it would
see inline: the loops registered before it, whether or not they are applied yet. It reads the
run's keyframes up to its own (a list only ever appended to) and the distance travelled as it
was when the proposal was made (`travelled_since`, taken then).
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.loop_policy import LoopPolicy
from ssmvpr_slam.run_result import Keyframe, LoopRecord


@dataclass(frozen=True)
class AppliedRegistration:
    """A registration due now: the record to replace (its index in the run's loops) and the
    seconds its computation took (in the worker or inline)."""

    index: int
    proposal: LoopProposal
    registration: LoopRegistration
    seconds: float


@dataclass
class _Pending:
    index: int
    proposal: LoopProposal
    due: int  # the keyframe whose step applies it
    result: Future[tuple[LoopRegistration, float]] | tuple[LoopRegistration, float]


class LoopRegistrations:
    """`submit` an accepted proposal at its keyframe; `due(k)` returns the registrations to apply
    at keyframe k (waiting for the worker where it is behind), in proposal order."""

    def __init__(self, policy: LoopPolicy, lag: int, worker: bool) -> None:
        if lag < 0:
            raise ValueError(f"registration lag must be 0 or more keyframes, got {lag}")
        self.policy = policy
        self.lag = lag
        self._executor = ThreadPoolExecutor(1, "loop-registration") if worker and lag > 0 else None
        self._pending: deque[_Pending] = deque()
        self._mirror: list[LoopRecord] = []  # the run's loop records as the worker sees them
        self._sent = 0  # how many of the run's records the mirror holds
        self.waited_s = 0.0  # seconds `due` spent waiting for the worker (the critical path's share)

    def submit(
        self,
        index: int,
        kf: Keyframe,
        proposal: LoopProposal,
        keyframes: Sequence[Keyframe],
        loops: Sequence[LoopRecord],
        travelled_since: float,
    ) -> None:
        """Register `proposal` (the record `loops[index]`, made at keyframe `kf`), inline or in
        the worker; it is applied at keyframe kf.id + lag. `loops` are the run's records so far:
        those since the last submission join the worker's copy."""
        if index != len(loops) - 1:
            raise ValueError("LoopRegistrations.submit: the proposal must be the run's latest loop record")
        new = list(loops[self._sent : index + 1])
        self._sent = index + 1
        task = (kf, proposal, keyframes, new, travelled_since)
        result: Future[tuple[LoopRegistration, float]] | tuple[LoopRegistration, float]
        result = self._executor.submit(self._register, *task) if self._executor is not None else self._register(*task)
        self._pending.append(_Pending(index, proposal, kf.id + self.lag, result))

    def _register(
        self,
        kf: Keyframe,
        proposal: LoopProposal,
        keyframes: Sequence[Keyframe],
        new: list[LoopRecord],
        travelled_since: float,
    ) -> tuple[LoopRegistration, float]:
        start = time.perf_counter()
        self._mirror.extend(new[:-1])
        registration = self.policy.register(kf, proposal, keyframes, self._mirror, travelled_since)
        self._mirror.append(replace(new[-1], registration=registration))
        return registration, time.perf_counter() - start

    def due(self, keyframe: int) -> list[AppliedRegistration]:
        """The registrations of proposals due at or before `keyframe`, oldest first."""
        out = []
        while self._pending and self._pending[0].due <= keyframe:
            out.append(self._take(self._pending.popleft()))
        return out

    def remaining(self) -> list[AppliedRegistration]:
        """Every registration not yet applied (the stream ended before they were due)."""
        return self.due(sys.maxsize)

    def _take(self, pending: _Pending) -> AppliedRegistration:
        if isinstance(pending.result, Future):
            start = time.perf_counter()
            registration, seconds = pending.result.result()  # re-raises the worker's error here
            self.waited_s += time.perf_counter() - start
        else:
            registration, seconds = pending.result
        return AppliedRegistration(pending.index, pending.proposal, registration, seconds)

    def unapplied(self) -> list[tuple[int, LoopRegistration]]:
        """(record index, registration) of every submitted proposal not applied yet, waiting for
        the worker: what a checkpoint keeps so that a resume applies them when they fall due."""
        out = []
        for pending in self._pending:
            registration = pending.result.result()[0] if isinstance(pending.result, Future) else pending.result[0]
            out.append((pending.index, registration))
        return out

    def restore(self, loops: Sequence[LoopRecord], unapplied: Sequence[tuple[int, LoopRegistration]]) -> None:
        """Continue from a checkpoint: `loops` are the run's records (the unapplied ones without
        their registration, as in the running system), `unapplied` their registrations, to be
        applied when due."""
        if self._pending or self._mirror:
            raise RuntimeError("LoopRegistrations.restore: only a fresh queue can be restored")
        found = dict(unapplied)
        self._mirror = [replace(r, registration=found[i]) if i in found else r for i, r in enumerate(loops)]
        self._sent = len(loops)
        for index, registration in unapplied:
            proposal = loops[index].proposal
            self._pending.append(_Pending(index, proposal, proposal.query_id + self.lag, (registration, 0.0)))

    def close(self) -> None:
        """End the worker (after the registrations already submitted)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=False)
            self._executor = None
