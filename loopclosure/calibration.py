"""The stream's model of wrong-match scores, learnt online from the runner-ups.

Why: SSM-VPR's spatial score depends on the scene's texture, the camera and the change of
condition between visits. A right match across day and night scores 0.26 on Gardens Point and a
wrong one in the simulated city scores the same, so no absolute threshold holds in both
worlds. What does hold is how far the winner stands above the matches that are certainly wrong
in the same stream: each query's runner-up, its best sequence away from the winner. Their
recent distribution (median and spread: twice the median absolute deviation) is the stream's
wrong-match model; a winner's calibrated score is its distance above the median in spreads. Shifting or
scaling every score of a stream changes neither (tested).

A stream has no runner-ups at its start, nor across a seam into a pass that nothing before it
could match, yet its first revisit may come at once. Until the stream has its own, a prior stands
in, stated in a unit every keyframe measures from the start: the spread (interquartile range) of
its own field, the stage-II scores of its stage-I candidates. The prior's median and spread of
runner-ups, in field spreads, bound the stream's own model from below: in full until the stream
has `prior_runner_ups` runner-ups of its own, then fading as they grow. The runner-ups of a
traverse's first streets come from a small database and are low: a street further on that
looks like them would stand far above them, though not above the runner-ups the grown map
gives later (docs/loop_decisions.md).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from loopclosure.config import CalibratedDecisionConfig, SequenceMatchConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.saved_state import saved_finite
from loopclosure.sequence_matcher import SequenceMatch, match_sequences


class RunnerUpModel:
    """The last `history` runner-up scores of one camera's stream and the calibrated score of a
    winner; while they are few, the prior in field spreads (see the module's docstring)."""

    def __init__(self, config: CalibratedDecisionConfig) -> None:
        self.config = config
        self._recent: deque[float] = deque(maxlen=config.history)
        self._fields: deque[float] = deque(maxlen=config.history)  # each deciding keyframe's field spread

    def __len__(self) -> int:
        return len(self._recent)

    @property
    def ready(self) -> bool:
        """A level to judge a winner by: the stream's runner-ups, or the prior's field spreads."""
        return self.level() is not None

    def _own(self) -> tuple[float, float] | None:
        """(median, spread) of the runner-ups, once there are `min_history` of them. The spread is
        the smaller of their interquartile range and twice their median absolute deviation: the
        two agree on a symmetric distribution, but the second holds while up to half the
        runner-ups are off (a young model whose first runner-ups came from a train standing at a
        station, each the same place again). It is never 0: a flat stream has no spread to
        measure leads in, so any lead above its level counts as far above."""
        if len(self._recent) < self.config.min_history:
            return None
        values = np.fromiter(self._recent, np.float64, len(self._recent))
        q1, median, q3 = np.percentile(values, [25.0, 50.0, 75.0])
        spread = min(float(q3 - q1), 2.0 * float(np.median(np.abs(values - median))))
        return float(median), max(spread, float(np.finfo(np.float32).eps) * max(1.0, abs(float(median))))

    def _prior_weight(self) -> float:
        """The prior's bounds hold in full until the stream has `prior_runner_ups` runner-ups of
        its own, then weigh prior_runner_ups / n: a half at twice as many, too little to matter
        once a model has grown."""
        if not self._fields or self.config.prior_runner_ups == 0:
            return 0.0
        return min(1.0, self.config.prior_runner_ups / max(len(self._recent), 1))

    def level(self) -> tuple[float, float] | None:
        """(median, spread) a winner is measured against; None while there is neither a model of
        the stream's own nor a field to scale the prior by."""
        own = self._own()
        weight = self._prior_weight()
        if weight == 0.0:
            return own
        unit = float(np.median(np.fromiter(self._fields, np.float64, len(self._fields))))
        median, spread = self.config.prior_median * unit * weight, self.config.prior_spread * unit * weight
        if own is not None:
            median, spread = max(median, own[0]), max(spread, own[1])
        return (median, spread) if spread > 0.0 else own

    def spread(self) -> float:
        level = self.level()
        if level is None:
            raise RuntimeError("RunnerUpModel.spread: no level yet (check `ready`)")
        return level[1]

    def score(self, winner: float) -> float | None:
        """(winner - median runner-up) / spread, or None while there is no level."""
        level = self.level()
        return None if level is None else (winner - level[0]) / level[1]

    def observe(self, runner_up: float) -> None:
        if not np.isfinite(runner_up):
            raise ValueError(f"runner-up score must be finite, got {runner_up}")
        self._recent.append(float(runner_up))

    def observe_field(self, field: np.ndarray) -> None:
        """A deciding keyframe's field: its interquartile range scales the prior."""
        values = np.asarray(field, np.float64)
        if values.size and np.isfinite(values).all():
            q1, q3 = np.percentile(values, [25.0, 75.0])
            self._fields.append(float(q3 - q1))

    # ---- state, for checkpoints -------------------------------------------------------------
    def state_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        return {
            f"{prefix}runner_ups": np.fromiter(self._recent, np.float64, len(self._recent)),
            f"{prefix}field_spreads": np.fromiter(self._fields, np.float64, len(self._fields)),
        }

    @staticmethod
    def check_state_arrays(arrays: dict[str, np.ndarray], prefix: str) -> None:
        name = f"{prefix}runner_ups"
        if name not in arrays:
            raise LoopClosureInputError(
                f"detector state has no {name}: it was saved before calibrated decisions "
                "(resume it with the version that wrote it)"
            )
        if saved_finite(arrays, name).ndim != 1:
            raise LoopClosureInputError(f"detector state {name}: expected a list of numbers")
        fields = f"{prefix}field_spreads"
        if fields in arrays and (saved_finite(arrays, fields).ndim != 1 or (arrays[fields] < 0).any()):
            raise LoopClosureInputError(f"detector state {fields}: expected a list of spreads (0 or more)")

    def load_state_arrays(self, arrays: dict[str, np.ndarray], prefix: str) -> None:
        """Restore what `state_arrays` saved; a state without field spreads (written before the
        prior) resumes with none: its model's own runner-ups decide."""
        self._recent.clear()
        self._recent.extend(np.asarray(arrays[f"{prefix}runner_ups"], np.float64).tolist())
        self._fields.clear()
        self._fields.extend(np.asarray(arrays.get(f"{prefix}field_spreads", ()), np.float64).tolist())


def runner_up(match: SequenceMatch, window: int, joined: Collection[int] = ()) -> float | None:
    """The best sequence score among the match's candidates farther than `window` places from
    its winner and from every place in `joined` (places an accepted loop made the same place);
    None when no candidate is that far."""
    if match.place is None:
        return None
    near = np.array(sorted({match.place, *joined}), np.int64)
    distance = np.abs(match.candidates[:, None] - near[None, :]).min(axis=1)
    far = distance > window
    return float(match.candidate_scores[far].max()) if far.any() else None


class PlaceLinks:
    """Places joined by accepted loops (union-find): the same place seen on several visits."""

    def __init__(self) -> None:
        self._parent: dict[int, int] = {}
        self._members: dict[int, set[int]] = {}
        self.pairs: list[tuple[int, int]] = []  # in the order they were joined (what a checkpoint keeps)

    def clear(self) -> None:
        self._parent.clear()
        self._members.clear()
        self.pairs.clear()

    def _root(self, place: int) -> int:
        root = place
        while self._parent.get(root, root) != root:
            root = self._parent[root]
        while place != root:  # path compression
            self._parent[place], place = root, self._parent.get(place, place)
        return root

    def join(self, a: int, b: int) -> None:
        self.pairs.append((int(a), int(b)))
        ra, rb = self._root(int(a)), self._root(int(b))
        if ra == rb:
            return
        members_a, members_b = self._members.pop(ra, {ra}), self._members.pop(rb, {rb})
        if len(members_a) > len(members_b):
            ra, rb, members_a, members_b = rb, ra, members_b, members_a
        self._parent[ra] = rb
        self._members[rb] = members_a | members_b

    def joined(self, place: int) -> set[int]:
        """The other places joined to `place`."""
        root = self._root(int(place))
        return self._members.get(root, {root}) - {int(place)}

    def state_arrays(self) -> dict[str, np.ndarray]:
        return {"place_links": np.array(self.pairs, np.int64).reshape(-1, 2)}

    @staticmethod
    def check_state_arrays(arrays: dict[str, np.ndarray], n_places: int) -> None:
        pairs = np.asarray(arrays.get("place_links", np.zeros((0, 2), np.int64)))
        if pairs.dtype.kind not in "iu" or pairs.ndim != 2 or pairs.shape[1] != 2:
            raise LoopClosureInputError(f"detector state place_links: expected (n, 2) place pairs, got {pairs!r:.80}")
        if pairs.size and (pairs.min() < 0 or pairs.max() >= n_places):
            raise LoopClosureInputError(f"detector state place_links: places outside 0..{n_places - 1}")

    def load_state_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        self.clear()
        for a, b in np.asarray(arrays.get("place_links", np.zeros((0, 2), np.int64))).tolist():
            self.join(a, b)


@dataclass(frozen=True)
class Verdict:
    """The calibrated decision on one winning sequence."""

    accepted: bool
    z: float  # the winner's lead over the stream's runner-ups, in their spreads
    single: float  # the keyframe's own centred score against the place, in the same spreads
    runner_up: float | None
    why: str  # what fell short ("" when accepted)


class CalibratedDecision:
    """One camera's calibrated decisions (the detector keeps one per camera; a batch replay of a
    stream, `decide_stream`, runs the same code)."""

    def __init__(self, config: CalibratedDecisionConfig, accept: float) -> None:
        self.config = config
        self.accept = accept
        self.model = RunnerUpModel(config)
        self.judged = 0  # winners measured against a level (the stream's model or the prior)

    def decide(self, match: SequenceMatch, field: np.ndarray, joined: Collection[int] = ()) -> Verdict | None:
        """The verdict on `match` (centred sequence scores), or None when it is not worth a
        proposal (no winner, no level yet, or below `propose`). `field`: the keyframe's stage-II
        scores of its stage-I candidates. A keyframe that could match fewer than `min_field`
        places decides nothing: a field of a few places neither scales the prior nor shows how
        far a winner stands out. The winner's runner-up joins the model afterwards, accepted or
        not: the next keyframe is judged by it."""
        if match.place is None:
            return None
        second = runner_up(match, self.config.runner_up_window, joined)
        z = None
        if len(field) >= self.config.min_field:
            self.model.observe_field(field)  # first: the first keyframe of a stream is judged by the prior
            z = self.model.score(match.score)
            self.judged += z is not None
        spread = self.model.spread() if z is not None else float("nan")
        if second is not None:
            self.model.observe(second)
        if z is None or z < self.config.propose:
            return None
        single = match.single_score / spread
        why = ""
        if z < self.accept:
            why = f"calibrated score {z:.2f} < {self.accept:g}"
        elif single < self.config.min_single:
            why = f"single frame {single:.2f} < {self.config.min_single:g} runner-up spreads"
        return Verdict(not why, z, single, second, why)


def decide_stream(
    scores: np.ndarray,
    candidates: Sequence[np.ndarray],
    limits: np.ndarray,
    sequence: SequenceMatchConfig,
    config: CalibratedDecisionConfig,
    place_segments: np.ndarray | None = None,
    query_segments: np.ndarray | None = None,
) -> list[tuple[SequenceMatch, Verdict | None]]:
    """The calibrated decisions of a whole stream from its dense (Q, R) stage-II score matrix, as
    the detector makes them one keyframe at a time (forward camera, without place links): each
    query's scores centred on the mean over its stage-I `candidates`, sequence matching, verdict."""
    centres = np.array([float(np.mean(scores[q, c], dtype=np.float64)) if len(c) else 0.0
                        for q, c in enumerate(candidates)])  # fmt: skip
    matches = match_sequences(scores, sequence, candidates, limits, centres, place_segments, query_segments)
    decision = CalibratedDecision(config, config.accept)
    return [(m, decision.decide(m, scores[q, candidates[q]])) for q, m in enumerate(matches)]
