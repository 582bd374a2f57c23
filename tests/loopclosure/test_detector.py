"""LoopDetector's bookkeeping without the CNN: PCA warm-up, the exclusion window (keyframes
and travelled distance), revisits decided on sequence scores (and the optional top-1 gate),
input checks and prior maps.

The backbone is a cheap fake with the real one's call signature: each distinct image gets its
own deterministic random conv maps of VGG16's shapes at input_size 224, so an identical image
is a perfect match (stage-II score 1) and distinct images are unrelated (scores near 0).
Recognition quality itself is tested with the real weights elsewhere.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_limits

from loopclosure.config import (
    CalibratedDecisionConfig,
    DetectorConfig,
    RearCameraConfig,
    SequenceGateConfig,
    SequenceMatchConfig,
    VPRConfig,
)
from loopclosure.database import PlaceDatabase
from loopclosure.detector import LoopDetector, LoopProposal
from loopclosure.encoder import Encoder
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks

WARMUP = 5
VPR = VPRConfig.model_validate({
    "filtering": {"pca": {"dim": 32}},  # 16 stage-I vectors per image: 5 images give 80 samples
    "spatial": {"pca": {"dim": 32, "l2_normalize_output": False}},
})  # fmt: skip


@pytest.fixture(autouse=True, scope="module")
def _one_blas_thread():  # noqa: ANN202
    # the PCA fits are small: on 2 shared cores, BLAS threads only fight each other (1.2 s vs 0.3 s);
    # scikit-learn/scipy bring their own BLAS, which must be loaded before it can be limited
    import sklearn.decomposition  # noqa: F401

    with threadpool_limits(limits=1):
        yield


class FakeBackbone:
    """(B, 224, 224, 3) uint8 -> (B, 512, 14, 14) conv5_2-like and (B, 512, 28, 28) conv4_2-like maps."""

    calibrates_on_stream = False
    device = torch.device("cpu")  # codes by numpy (vpr.backbone.projection: auto)

    def __init__(self) -> None:
        self.images = 0

    def stream_calibration(self) -> None:
        return None  # not int8: nothing a checkpoint must keep

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        assert images.dtype == np.uint8 and images.shape[1:] == (224, 224, 3)
        self.images += len(images)
        maps1, maps2 = [], []
        for image in images:
            seed = int.from_bytes(hashlib.sha1(image.tobytes()).digest()[:8], "little")
            rng = np.random.default_rng(seed)
            maps1.append(rng.standard_normal((512, 14, 14), dtype=np.float32))
            maps2.append(rng.standard_normal((512, 28, 28), dtype=np.float32))
        return np.stack(maps1), np.stack(maps2)


class SlowBackbone(FakeBackbone):
    """A pass that takes `seconds`."""

    def __init__(self, seconds: float) -> None:
        super().__init__()
        self.seconds = seconds

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        time.sleep(self.seconds)
        return super().__call__(images)


def scene(i: int) -> np.ndarray:
    """A small image that stands for place `i` (same i, same pixels)."""
    return np.random.default_rng([7, i]).integers(0, 256, (24, 32, 3), dtype=np.uint8)


def detector(
    database: PlaceDatabase | None = None,
    *,
    keyframes: int = 0,
    distance: float = 0.0,
    codebooks: str | None = None,
    direction: str = "both",
    accept: float = 0.9,
    rear: bool = True,
    decision: str = "absolute",
    warmup: int = WARMUP,
    **gate: object,
) -> LoopDetector:
    # identical images score 1 and unrelated ones about 0: a sequence of L = 3 scores about
    # 1/3 per matching keyframe, so 0.9 accepts only when all three match
    config = DetectorConfig(
        exclusion_keyframes=keyframes,
        exclusion_distance=distance,
        decision=decision,  # most tests plant exact scores for the absolute rule; calibrated ones say so
        calibrated=CalibratedDecisionConfig(min_history=5, history=50),
        min_score=0.2,
        accept_score=accept,
        min_single_score=0.5,
        pca_warmup_keyframes=warmup,
        codebooks=codebooks,
        sequence=SequenceMatchConfig(length=3, direction=direction),
        gate=SequenceGateConfig(**{"length": 3, "tolerance": 1, **gate}),
        rear=RearCameraConfig(
            enabled=rear, direction=direction, min_score=0.2, accept_score=accept, min_single_score=0.5
        ),
    )
    return LoopDetector(VPR, config, Encoder(VPR, FakeBackbone()), database)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def codebooks(tmp_path_factory: pytest.TempPathFactory) -> str:
    """PCA fitted once by a warm-up (a few seconds on 2 cores); most tests start from it."""
    det = detector()
    for k in range(WARMUP):
        det.process(scene(900 + k), k)
    path = tmp_path_factory.mktemp("codebooks") / "codebooks.npz"
    det.encoder.codebooks.save(path)
    return str(path)


def at(x: float) -> np.ndarray:
    return np.array([x, 0.0, 0.0])


def feed(
    det: LoopDetector, scenes: list[int], first_id: int, positions: list[float] | None = None
) -> list[LoopProposal | None]:
    out = []
    for k, s in enumerate(scenes):
        position = None if positions is None else at(positions[k])
        out.append(det.process(scene(s), first_id + k, position, timestamp=float(first_id + k)))
    return out


# ------------------------------------------------------------------------------- warm-up


def test_no_proposals_during_warmup_then_every_keyframe_is_a_place() -> None:
    det = detector()  # no codebooks, no exclusion at all
    backbone = det.encoder.backbone
    # keyframe 3 repeats keyframe 0 exactly: still nothing is proposed while PCA is not fitted
    results = feed(det, [0, 1, 2, 0], 0)
    assert results == [None] * 4
    assert not det.ready and det.database is None and det.encoder.codebooks is None
    assert det.process(scene(4), 4) is None  # the warm-up's last keyframe fits PCA
    assert det.ready and det.encoder.codebooks is not None
    assert len(det.database) == WARMUP
    assert [p.frame_id for p in det.database.places] == [0, 1, 2, 3, 4]
    assert backbone.images == WARMUP  # one backbone pass per keyframe, none repeated for the fit

    # the first query after the warm-up is recognised, but its sequence has no history yet:
    # the two missing terms count as 0
    proposal = det.process(scene(2), 5)
    assert proposal is not None
    assert proposal.query_id == 5 and proposal.match_id == proposal.match_place == 2
    assert proposal.score == pytest.approx(1.0)
    assert proposal.sequence_terms == 1 and proposal.sequence_score == pytest.approx(1 / 3)
    assert proposal.column_shift == 0 and proposal.yaw_guess == 0.0
    assert not proposal.accepted
    assert proposal.reason == "sequence score 0.333 < 0.900 (1/3 keyframes, forward); single frame 1.000"
    assert not proposal.prior_map
    assert len(det.database) == 6

    for k in range(6, 12):
        # unrelated keyframes; at most the tail of the last sequence is proposed, and refused
        p = det.process(scene(100 + k), k)
        assert p is None or (not p.accepted and p.score < 0.2)
        assert len(det.database) == k + 1
    assert backbone.images == 12
    assert [p.frame_id for p in det.database.places] == list(range(12))
    assert det.timings.backbone > 0 and det.timings.database_query >= 0 and det.timings.spatial_matching >= 0


def test_configured_codebooks_skip_the_warmup(codebooks: str) -> None:
    det = detector(codebooks=codebooks)
    assert det.process(scene(0), 0) is None  # the first keyframe only creates the database
    assert det.ready and len(det.database) == 1
    assert det.process(scene(1), 1) is None
    proposal = det.process(scene(0), 2)
    assert proposal is not None and proposal.match_place == 0 and proposal.score == pytest.approx(1.0)
    assert len(det.database) == 3


def test_configured_codebooks_that_cannot_serve_are_refused_before_the_first_keyframe(
    codebooks: str, tmp_path: Path
) -> None:
    with pytest.raises(LoopClosureInputError, match=r"^detector\.codebooks: PCA codebooks not found: .*nope\.npz"):
        detector(codebooks=str(tmp_path / "nope.npz"))
    junk = tmp_path / "junk.npz"
    junk.write_text("junk\n")
    with pytest.raises(LoopClosureInputError, match=r"not a PCA codebook file: .*junk\.npz \(neither an \.npz"):
        detector(codebooks=str(junk))
    books = Codebooks.load(codebooks)
    stage2 = books.stage2
    other_cubes = replace(stage2, mean=stage2.mean[:512], components=stage2.components[:, :512])  # 1x1 cubes
    other = tmp_path / "other_cubes.npz"
    Codebooks(books.stage1, other_cubes).save(other)
    made = 512 * VPR.spatial.cubes.cube_size**2
    with pytest.raises(
        LoopClosureInputError, match=rf"stage2 codebook takes 512-dim cube vectors, but conv4_2 .* makes {made}"
    ):
        detector(codebooks=str(other))
    detector(codebooks=codebooks)  # the fitted ones pass


def test_distinct_images_are_not_proposed(codebooks: str) -> None:
    det = detector(codebooks=codebooks)
    results = feed(det, list(range(30)), 0)
    assert results == [None] * 30  # below min_score: unrelated places are no loop candidates


# ------------------------------------------------------------------------------ exclusion


def test_recent_keyframes_are_never_candidates(codebooks: str) -> None:
    det = detector(codebooks=codebooks, keyframes=5)
    feed(det, list(range(20)), 0)
    # keyframe 15 is the 5th most recent place: excluded even though the image is identical
    for query_id, repeat in ((20, 19), (21, 17)):
        proposal = det.process(scene(repeat), query_id)
        assert proposal is None or (proposal.match_id != repeat and proposal.score < 0.5), proposal
    proposal = det.process(scene(15), 22)  # places 17..21 are the recent five now; 15 is not
    assert proposal is not None and proposal.match_id == 15 and proposal.score == pytest.approx(1.0)


def test_exclusion_window_boundary_in_keyframes(codebooks: str) -> None:
    det = detector(codebooks=codebooks, keyframes=5)
    feed(det, list(range(20)), 0)
    assert det.process(scene(15), 20) is None  # 5 keyframes back: inside the window
    proposal = det.process(scene(15), 21)  # 6 back now; its copy (place 20) is inside
    assert proposal is not None and proposal.match_place == 15


def test_control_without_exclusion_the_identical_recent_image_is_found(codebooks: str) -> None:
    # what the exclusion tests rule out really happens without the window
    det = detector(codebooks=codebooks)
    feed(det, list(range(20)), 0)
    proposal = det.process(scene(19), 20)
    assert proposal is not None and proposal.match_id == 19 and proposal.score == pytest.approx(1.0)


def test_places_within_the_travelled_distance_are_never_candidates() -> None:
    det = detector(distance=10.0)  # warm-up fitted here: its places' distances must be kept too
    feed(det, list(range(12)), 0, positions=[float(k) for k in range(12)])  # 1 m per keyframe
    # keyframe 12 at 12 m: warm-up place 3 was passed 9 m ago -> excluded
    proposal = det.process(scene(3), 12, at(12.0))
    assert proposal is None or proposal.match_place != 3
    # keyframe 13 at 13 m: place 3 is exactly 10 m back -> a candidate again (its copy, place 12, is not)
    proposal = det.process(scene(3), 13, at(13.0))
    assert proposal is not None and proposal.match_place == 3 and proposal.score == pytest.approx(1.0)
    # place 5 is 9 m behind keyframe 14 (the tail of the sequence through place 3 may be proposed)
    proposal = det.process(scene(5), 14, at(14.0))
    assert proposal is None or (proposal.match_place != 5 and not proposal.accepted)


def test_distance_window_counts_travel_not_keyframes(codebooks: str) -> None:
    det = detector(distance=10.0, codebooks=codebooks)
    # moving 1 m per keyframe, then standing still for 25 keyframes
    positions = [float(k) for k in range(5)] + [4.0] * 25
    feed(det, list(range(30)), 0, positions)
    # keyframes 8 and 9 are 21-22 keyframes old but 0 m away: still excluded
    assert det.process(scene(8), 30, at(4.0)) is None
    # 10 m further on they are candidates
    proposal = det.process(scene(9), 31, at(14.0))
    assert proposal is not None and proposal.match_place == 9 and proposal.score == pytest.approx(1.0)


def test_travelled_since_a_place_is_the_path_driven_from_it(codebooks: str) -> None:
    det = detector(codebooks=codebooks)
    feed(det, list(range(6)), 0, positions=[0.0, 1.0, 3.0, 3.0, 2.0, 5.0])  # back and forth: 1+2+0+1+3 m
    assert det.travelled_since(0) == pytest.approx(7.0)
    assert det.travelled_since(3) == pytest.approx(4.0) and det.travelled_since(5) == 0.0
    with pytest.raises(ValueError, match="place 6 is not one of this session's places"):
        det.travelled_since(6)


def test_position_none_does_not_advance_the_distance(codebooks: str) -> None:
    det = detector(distance=10.0, codebooks=codebooks)
    feed(det, list(range(10)), 0, positions=[0.0] * 10)
    assert det.process(scene(2), 10, None) is None  # no position: still 0 m travelled


def test_a_stream_without_positions_is_windowed_by_keyframes_alone(codebooks: str) -> None:
    det = detector(keyframes=5, distance=10.0, codebooks=codebooks)
    feed(det, list(range(10)), 0)  # never a position: the 10 m window cannot be measured
    proposal = det.process(scene(2), 10)
    assert proposal is not None and proposal.match_id == 2


@pytest.mark.parametrize("bad", [np.eye(4), np.zeros(4), np.zeros((1, 3)), np.zeros(1)])
def test_a_position_of_the_wrong_shape_is_an_input_error(bad: np.ndarray, codebooks: str) -> None:
    """A 4x4 pose passed as the position was read row by row: its first row became the position."""
    det = detector(distance=10.0, codebooks=codebooks)
    with pytest.raises(LoopClosureInputError, match=rf"2- or 3-vector in metres, got shape \({bad.shape[0]},"):
        det.process(scene(50), 0, bad)
    assert det.database is None or len(det.database) == 0  # nothing half-added
    det.process(scene(51), 0, np.array([1.0, 2.0]))  # a planar position is fine


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_position_is_an_input_error(bad: float, codebooks: str) -> None:
    det = detector(distance=10.0, codebooks=codebooks)
    feed(det, list(range(6)), 0, positions=[float(k) for k in range(6)])
    before = len(det.database)
    with pytest.raises(LoopClosureInputError, match="not finite"):
        det.process(scene(50), 6, np.array([1.0, bad, 0.0]))
    assert len(det.database) == before  # nothing half-added
    # and the stream carries on from where it was
    det.process(scene(51), 6, at(6.0))
    assert len(det.database) == before + 1


# ------------------------------------------------------------------------ revisits + sequences


def test_revisit_beyond_the_window_is_accepted_on_sequence_scores_forward_then_reverse(codebooks: str) -> None:
    det = detector(keyframes=5, distance=10.0, codebooks=codebooks)
    first_pass = list(range(20))
    results = feed(det, first_pass, 0, positions=[2.0 * k for k in range(20)])
    assert all(r is None for r in results)

    # forward revisit of places 5..8, two new places, then a reverse revisit of 15..12
    revisit = [5, 6, 7, 8, 50, 51, 15, 14, 13, 12]
    results = feed(det, revisit, 20, positions=[100.0 + 2.0 * k for k in range(len(revisit))])
    proposals = results[:4] + results[6:]
    assert all(p is not None for p in proposals)
    assert [p.match_id for p in proposals] == revisit[:4] + revisit[6:]
    assert [p.query_id for p in proposals] == [20, 21, 22, 23, 26, 27, 28, 29]
    for p in proposals:
        assert p.score == pytest.approx(1.0) and p.stage1_score > 0 and not p.prior_map
        assert p.sequence_terms == 3
    # 1, 2, then 3 of the 3 keyframes match: the sequence score climbs past the threshold
    seq = [p.sequence_score for p in proposals]
    assert seq[2] == seq[3] == seq[6] == seq[7] == pytest.approx(1.0)
    assert 0.3 < seq[0] < 0.5 and 0.6 < seq[1] < 0.8 and 0.3 < seq[4] < 0.5 and 0.6 < seq[5] < 0.8
    assert [p.accepted for p in proposals] == [False, False, True, True, False, False, True, True]
    assert [p.direction for p in proposals][1:4] == ["forward"] * 3
    assert [p.direction for p in proposals][5:] == ["reverse"] * 3
    assert proposals[0].reason.startswith(f"sequence score {seq[0]:.3f} < 0.900 (3/3 keyframes, ")
    assert proposals[3].reason == "accepted: sequence score 1.000 >= 0.900 (3/3 keyframes, forward); single frame 1.000"
    assert proposals[7].reason == "accepted: sequence score 1.000 >= 0.900 (3/3 keyframes, reverse); single frame 1.000"
    # after the forward revisit, its sequence runs on for L-1 keyframes that no longer match
    for tail in results[4:6]:
        assert tail is None or (not tail.accepted and tail.score < 0.2)
    assert len(det.database) == 30


def test_a_sequence_that_has_ended_is_not_carried_onto_a_new_place(codebooks: str) -> None:
    det = detector(keyframes=5, accept=0.6, codebooks=codebooks)
    feed(det, list(range(20)), 0)
    proposals = feed(det, [5, 6, 7, 50], 20)
    assert [p.accepted for p in proposals[:3]] == [False, True, True]
    tail = proposals[3]  # places 5..7 continue to 8, but keyframe 23 shows a new place
    assert tail.match_place == 8 and tail.sequence_score == pytest.approx(2 / 3, abs=0.05) and tail.score < 0.2
    assert not tail.accepted and tail.reason.startswith(f"single frame {tail.score:.3f} < 0.500: sequence score")


def test_reverse_revisit_not_accepted_when_only_forward_sequences_are_matched(codebooks: str) -> None:
    det = detector(keyframes=5, direction="forward", codebooks=codebooks)
    feed(det, list(range(20)), 0)
    proposals = feed(det, [12, 11, 10, 9], 20)
    assert proposals[0] is not None and proposals[0].match_id == 12
    assert not any(p.accepted for p in proposals if p is not None)
    assert all(p.direction == "forward" for p in proposals if p is not None)


def test_the_top1_gate_is_an_extra_check_on_request(codebooks: str) -> None:
    # a revisit of 5..12 with keyframe 23 unrecognisable (an occlusion): two of three keyframes
    # matching is enough for a sequence score of 2/3, not for the top-1 gate
    revisit = [5, 6, 7, 55, 9, 10, 11, 12]
    plain = detector(keyframes=5, accept=0.6, codebooks=codebooks)
    gated = detector(keyframes=5, accept=0.6, codebooks=codebooks, enabled=True)
    for det in (plain, gated):
        feed(det, list(range(20)), 0)
    without, with_gate = feed(plain, revisit, 20), feed(gated, revisit, 20)
    assert [p.accepted for p in without] == [False, True, True, False, True, True, True, True]
    assert [p.accepted for p in with_gate] == [False, False, True, False, False, False, True, True]
    assert with_gate[1].reason.startswith("top-1 gate rejects: keyframe 19 recognised nothing; accepted: sequence")
    assert with_gate[4].reason.startswith("top-1 gate rejects: keyframe 23 recognised nothing")
    assert "; top-1 gate: accepted: 2 predecessors consistent (forward)" in with_gate[6].reason


# ------------------------------------------------------------------------------ prior map


def test_prior_map_matches_are_flagged_and_not_excluded(tmp_path: Path, codebooks: str) -> None:
    first = detector(codebooks=codebooks)
    feed(first, list(range(10)), 0)
    first.database.save(tmp_path / "db")

    prior = PlaceDatabase.load(tmp_path / "db")
    assert len(prior) == 10
    # a huge exclusion window, standing still: only this session's places fall inside it
    det = detector(prior, keyframes=2, distance=1000.0)
    assert det.ready and det.encoder.codebooks is prior.codebooks
    proposals = feed(det, [3, 4, 5], 0, positions=[0.0] * 3)
    assert [p.match_place for p in proposals] == [3, 4, 5]
    assert [p.match_id for p in proposals] == [3, 4, 5]  # the earlier session's keyframe ids
    assert all(p.prior_map and p.score == pytest.approx(1.0) for p in proposals)
    assert [p.accepted for p in proposals] == [False, False, True]
    assert proposals[2].direction == "forward"
    assert len(det.database) == 13  # this session's keyframes join after the prior places
    assert det.database.places[10].frame_id == 0


def test_session_places_after_a_prior_map_are_not_flagged(tmp_path: Path, codebooks: str) -> None:
    first = detector(codebooks=codebooks)
    feed(first, list(range(10)), 0)
    first.database.save(tmp_path / "db")
    det = detector(PlaceDatabase.load(tmp_path / "db"), keyframes=2)
    feed(det, [50, 51, 52, 53], 0)
    proposal = det.process(scene(50), 4)
    assert proposal is not None
    assert proposal.match_place == 10 and proposal.match_id == 0 and not proposal.prior_map


# ------------------------------------------------------------------------------ rear camera


def drive_back(
    det: LoopDetector, first_id: int, fronts: list[int], rears: list[int | None]
) -> list[LoopProposal | None]:
    """Keyframes whose forward images are new places and whose rear images are `rears`."""
    return [
        det.process(scene(f), first_id + k, rear_image=None if r is None else scene(r))
        for k, (f, r) in enumerate(zip(fronts, rears))
    ]


def test_rear_images_recognise_a_street_driven_the_other_way(codebooks: str) -> None:
    det = detector(codebooks=codebooks, keyframes=5)
    feed(det, list(range(20)), 0)
    backbone = det.encoder.backbone
    before = backbone.images
    # driving back down places 14..11 (15..19 are inside the first query's exclusion window):
    # the forward camera sees new things, the rear one what the forward camera saw on the way out
    proposals = drive_back(det, 20, [200, 201, 202, 203], [14, 13, 12, 11])
    assert backbone.images - before == 8  # both images of every keyframe
    assert len(det.database) == 24  # rear images are queries only, never places
    assert [p.frame_id for p in det.database.places][20:] == [20, 21, 22, 23]
    accepted = [p for p in proposals if p is not None and p.accepted]
    assert [p.match_id for p in accepted] == [12, 11]  # once the rear sequence has three terms
    for p in accepted:
        assert p.camera == "rear" and p.direction == "reverse" and p.sequence_terms == 3
        assert p.yaw_guess == pytest.approx(np.pi) and p.reason.startswith("rear camera accepted")
    first = proposals[0]
    assert first is not None and first.camera == "rear" and not first.accepted and first.match_id == 14


def test_the_forward_camera_wins_when_both_are_accepted(codebooks: str) -> None:
    det = detector(codebooks=codebooks, keyframes=5)
    feed(det, list(range(20)), 0)
    # forward images repeat places 3..6, rear images repeat 14..11: both sequences accept
    proposals = drive_back(det, 20, [3, 4, 5, 6], [14, 13, 12, 11])
    assert [(p.camera, p.match_id) for p in proposals[2:]] == [("front", 5), ("front", 6)]


def test_rear_camera_switched_off_or_missing(codebooks: str) -> None:
    off = detector(codebooks=codebooks, keyframes=5, rear=False)
    feed(off, list(range(20)), 0)
    before = off.encoder.backbone.images
    assert drive_back(off, 20, [200, 201, 202, 203], [14, 13, 12, 11]) == [None] * 4
    assert off.encoder.backbone.images - before == 4  # the rear images are not even encoded

    gap = detector(codebooks=codebooks, keyframes=5)
    feed(gap, list(range(20)), 0)
    # a keyframe without its rear image breaks the rear sequence: it must build up again
    proposals = drive_back(gap, 20, [200, 201, 202, 203, 204], [14, 13, None, 11, 10])
    assert [p.match_id for p in proposals if p is not None and p.accepted] == []
    more = drive_back(gap, 25, [205], [9])
    assert more[0] is not None and more[0].accepted and more[0].match_id == 9


# ------------------------------------------------------------------------- state for checkpoints


def saved(det: LoopDetector, folder: Path) -> tuple[dict[str, np.ndarray], PlaceDatabase]:
    """The detector's state through an .npz as a checkpoint writes it, and its database through
    `folder`: what a resume reads back."""
    import io

    buffer = io.BytesIO()
    np.savez(buffer, **det.state_arrays())
    det.database.save(folder)
    buffer.seek(0)
    with np.load(buffer, allow_pickle=False) as data:
        state = {name: data[name] for name in data.files}
    return state, PlaceDatabase.load(folder)


def test_a_detector_restored_from_its_state_continues_exactly(tmp_path: Path, codebooks: str) -> None:
    """state_arrays + the saved database -> a new detector proposes what the first would have."""

    fronts = list(range(20)) + [3, 4, 5, 200, 201, 202, 203, 204, 6, 7]
    rears: list[int | None] = [None] * 20 + [None, None, None, 14, 13, 12, 11, None, None, None]
    positions = [float(k) for k in range(len(fronts))]

    def drive(det: LoopDetector, ks: range) -> list[LoopProposal | None]:
        return [det.process(scene(fronts[k]), k, at(positions[k]), float(k), None if rears[k] is None else scene(rears[k]))
                for k in ks]  # fmt: skip

    whole = drive(detector(codebooks=codebooks, keyframes=5, distance=2.0), range(len(fronts)))
    accepted = [(k, p.camera) for k, p in enumerate(whole) if p is not None and p.accepted]
    assert accepted == [(22, "front"), (25, "rear"), (26, "rear")]  # each needs its sequence's history

    for cut in (21, 24):  # inside the forward revisit, and inside the rear one
        first = detector(codebooks=codebooks, keyframes=5, distance=2.0)
        assert drive(first, range(cut)) == whole[:cut]
        second = detector(keyframes=5, distance=2.0)  # no codebooks: they come with the database
        second.load_state_arrays(*saved(first, tmp_path / f"db{cut}"))
        assert drive(second, range(cut, len(fronts))) == whole[cut:]


@pytest.mark.parametrize(
    ("damage", "fragment"),
    [
        (lambda a: a["sequence_q0_token"].flat.__setitem__(0, np.nan), "sequence_q0_token: expected finite"),
        (lambda a: a.__setitem__("sequence_q0_places", a["sequence_q0_places"] + 10_000), "sequence_q0_places"),
        (lambda a: a["session_travelled"].__setitem__(3, -5.0), "distances travelled run backwards"),
        (lambda a: a.__setitem__("travelled", np.array(np.nan)), "travelled: expected finite"),
        (lambda a: a.__setitem__("last_position", np.zeros(2)), "last_position: expected 3 numbers"),
        (lambda a: a.__setitem__("sequence_previous_forward", np.array([99_999])), "sequence_previous_forward"),
        (lambda a: a.__setitem__("model_runner_ups", np.array([0.1, np.inf])), "model_runner_ups: expected finite"),
        (lambda a: a.pop("rear_model_runner_ups"), "saved before calibrated decisions"),
        (lambda a: a.__setitem__("segment_starts", np.array([0, 5, 5])), "segment_starts: expected increasing"),
        (lambda a: a.__setitem__("place_links", np.array([[0, 99_999]])), "place_links"),
    ],
)
def test_a_damaged_state_is_refused_and_leaves_the_detector_as_it_was(damage, fragment: str, codebooks: str) -> None:  # noqa: ANN001
    """A checkpoint's detector.npz with NaN tokens or places outside the map resumed without an
    error (a tester found it); each is refused before the detector changes."""
    first = detector(codebooks=codebooks, keyframes=5, distance=2.0)
    for k in range(12):
        first.process(scene(k), k, at(float(k)), float(k))
    state = {name: np.array(value, copy=True) for name, value in first.state_arrays().items()}
    state.setdefault("sequence_previous_forward", np.array([0]))
    damage(state)
    second = detector(codebooks=codebooks, keyframes=5, distance=2.0)
    with pytest.raises(LoopClosureInputError, match=fragment):
        second.load_state_arrays(state, first.database)
    assert second.database is None and second.prior_places == 0


def test_no_state_during_the_warmup() -> None:
    det = detector()
    feed(det, [0, 1], 0)
    with pytest.raises(RuntimeError, match="warm-up"):
        det.state_arrays()


def test_rear_images_are_not_encoded_during_the_pca_warmup() -> None:
    det = detector()
    for k in range(WARMUP):
        assert det.process(scene(k), k, rear_image=scene(500 + k)) is None
    assert det.ready and det.encoder.backbone.images == WARMUP  # nothing to match them against yet
    det.process(scene(50), WARMUP, rear_image=scene(2))
    assert det.encoder.backbone.images == WARMUP + 2


def test_codes_encoded_ahead_give_what_process_would_have_computed() -> None:
    """`encode_ahead` (another thread's backbone pass for a later keyframe) gives nothing during
    the PCA warm-up, then the very codes `process` computes itself: fed them, a detector makes
    the same proposals, places and codes as one that encodes inline, with no backbone pass of
    its own; codes of another keyframe are refused."""
    fronts = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 3, 4, 5, 6, 20, 21, 8, 9]
    rears = [None, 500, None, 501, 502, None, 503, 504, 505, 506, 507, 508, None, 7, 6, 5, 4, 3]
    inline, ahead = detector(keyframes=3), detector(keyframes=3)
    expected, got = [], []
    for k, (f, r) in enumerate(zip(fronts, rears)):
        rear = None if r is None else scene(r)
        expected.append(inline.process(scene(f), k, at(float(k)), float(k), rear))
        encoded = ahead.encode_ahead(scene(f), k, rear)
        assert (encoded is None) == (k < WARMUP)
        images = ahead.encoder.backbone.images
        got.append(ahead.process(scene(f), k, at(float(k)), float(k), rear, encoded=encoded))
        if encoded is not None:
            assert ahead.encoder.backbone.images == images  # no pass of its own
            assert encoded.with_rear == (r is not None) and ahead.timings.backbone_ahead == encoded.seconds
    assert [p for p in got if p is not None] and got == expected
    assert any(p is not None and p.accepted and p.camera == "rear" for p in got)
    assert np.array_equal(ahead.database.codes_of(list(range(len(fronts)))).stage2,
                          inline.database.codes_of(list(range(len(fronts)))).stage2)  # fmt: skip
    assert ahead.encoder.backbone.images == inline.encoder.backbone.images
    pass_s = 0.05
    slow = ahead.encoder.backbone = SlowBackbone(pass_s)  # type: ignore[assignment]
    assert ahead.encode_ahead(scene(40), 40).seconds >= pass_s  # its time is the pass's, not only the wait's
    assert slow.images == 1
    other = ahead.encode_ahead(scene(30), 99)
    with pytest.raises(ValueError, match="keyframe 18: codes encoded ahead for keyframe 99"):
        ahead.process(scene(30), len(fronts), encoded=other)
    with pytest.raises(ValueError, match="without its rear image"):
        ahead.process(scene(30), 99, rear_image=scene(31), encoded=other)


# ------------------------------------------------------------------------- calibrated decision


def test_calibrated_revisit_is_accepted_and_unrelated_keyframes_are_not(codebooks: str) -> None:
    det = detector(keyframes=5, codebooks=codebooks, decision="calibrated", direction="forward")
    first = feed(det, list(range(40)), 0)
    assert not any(p is not None and p.accepted for p in first)  # no place seen twice
    assert len(det.decision.model) >= 5  # every query's runner-up taught the model
    revisit = feed(det, list(range(10, 20)), 40)
    accepted = [p for p in revisit if p is not None and p.accepted]
    assert len(accepted) >= 7
    for p in accepted:
        assert p.match_id == p.query_id - 30 and p.decision_score is not None and p.decision_score >= 6.0
        assert p.reason.startswith(f"accepted: calibrated score {p.decision_score:.2f} >= 6 ")
        assert p.score == pytest.approx(1.0, abs=1e-5)  # the raw single-frame score, not the centred one
        assert p.runner_up_score is not None and p.runner_up_score < p.sequence_score
    # the accepted loops joined their places
    assert det.links.joined(accepted[0].match_place) == {accepted[0].query_id}


def test_calibrated_single_frame_check_stops_a_sequence_carried_onto_a_new_place(codebooks: str) -> None:
    det = detector(keyframes=5, codebooks=codebooks, decision="calibrated", direction="forward")
    feed(det, list(range(40)), 0)
    proposals = feed(det, [10, 11, 12, 13, 14, 15, 300], 40)
    assert proposals[5] is not None and proposals[5].accepted
    tail = proposals[6]  # the line runs on to place 16, but keyframe 46 shows a new place
    assert tail is None or not tail.accepted


def test_a_break_starts_sequences_again_on_both_sides_of_the_seam(codebooks: str) -> None:
    """Two traverses of one route streamed one after the other: without the break, the first
    keyframes of the second would continue the first's last sequence, and lines would run from
    its places onto the first traverse's last ones."""
    det = detector(keyframes=5, codebooks=codebooks, decision="calibrated", direction="forward")
    feed(det, list(range(30)), 0)
    det.break_sequence()
    second = feed(det, list(range(30)), 30)
    assert det._segment_of(np.array([0, 29, 30, 59])).tolist() == [1, 1, 2, 2]
    for k, p in enumerate(second[:8]):
        if p is not None:
            assert p.sequence_terms <= k + 1  # nothing from before the break
    accepted = [p for p in second if p is not None and p.accepted]
    assert accepted and all(p.match_id == p.query_id - 30 for p in accepted)


def test_a_warmup_ends_at_a_seam_when_the_keyframes_so_far_suffice() -> None:
    """Two passes of one route, the first shorter than the warm-up: PCA is fitted at the seam
    on the first pass, so the second is recognised from its first keyframe on."""
    det = detector(warmup=50, decision="calibrated", direction="forward")
    feed(det, list(range(20)), 0)
    assert not det.ready
    det.break_sequence()
    assert det.ready and len(det.database) == 20  # the first pass became places, one segment
    second = feed(det, list(range(20)), 20)
    assert second[0] is not None and second[0].match_id == 0  # the first keyframe after the seam
    accepted = [p for p in second if p is not None and p.accepted]
    assert accepted and all(p.match_id == p.query_id - 20 for p in accepted)
    assert accepted[0].query_id <= 21  # an exact revisit is accepted at once, not after L keyframes
    assert det._segment_of(np.array([0, 19, 20, 39])).tolist() == [1, 1, 2, 2]


def test_a_seam_too_early_for_a_fit_keeps_the_warmup() -> None:
    det = detector(warmup=50)
    feed(det, [0], 0)  # one keyframe: 16 stage-I vectors, fewer than the 32 dimensions
    det.break_sequence()
    assert not det.ready and det.too_short_to_decide() is not None
    assert "recognition never started" in det.too_short_to_decide()  # type: ignore[operator]


def test_early_codebooks_round_trip_through_a_saved_map_and_a_resume(tmp_path: Path) -> None:
    """The stream's own codebooks, fitted after its first keyframes: saved with the places, a
    detector loaded from the map and the state continues exactly as the uninterrupted one."""

    scenes = list(range(12)) + list(range(12))
    make = lambda: detector(keyframes=3, decision="calibrated", direction="forward")  # noqa: E731
    uncut = make()
    whole = feed(uncut, scenes[:12], 0)
    uncut.break_sequence()
    whole += feed(uncut, scenes[12:], 12)
    assert any(p is not None and p.accepted for p in whole) and uncut.keyframes_judged > 0
    cut = 16
    first = make()
    feed(first, scenes[:12], 0)
    first.break_sequence()
    assert feed(first, scenes[12:cut], 12) == whole[:cut][12:]
    state, loaded = saved(first, tmp_path / "db")
    assert loaded.codebooks.same_as(first.encoder.codebooks)  # the map records the codes' codebooks
    second = make()  # no codebooks of its own: it takes the map's
    second.load_state_arrays(state, loaded)
    assert second.encoder.codebooks is loaded.codebooks
    assert feed(second, scenes[cut:], cut) == whole[cut:]
    assert second.keyframes_judged == uncut.keyframes_judged


@pytest.mark.parametrize("decision", ["absolute", "calibrated"])
def test_a_calibrated_detector_restored_from_its_state_continues_exactly(
    tmp_path: Path, codebooks: str, decision: str
) -> None:

    scenes = list(range(30)) + list(range(8, 20)) + [300, 301]
    det = lambda: detector(codebooks=codebooks, keyframes=5, decision=decision, direction="forward")  # noqa: E731
    uncut = det()
    whole = feed(uncut, scenes, 0)
    assert any(p is not None and p.accepted for p in whole)
    cut = 36
    first = det()
    assert feed(first, scenes[:cut], 0) == whole[:cut]
    second = detector(keyframes=5, decision=decision, direction="forward")
    second.load_state_arrays(*saved(first, tmp_path / "db"))
    assert feed(second, scenes[cut:], cut) == whole[cut:]
    assert second.links.pairs == uncut.links.pairs


def test_a_prior_map_seeds_the_runner_up_models_of_the_next_session(tmp_path: Path, codebooks: str) -> None:
    first = detector(keyframes=5, codebooks=codebooks, decision="calibrated", direction="forward")
    feed(first, list(range(30)), 0)
    first.annotate_database()
    first.database.save(tmp_path / "map")
    learnt = first.decision.model.state_arrays("")["runner_ups"]
    assert len(learnt) >= 5
    first.links.join(3, 25)  # as if an accepted loop had made places 3 and 25 one
    first.annotate_database()
    first.database.save(tmp_path / "map")
    second = detector(PlaceDatabase.load(tmp_path / "map"), keyframes=5, decision="calibrated", direction="forward")
    assert second.decision.model.ready  # from its first keyframe
    assert second.links.joined(25) == first.links.joined(25) and 3 in second.links.joined(25)
    np.testing.assert_array_equal(second.decision.model.state_arrays("")["runner_ups"], learnt)
    # a revisit of the map at once: accepted as soon as its sequence is long enough
    proposals = feed(second, list(range(10, 20)), 0)
    assert any(p is not None and p.accepted and p.prior_map for p in proposals[:6])


@pytest.mark.parametrize(
    ("key", "bad"),
    [
        ("runner_ups", {"front": [1.0, "x"]}),
        ("runner_ups", "nothing"),
        ("runner_ups", {"front": [float("nan")]}),
        ("place_links", [[0, 1, 2]]),
        ("place_links", [[0, 99]]),
        ("place_links", [["a", 1]]),
    ],
)
def test_a_prior_map_with_a_damaged_decision_record_is_refused(codebooks: str, key: str, bad: object) -> None:
    first = detector(keyframes=5, codebooks=codebooks, decision="calibrated")
    feed(first, list(range(12)), 0)
    first.database.extra[key] = bad
    with pytest.raises(LoopClosureInputError, match=f"prior map: extra.{key}"):
        detector(first.database, decision="calibrated")


def test_a_caller_that_registers_loops_joins_their_places_itself(codebooks: str) -> None:
    det = detector(keyframes=5, codebooks=codebooks, decision="calibrated", direction="forward")
    det.links_from_decisions = False  # as a SLAM run: places become one once the loop is registered
    feed(det, list(range(30)), 0)
    accepted = [p for p in feed(det, list(range(10, 20)), 30) if p is not None and p.accepted]
    assert accepted and det.links.pairs == []
    det.join(accepted[0])
    assert det.links.joined(accepted[0].match_place) == {accepted[0].query_id}


def test_too_few_candidates_for_the_calibrated_decision_is_one_warning(caplog: pytest.LogCaptureFixture) -> None:
    few = VPR.model_copy(update={"filtering": VPR.filtering.model_copy(update={"num_candidates": 15})})
    with caplog.at_level("WARNING", logger="loopclosure.detector"):
        LoopDetector(few, DetectorConfig(), Encoder(few, FakeBackbone()))  # type: ignore[arg-type]
        LoopDetector(few, DetectorConfig(decision="absolute"), Encoder(few, FakeBackbone()))  # type: ignore[arg-type]
    warnings = [r.getMessage() for r in caplog.records if "num_candidates" in r.getMessage()]
    assert len(warnings) == 1 and "vpr.filtering.num_candidates is 15" in warnings[0]


# ------------------------------------------------------------------ stored codes (`map`)


def test_another_sessions_stored_codes_are_recognised_as_its_images_would_be(codebooks: str) -> None:
    """A session's keyframes matched later from their stored codes (front, and rear kept with
    `rear.keep_codes`) against another session's places get the proposals their images would,
    without becoming places; a seam between two merged sessions stops sequences across it."""
    mapped = detector(codebooks=codebooks, keyframes=5)
    feed(mapped, list(range(30)), 0)
    session = detector(codebooks=codebooks, keyframes=5)
    session.config.rear.keep_codes = True
    # this session drives places 8..12 forward, then back down 25..22 (rear images), among new places
    fronts, rears = [500, 8, 9, 10, 11, 12, 501, 502, 503, 504], [None, 600, 601, 602, 603, 604, 25, 24, 23, 22]
    direct = detector(mapped.database.copy(), keyframes=5)
    by_images = [direct.process(scene(f), 100 + k, rear_image=None if r is None else scene(r))
                 for k, (f, r) in enumerate(zip(fronts, rears))]  # fmt: skip
    drive_back(session, 0, fronts, rears)
    assert session.rear_database is not None
    assert [p.frame_id for p in session.rear_database.places] == list(range(1, 10))  # none in keyframe 0's warm-up
    stored = LoopDetector(VPR, mapped.config, None, mapped.database.copy())
    rows = {p.frame_id: i for i, p in enumerate(session.rear_database.places)}
    by_codes = []
    for k in range(len(fronts)):
        rear = session.rear_database.codes_of([rows[k]]) if k in rows else None
        by_codes.append(stored.match_stored(session.database.codes_of([k]), 100 + k, rear))
    assert len(stored.database) == 30  # queries only
    accepted = [(p.camera, p.match_id) for p in by_codes if p is not None and p.accepted]
    assert accepted == [("front", 10), ("front", 11), ("front", 12), ("rear", 23), ("rear", 22)]
    assert accepted == [(p.camera, p.match_id) for p in by_images if p is not None and p.accepted]
    with pytest.raises(RuntimeError, match="stored codes only"):
        stored.process(scene(1), 999)


def test_no_sequence_runs_across_a_seam_between_merged_sessions(codebooks: str) -> None:
    mapped = detector(codebooks=codebooks, keyframes=5)
    feed(mapped, list(range(20)), 0)
    query_codes = mapped.database.codes_of(np.arange(8, 14))  # places 8..13 again
    joined = LoopDetector(VPR, mapped.config, None, mapped.database.copy())
    seamed = LoopDetector(VPR, mapped.config, None, mapped.database.copy())
    seamed.mark_segments([11])  # as if places 11.. were another session's
    through = [joined.match_stored(query_codes[k], 100 + k) for k in range(6)]
    cut = [seamed.match_stored(query_codes[k], 100 + k) for k in range(6)]
    assert [p.match_id for p in through if p is not None and p.accepted] == [10, 11, 12, 13]
    # at 11 and 12 the sequence would reach back across the seam: it starts again after it
    assert [p.match_id for p in cut if p is not None and p.accepted] == [10, 13]
