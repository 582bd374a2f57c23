"""Streaming loop-closure detection: one keyframe in, at most one proposal out.

Per keyframe: one backbone pass; stage I against the database minus an exclusion window
(the most recent keyframes and the last metres travelled, which always look alike); stage
II re-ranking of the candidates plus the places that continue the recent best sequences;
sequence matching over the last L keyframes (`SequenceMatcher`), whose score decides; the
optional top-1 `SequenceGate` on top; then the keyframe joins the database. A keyframe's rear
image, when it has one, runs the same stages against the same places with thresholds of its
own (`RearCameraConfig`) and its own sequence history; it is never added as a place. Without codebooks
the first keyframes are buffered, PCA is fitted on them, and querying starts afterwards.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from loopclosure.backbone import cube_dims
from loopclosure.blas import blas_limits_left_alone, one_blas_thread
from loopclosure.calibration import CalibratedDecision, PlaceLinks, RunnerUpModel
from loopclosure.config import DetectorConfig, VPRConfig, feature_side, grid_side
from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.device_search import check_search_device
from loopclosure.encoder import Encoder, PlaceCodes, RawCubes, per_image_cells
from loopclosure.errors import LoopClosureInputError
from loopclosure.filtering import Candidates
from loopclosure.pca import Codebooks
from loopclosure.saved_state import saved_finite, saved_ints
from loopclosure.sequence_gate import SequenceGate
from loopclosure.sequence_matcher import SequenceMatch, SequenceMatcher
from loopclosure.spatial_torch import stage2_scores, stage2_scores_many
from loopclosure.two_stage import Recognition, TwoStageRanker

log = logging.getLogger(__name__)

MIN_CALIBRATED_CANDIDATES = 30
"""Stage-I candidates below which the calibrated decision has too few to measure a winner against."""

RUNNER_UPS_KEY = "runner_ups"
"""PlaceDatabase.extra key of the runner-up models a database's session learnt."""
PLACE_LINKS_KEY = "place_links"
"""PlaceDatabase.extra key of the place pairs its session's accepted loops joined."""


@dataclass
class LoopProposal:
    """The best sequence match of one keyframe and the decision on it."""

    query_id: int
    match_id: int  # keyframe id (PlaceInfo.frame_id) of the matched place
    match_place: int  # database index of the matched place
    score: float  # single-frame stage-II score of the query against the matched place, in [0, 1]
    stage1_score: float
    column_shift: int  # dominant grid column displacement (query minus match)
    yaw_guess: float  # rad, rotation of the query about z relative to the match, from the shift
    accepted: bool
    reason: str
    direction: Literal["forward", "reverse"] | None = None  # of the winning sequence
    prior_map: bool = False  # the match comes from a database loaded from an earlier session
    sequence_score: float | None = (
        None  # stage-II scores along the sequence (centred on each keyframe's field when calibrated)
    )
    sequence_terms: int = 0  # keyframes of the sequence that could be compared (at most L)
    camera: Literal["front", "rear"] = "front"  # which of the keyframe's images matched the place
    decision_score: float | None = None  # calibrated decision: the winner's lead over the stream's runner-ups (z)
    runner_up_score: float | None = None  # calibrated decision: the best sequence away from the winner


@dataclass
class DetectorTimings:
    """Seconds spent per stage in the last `process` call."""

    backbone: float = 0.0
    database_query: float = 0.0
    spatial_matching: float = 0.0
    sequence_matching: float = 0.0  # the earlier keyframes' spatial scores and the aggregation
    gate: float = 0.0
    # the backbone's seconds for codes encoded ahead (`encode_ahead`), in the thread that ran them
    backbone_ahead: float = 0.0


@dataclass(frozen=True)
class EncodedKeyframe:
    """A keyframe's codes computed before its turn (`LoopDetector.encode_ahead`), so the backbone
    of keyframe k+1 runs while keyframe k is recognised. The same codes `process` would compute."""

    keyframe_id: int
    codes: PlaceCodes  # the forward image's, then the rear image's where `with_rear`
    with_rear: bool
    seconds: float  # the backbone pass and the projection, in the thread that ran them (no wait for the other's)


class LoopDetector:
    def __init__(
        self, vpr: VPRConfig, config: DetectorConfig, encoder: Encoder | None, database: PlaceDatabase | None = None
    ) -> None:
        """encoder: None for a detector that only matches stored codes (`match_stored`)."""
        check_search_device(vpr.filtering)  # before the first frame, not after the PCA warm-up
        if config.decision == "calibrated" and vpr.filtering.num_candidates < MIN_CALIBRATED_CANDIDATES:
            log.warning(
                "vpr.filtering.num_candidates is %d: the calibrated decision (detector.decision) measures a winner "
                "against the other candidates, and below %d it has too few (recall 0.49 on the demo at N=15)",
                vpr.filtering.num_candidates, MIN_CALIBRATED_CANDIDATES,
            )  # fmt: skip
        self.vpr = vpr
        self.config = config
        self._encoder = encoder
        self.database = database
        if database is not None and encoder is not None:
            encoder.codebooks = database.codebooks
        # the rear image's codes of each keyframe (`rear.keep_codes`), by keyframe id as PlaceInfo.frame_id
        self.rear_database: PlaceDatabase | None = None
        self.prior_places = len(database) if database is not None else 0
        self._recognizer = TwoStageRanker(vpr, database) if database is not None else None
        self.gate = SequenceGate(config.gate)
        # places [start_i, start_i+1) lie on one stretch of path: a sequence never runs across a seam
        # (a prior map's last place and the session's first; two traverses streamed one after the other)
        self._segment_starts: list[int] = [0] if self.prior_places == 0 else [0, self.prior_places]
        self._break_pending = False
        self.sequence = SequenceMatcher(config.sequence, self._score_places, self._segment_of, self._score_many)
        rear_sequence = config.sequence.model_copy(update={"direction": config.rear.direction})
        self.rear_sequence = SequenceMatcher(  # its own stream
            rear_sequence, self._score_places, self._segment_of, self._score_many
        )
        self.decision = CalibratedDecision(config.calibrated, config.calibrated.accept)  # the forward camera's
        self.rear_decision = CalibratedDecision(config.calibrated, config.rear_accept)
        self.links = PlaceLinks()
        # keyframes whose winner was measured against a level (the stream's model or its prior): a
        # stream with none was too short to decide anything, which a caller reports as such
        self.keyframes_judged = 0
        self._absolute_judged = 0
        # who joins the places of an accepted loop: the detector itself (used alone), or the caller
        # once the loop is registered (`join`: a SLAM back end, which refuses some)
        self.links_from_decisions = True
        if database is not None:  # a prior map brings the wrong-match model its session learnt
            self._seed_models(database.extra.get(RUNNER_UPS_KEY))
            self._seed_links(database.extra.get(PLACE_LINKS_KEY), len(database))
        self.timings = DetectorTimings()
        self._encoding = threading.Lock()  # one backbone pass at a time: ahead (`encode_ahead`) or inline
        # distance travelled when each session place was added, in order; it never decreases,
        # so the places too near to the query are always a suffix of the session
        self._session_travelled: list[float] = []
        self._place_of_keyframe: dict[int, int] = {}  # session keyframe id -> its place
        self._warmup: list[tuple[RawCubes, PlaceInfo, float, bool]] = []
        self._travelled = 0.0
        self._last_position: np.ndarray | None = None
        gw = grid_side(feature_side(vpr.backbone.stage2_layer, vpr.backbone.input_size), vpr.spatial.cubes)
        self._yaw_per_column = math.radians(config.camera_hfov_deg) / gw
        # read before the first frame: a wrong path or a codebook of other cubes is refused up front
        self._configured_codebooks = (
            self._load_codebooks(config.codebooks) if config.codebooks is not None and database is None else None
        )

    @classmethod
    def from_config(
        cls,
        vpr: VPRConfig | None = None,
        config: DetectorConfig | None = None,
        weights: str | Path | None = None,
        device: str | None = None,
        database: PlaceDatabase | None = None,
    ) -> LoopDetector:
        """A detector with its backbone and encoder built: the ECMR 2019 recognition settings and
        the default preset's decision unless given; weights as configured (a path,
        $SSMVPR_WEIGHTS, the cache, a download)."""
        from loopclosure.backbone import load_backbone
        from loopclosure.place_recognizer import configured

        vpr = configured(vpr, weights, device)
        return cls(vpr, config or DetectorConfig(), Encoder(vpr, load_backbone(vpr.backbone)), database)

    def _load_codebooks(self, path: str) -> Codebooks:
        """`detector.codebooks`, checked against the cube vectors this backbone and these cubes make."""
        try:
            books = Codebooks.load(path)
        except LoopClosureInputError as exc:
            raise LoopClosureInputError(f"detector.codebooks: {exc}") from None
        backbone, made_by = self.vpr.backbone, cube_dims(self.vpr)
        stages = (("stage1", books.stage1, backbone.stage1_layer, self.vpr.filtering.cubes),
                  ("stage2", books.stage2, backbone.stage2_layer, self.vpr.spatial.cubes))  # fmt: skip
        for name, book, layer, cubes in stages:
            made = made_by[name]
            if book.input_dim != made:
                raise LoopClosureInputError(
                    f"detector.codebooks: {path}: the {name} codebook takes {book.input_dim}-dim cube vectors, "
                    f"but {layer} in {cubes.cube_size}x{cubes.cube_size} cubes makes {made} (fitted with other settings)"
                )
        return books

    def _seed_models(self, saved: object) -> None:
        """Start the runner-up models from a prior map's (`annotate_database`): a session that
        starts in a mapped world is judged from its first keyframes by what wrong matches scored
        there (they count as its own: the prior does not apply), until its own runner-ups take
        over (the newest `history` count)."""
        if saved is None:
            return
        if not isinstance(saved, dict):
            raise LoopClosureInputError(f"prior map: extra.{RUNNER_UPS_KEY} must be an object, got {saved!r:.60}")
        for camera, decision in (("front", self.decision), ("rear", self.rear_decision)):
            values = np.asarray(saved.get(camera, []), dtype=object)
            try:
                numbers = values.astype(np.float64)
            except (TypeError, ValueError):
                numbers = np.array([np.nan])
            if numbers.ndim != 1 or not np.isfinite(numbers).all():
                raise LoopClosureInputError(f"prior map: extra.{RUNNER_UPS_KEY}.{camera} must be a list of numbers")
            for value in numbers.tolist()[-self.config.calibrated.history :]:
                decision.model.observe(value)

    def _seed_links(self, saved: object, n_places: int) -> None:
        """The prior map's places that its accepted loops made one (a place visited twice in the
        map is one place to the next session too, not each other's runner-up)."""
        if saved is None:
            return
        pairs = np.asarray(saved, dtype=object)
        try:
            pairs = pairs.astype(np.int64)
        except (TypeError, ValueError):
            pairs = np.array([[-1, -1]])
        if pairs.size == 0:
            return
        if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0 or pairs.max() >= n_places:
            raise LoopClosureInputError(f"prior map: extra.{PLACE_LINKS_KEY} must be pairs of its place indices")
        for a, b in pairs.tolist():
            self.links.join(a, b)

    def annotate_database(self) -> None:
        """Keep the runner-up models and the joined places with the database, so a later session
        that loads it as its prior map (`--map`) starts with them (see `_seed_models`)."""
        if self.database is not None:
            self.database.extra[RUNNER_UPS_KEY] = {
                "front": self.decision.model.state_arrays("")["runner_ups"].tolist(),
                "rear": self.rear_decision.model.state_arrays("")["runner_ups"].tolist(),
            }
            self.database.extra[PLACE_LINKS_KEY] = [list(pair) for pair in self.links.pairs]

    def join(self, proposal: LoopProposal) -> None:
        """Make the two places of a loop the caller accepted one (with `links_from_decisions`
        off). The query's place is its keyframe's (`place_of`)."""
        self._join_places(self.place_of(proposal.query_id), proposal.match_place)

    @property
    def has_encoder(self) -> bool:
        """False for a detector that only matches stored codes (`match_stored`)."""
        return self._encoder is not None

    @property
    def encoder(self) -> Encoder:
        if self._encoder is None:
            raise RuntimeError("this LoopDetector has no encoder: it matches stored codes only (match_stored)")
        return self._encoder

    def mark_segments(self, starts: list[int]) -> None:
        """The database's places from each of `starts` on continue no path before them (the
        sessions a merged map is made of): no sequence runs across one."""
        self._segment_starts = sorted({0, *(int(s) for s in starts)})

    def match_stored(self, front: PlaceCodes, keyframe_id: int, rear: PlaceCodes | None = None) -> LoopProposal | None:
        """Recognise a keyframe from codes stored by its own session (front, and rear when kept)
        with the same stages, sequences and decision as `process`, without adding it as a place:
        how one session's keyframes are matched against another's places."""
        self.timings = DetectorTimings()
        if self.database is None:
            raise RuntimeError("match_stored: the detector has no places to match against")
        return self._recognise(front, keyframe_id, rear)

    def _recognise(self, front: PlaceCodes, keyframe_id: int, rear: PlaceCodes | None) -> LoopProposal | None:
        """One keyframe's proposal: its forward codes, and its rear codes when it has them."""
        judged = self._judged_decisions()
        proposal = self._query(front, keyframe_id)
        if rear is not None:
            proposal = _preferred(proposal, self._query(rear, keyframe_id, rear=True))
        elif self.config.rear.enabled:
            self.rear_sequence.reset()  # a keyframe without its rear image breaks the rear sequence
        self.keyframes_judged += self._judged_decisions() > judged
        return proposal

    def _judged_decisions(self) -> int:
        return self.decision.judged + self.rear_decision.judged + self._absolute_judged

    def too_short_to_decide(self) -> str | None:
        """Why no keyframe was judged (None once one was): a stream too short for the PCA
        warm-up, or one whose keyframes never had enough places outside the exclusion window.
        A caller says so instead of reporting a bare recall of 0."""
        if self.keyframes_judged:
            return None
        config = self.config
        keyframes = len(self._session_travelled) + len(self._warmup)
        if not self.ready:
            return (f"recognition never started: the PCA warm-up takes {config.pca_warmup_keyframes} keyframes "
                    f"(detector.pca_warmup_keyframes) and the stream had {keyframes}")  # fmt: skip
        if config.decision == "calibrated":
            need = f"{config.calibrated.min_field} places or more (detector.calibrated.min_field)"
        else:
            need = "a place"
        return (f"no keyframe could be matched against {need}: the exclusion window keeps the last "
                f"{config.exclusion_keyframes} keyframes and {config.exclusion_distance:g} m out "
                f"(detector.exclusion_keyframes, detector.exclusion_distance) and the stream had {keyframes}")  # fmt: skip

    @property
    def ready(self) -> bool:
        """Codebooks exist and places are being matched (the PCA warm-up is over)."""
        return self.database is not None

    def break_sequence(self) -> None:
        """The next keyframe does not follow the last one along a path (a gap in the traverse, a
        second traverse streamed after the first): sequences start again from it, on both sides:
        no query's sequence reaches back across the gap, and no line runs along the places across it.
        The exclusion window does not reach back across it either, so the next keyframe may match
        any place before it: a PCA warm-up ends here if it has enough keyframes to fit on."""
        self.sequence.reset()
        self.rear_sequence.reset()
        self._break_pending = True
        # the next keyframe may match the ones before the seam: end a PCA warm-up that can end
        if self.database is None and self._can_fit():
            self._end_warmup()

    def _segment_of(self, places: np.ndarray) -> np.ndarray:
        return np.searchsorted(np.asarray(self._segment_starts, np.int64), places, side="right")

    def process(
        self,
        image: np.ndarray,
        keyframe_id: int,
        position: np.ndarray | None = None,
        timestamp: float = float("nan"),
        rear_image: np.ndarray | None = None,
        encoded: EncodedKeyframe | None = None,
    ) -> LoopProposal | None:
        """Recognise keyframe `keyframe_id` against earlier places, then add it as a place.

        A rear image (optional) is matched against the same places, never added: it is what
        recognises a street driven the other way. Both images go through one backbone pass.
        encoded: this keyframe's codes from `encode_ahead` (then no backbone pass here)."""
        self.timings = DetectorTimings()
        use_rear = self._uses_rear(rear_image)
        if encoded is not None and (
            encoded.keyframe_id != keyframe_id or encoded.with_rear != use_rear or self.database is None
        ):
            raise ValueError(f"keyframe {keyframe_id}: codes encoded ahead for keyframe {encoded.keyframe_id} "
                             f"({'with' if encoded.with_rear else 'without'} its rear image) do not belong to it")  # fmt: skip
        self._advance(position)
        start = time.perf_counter()
        info = PlaceInfo(frame_id=keyframe_id, timestamp=timestamp, extra={"session": "current"})
        if self.database is None:
            with self._encoding:
                raw = self.encoder.raw_cubes(
                    self._prepared(image, keyframe_id, rear_image=None)
                )  # PCA is fitted on these
            self.timings.backbone = time.perf_counter() - start
            self._warm_up(RawCubes(raw.stage1[:1], raw.stage2[:1]), info)
            return None
        if encoded is None:
            codes, _ = self._codes(image, keyframe_id, rear_image if use_rear else None)
        else:
            codes, self.timings.backbone_ahead = encoded.codes, encoded.seconds
        self.timings.backbone = time.perf_counter() - start
        rear_codes = codes[1] if use_rear else None
        if rear_codes is not None and self.config.rear.keep_codes:
            if self.rear_database is None:
                self.rear_database = PlaceDatabase(self.database.codebooks, self.vpr.database)
            self.rear_database.add(rear_codes, PlaceInfo(frame_id=keyframe_id, timestamp=timestamp))
        proposal = self._recognise(codes[0], keyframe_id, rear_codes)
        self._add(codes[0], info)
        return proposal

    def encode_ahead(
        self, image: np.ndarray, keyframe_id: int, rear_image: np.ndarray | None = None
    ) -> EncodedKeyframe | None:
        """The codes `process` would compute for this keyframe, computed now, in any thread, while
        earlier keyframes are still being recognised; None during the PCA warm-up, whose codebooks
        do not exist yet, and while an int8 backbone still calibrates on the stream's images
        (`process` then runs the backbone itself, in the stream's order).

        The codes depend only on the image and the codebooks, which never change once the warm-up
        has ended, so a keyframe gets the same codes ahead or inline: a run's results do not depend
        on which thread got there first."""
        if self.database is None:  # set after the codebooks: once it is, they are final
            return None
        if getattr(self.encoder.backbone, "calibrating_on_stream", False):  # its images in the stream's order
            return None
        start = time.perf_counter()
        use_rear = self._uses_rear(rear_image)
        with blas_limits_left_alone():  # the thread recognising may hold them
            codes, waited = self._codes(image, keyframe_id, rear_image if use_rear else None)
        return EncodedKeyframe(keyframe_id, codes, use_rear, time.perf_counter() - start - waited)

    def _uses_rear(self, rear_image: np.ndarray | None) -> bool:
        """Whether a keyframe's rear image is encoded and matched (it has nothing to match during
        the PCA warm-up, and is never needed where the rear camera is off)."""
        return rear_image is not None and self.config.rear.enabled and self.database is not None

    def _prepared(self, image: np.ndarray, keyframe_id: int, rear_image: np.ndarray | None) -> list[np.ndarray]:
        images = [self.encoder.prepare(image, f"keyframe {keyframe_id} image")]
        if rear_image is not None:
            images.append(self.encoder.prepare(rear_image, f"keyframe {keyframe_id} rear image"))
        return images

    def _codes(self, image: np.ndarray, keyframe_id: int, rear_image: np.ndarray | None) -> tuple[PlaceCodes, float]:
        """Both images' codes in one backbone pass (the rear one's where given), and the seconds
        spent waiting for the other thread's pass to end first."""
        images = self._prepared(image, keyframe_id, rear_image)
        asked = time.perf_counter()
        with self._encoding:
            waited = time.perf_counter() - asked
            return self.encoder.codes(images), waited

    # ---- state, for checkpoints: the database is saved on its own, the rest as plain arrays --
    def state_arrays(self) -> dict[str, np.ndarray]:
        """Everything besides the place database that the next `process` call depends on: the
        travelled distance per place, the gate's and both sequence matchers' recent queries, and
        the images an int8 backbone calibrated on from the stream.

        Only once the detector is `ready`: the PCA warm-up's raw cubes are megabytes per keyframe
        and are not saved, so a checkpoint waits until they have become codes."""
        if not self.ready or self._warmup:
            raise RuntimeError("LoopDetector.state_arrays: still in the PCA warm-up (nothing to resume from)")
        out = {
            "prior_places": np.array(self.prior_places, np.int64),
            "session_travelled": np.array(self._session_travelled, np.float64),
            "travelled": np.array(self._travelled, np.float64),
            "last_position": np.full(3, np.nan) if self._last_position is None else self._last_position.copy(),
            **self.gate.state_arrays(),
            **self.sequence.state_arrays("sequence_"),
            **self.rear_sequence.state_arrays("rear_sequence_"),
            **self.decision.model.state_arrays("model_"),
            **self.rear_decision.model.state_arrays("rear_model_"),
            **self.links.state_arrays(),
            "segment_starts": np.array(self._segment_starts, np.int64),
            "break_pending": np.array(self._break_pending),
            "keyframes_judged": np.array(self.keyframes_judged, np.int64),
        }
        calibration = self.encoder.backbone.stream_calibration()
        if calibration is not None:
            out["int8_stream_calibration"] = calibration[0]
            out["int8_stream_calibrated"] = np.array(calibration[1])
        return out

    def load_state_arrays(self, arrays: dict[str, np.ndarray], database: PlaceDatabase) -> None:
        """Continue from `state_arrays` with `database` (the places saved with it, in order)."""
        _check_state(arrays, len(database))  # before anything changes: a refused state leaves the detector as it was
        prior = int(arrays["prior_places"])
        travelled = arrays["session_travelled"].tolist()
        if len(database) != prior + len(travelled):
            raise LoopClosureInputError(
                f"detector state for {prior} prior + {len(travelled)} session places, database holds {len(database)}"
            )
        calibration = arrays.get("int8_stream_calibration")
        if calibration is not None:  # first: a state it refuses leaves the detector as it was
            self.encoder.backbone.resume_stream_calibration(calibration, bool(arrays["int8_stream_calibrated"]))
        elif self.encoder.backbone.calibrates_on_stream:  # a checkpoint written before it was kept
            log.warning(
                "the checkpoint does not hold the images int8 was calibrated on: it calibrates again on the next "
                "%d images (fp32 until then), so codes after the resume come from another int8 model",
                self.encoder.backbone.config.int8_calibration_images,
            )
        self.database = database
        self.encoder.codebooks = database.codebooks
        self.prior_places = prior
        self._recognizer = TwoStageRanker(self.vpr, database)
        self._session_travelled = travelled
        self._place_of_keyframe = {database.places[i].frame_id: i for i in range(prior, len(database))}
        self._travelled = float(arrays["travelled"])
        last = np.asarray(arrays["last_position"], np.float64)
        self._last_position = last.copy() if np.isfinite(last).all() else None
        self._warmup.clear()
        self.gate.load_state_arrays(arrays)
        self.sequence.load_state_arrays(arrays, "sequence_")
        self.rear_sequence.load_state_arrays(arrays, "rear_sequence_")
        self.decision.model.load_state_arrays(arrays, "model_")
        self.rear_decision.model.load_state_arrays(arrays, "rear_model_")
        self.links.load_state_arrays(arrays)
        self._segment_starts = np.asarray(arrays["segment_starts"], np.int64).tolist()
        self._break_pending = bool(arrays["break_pending"])
        self.keyframes_judged = int(arrays.get("keyframes_judged", 0))  # absent from states saved before it

    def _advance(self, position: np.ndarray | None) -> None:
        if position is None:
            return
        position = np.asarray(position, dtype=np.float64)
        if position.shape not in ((2,), (3,)):  # a 4x4 pose would have been read row by row
            raise LoopClosureInputError(
                f"keyframe position must be a 2- or 3-vector in metres, got shape {position.shape}"
            )
        if not np.isfinite(position).all():
            raise LoopClosureInputError(f"keyframe position is not finite: {position}")
        if self._last_position is not None:
            self._travelled += float(np.linalg.norm(position - self._last_position))
        self._last_position = position

    def travelled_at(self, place: int) -> float:
        """Metres driven, keyframe position to keyframe position, when session place `place` was added."""
        if not self.prior_places <= place < self.prior_places + len(self._session_travelled):
            raise ValueError(f"place {place} is not one of this session's places")
        return self._session_travelled[place - self.prior_places]

    def travelled_since(self, place: int) -> float:
        """Metres driven, keyframe position to keyframe position, from session place `place` to
        the latest keyframe: the path a loop to that place spans."""
        if not self.prior_places <= place < self.prior_places + len(self._session_travelled):
            raise ValueError(f"place {place} is not one of this session's places")
        return self._travelled - self._session_travelled[place - self.prior_places]

    def _warm_up(self, raw: RawCubes, info: PlaceInfo) -> None:
        """Buffer cubes until PCA can be fitted (or use configured codebooks at once)."""
        if self._configured_codebooks is not None:
            self.encoder.codebooks = self._configured_codebooks
        self._warmup.append((raw, info, self._travelled, self._break_pending))
        self._break_pending = False
        if self.encoder.codebooks is None and len(self._warmup) < self.config.pca_warmup_keyframes:
            return
        self._end_warmup()

    def _end_warmup(self) -> None:
        """Fit PCA on the buffered keyframes (unless codebooks were given) and make them places."""
        if self.encoder.codebooks is None:
            self.encoder.codebooks = self.encoder.fit_codebooks_from_raw([r for r, _, _, _ in self._warmup])
        self.database = PlaceDatabase(self.encoder.codebooks, self.vpr.database)
        self._recognizer = TwoStageRanker(self.vpr, self.database)
        pending = self._break_pending
        for raw_i, info_i, travelled, starts in self._warmup:
            self._break_pending = starts
            place = self._add(self.encoder.project(raw_i), info_i, travelled)
            self.gate.observe(place, None)
        self._break_pending = pending
        self._warmup.clear()

    def _can_fit(self) -> bool:
        """The buffered keyframes hold enough cube vectors for both PCA codebooks."""
        if not self._warmup:
            return False
        raw = self._warmup[0][0]
        vectors1 = raw.stage1.shape[1] * len(self._warmup)
        cells = int(np.prod(raw.stage2.shape[1:3]))
        vectors2 = min(cells, per_image_cells(self.vpr)) * len(self._warmup)
        return vectors1 >= self.vpr.filtering.pca.dim and vectors2 >= self.vpr.spatial.pca.dim

    def _add(self, codes: PlaceCodes, info: PlaceInfo, travelled: float | None = None) -> int:
        assert self.database is not None
        if self._break_pending and len(self.database) > self._segment_starts[-1]:
            self._segment_starts.append(len(self.database))
        self._break_pending = False
        place = self.database.add(codes, info)[0]
        self._session_travelled.append(self._travelled if travelled is None else travelled)
        self._place_of_keyframe[info.frame_id] = place
        return place

    def place_of(self, keyframe_id: int) -> int:
        """The database place of one of this session's keyframes (a keyframe that skipped
        recognition, `skip`, has none: places and keyframes then no longer count alike)."""
        try:
            return self._place_of_keyframe[keyframe_id]
        except KeyError:
            raise ValueError(f"keyframe {keyframe_id} is not one of this session's places") from None

    def skip(self, position: np.ndarray | None = None) -> None:
        """A keyframe handled without recognition (a run that fell behind its sensor): it becomes
        no place and proposes nothing, but the distance it moved still counts."""
        self.timings = DetectorTimings()
        self._advance(position)

    def _excluded(self) -> np.ndarray:
        """Session places too recent in keyframes or in travelled distance to be loop candidates."""
        n = len(self._session_travelled)
        first_recent = n - min(self.config.exclusion_keyframes, n)
        # near: travelled_now - travelled_place < exclusion_distance; a stream that never gave a
        # position has travelled nothing, so only its keyframe count can say what is recent
        first_near = (
            n
            if self._last_position is None
            else bisect.bisect_right(self._session_travelled, self._travelled - self.config.exclusion_distance)
        )
        # the window never reaches back across a seam: the places before it are another traverse,
        # not the same street a moment ago (two passes of a route streamed one after the other)
        seam = len(self.database) if self._break_pending and self.database is not None else self._segment_starts[-1]
        first = max(self.prior_places + min(first_recent, first_near), seam)
        return np.arange(first, self.prior_places + n, dtype=np.int64)

    def _score_places(self, grid: np.ndarray, places: np.ndarray) -> np.ndarray:
        """Stage-II scores of an earlier keyframe's grid against database places (sequence terms)."""
        assert self.database is not None
        return stage2_scores(grid, self.database.stage2[places], self.vpr).scores

    def _score_many(self, wanted: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
        """`_score_places` of several earlier keyframes at once (one device round trip on a GPU)."""
        assert self.database is not None
        return stage2_scores_many([(grid, self.database.stage2[places]) for grid, places in wanted], self.vpr)

    def _query(self, codes: PlaceCodes, keyframe_id: int, rear: bool = False) -> LoopProposal | None:
        """Stage I, stage II and sequence matching of one image of the keyframe."""
        assert self.database is not None
        timings = self.timings
        start = time.perf_counter()
        filtering = self.vpr.filtering
        excluded = self._excluded()
        # places [0, limit) may be matched: the exclusion window is always a suffix
        limit = int(excluded[0]) if len(excluded) else len(self.database)
        candidates = self.database.filter(codes.stage1[0], filtering.k_neighbours, filtering.num_candidates, excluded)
        timings.database_query += time.perf_counter() - start
        sequence = self.rear_sequence if rear else self.sequence
        # one BLAS thread for the many small products of stage II: right after the backbone pass
        # torch's threads hold the cores, and two BLAS threads were measured several times slower
        assert self._recognizer is not None  # built with the database
        with one_blas_thread():
            start = time.perf_counter()
            continued = sequence.continuations(limit)
            recognition = self._recognizer.rerank(codes, candidates, extra=continued)
            timings.spatial_matching += time.perf_counter() - start

            start = time.perf_counter()
            spatial = dict(zip(recognition.ranked_places.tolist(), recognition.spatial_scores.tolist()))
            field = np.array([spatial[p] for p in candidates.places.tolist()], np.float32)
            # calibrated: every score of this keyframe counts from its own field's level
            centre = float(field.mean(dtype=np.float64)) if self._calibrated and len(field) else 0.0
            match = sequence.step(
                codes.stage2[0], candidates.places, field, limit, continued,
                np.array([spatial[p] for p in continued.tolist()], np.float32), centre,
            )  # fmt: skip
            timings.sequence_matching += time.perf_counter() - start

        start = time.perf_counter()
        query_place = len(self.database)  # the gate and the links work in place indices: unique across sessions
        if rear:
            decided = self._decide(match, centre, field, rear=True)
            proposal = None
            if decided is not None:
                accepted, reason, z, second = decided
                proposal = self._proposal(match, recognition, candidates, keyframe_id, accepted,
                                          f"rear camera {reason}", "rear", z, second, centre)  # fmt: skip
                self._link(proposal, query_place)
            timings.gate += time.perf_counter() - start
            return proposal

        top1 = recognition.best_place
        if not self._calibrated and recognition.best_score < self.config.min_score:
            top1 = None
        decided = self._decide(match, centre, field)
        if decided is None:
            self.gate.observe(query_place, top1)
            timings.gate += time.perf_counter() - start
            return None
        accepted, reason, z, second = decided
        if accepted and self.config.gate.enabled:  # the top-1 consistency check, on request
            assert match.place is not None  # a decision was made on it
            decision = self.gate.decide(query_place, match.place)
            accepted = decision.accepted
            reason = (
                f"{reason}; top-1 gate: {decision.reason}"
                if accepted
                else f"top-1 gate rejects: {decision.reason}; {reason}"
            )
        self.gate.observe(query_place, top1)  # the gate judges each keyframe's own top-1 recognition
        proposal = self._proposal(match, recognition, candidates, keyframe_id, accepted, reason, "front", z, second,
                                  centre)  # fmt: skip
        self._link(proposal, query_place)
        timings.gate += time.perf_counter() - start
        return proposal

    @property
    def _calibrated(self) -> bool:
        return self.config.decision == "calibrated"

    def _link(self, proposal: LoopProposal, query_place: int) -> None:
        """An accepted loop makes its two places one (see `CalibratedDecisionConfig.link_accepted`)."""
        if proposal.accepted and self.links_from_decisions:
            self._join_places(query_place, proposal.match_place)

    def _join_places(self, a: int, b: int) -> None:
        if self._calibrated and self.config.calibrated.link_accepted:
            self.links.join(a, b)

    def _decide(
        self, match: SequenceMatch, centre: float, field: np.ndarray, rear: bool = False
    ) -> tuple[bool, str, float | None, float | None] | None:
        """(accepted, reason, calibrated z, runner-up) of the winning sequence, or None when it is not
        worth a proposal."""
        if self._calibrated:
            return self._decide_calibrated(match, centre, field, rear)
        threshold, min_single, floor = (
            (self.config.rear.accept_score, self.config.rear.min_single_score, self.config.rear.min_score)
            if rear
            else (self.config.accept_threshold, self.config.min_single_score, self.config.min_score)
        )
        if match.place is None:
            return None
        self._absolute_judged += 1
        if match.score < floor:
            return None
        accepted, reason = self._decide_absolute(match, threshold, min_single)
        return accepted, reason, None, None

    def _decide_calibrated(
        self, match: SequenceMatch, centre: float, field: np.ndarray, rear: bool
    ) -> tuple[bool, str, float | None, float | None] | None:
        """The winner's lead over this camera's runner-ups (`CalibratedDecision`)."""
        if match.place is None:
            return None
        joined = self.links.joined(match.place) if self.config.calibrated.link_accepted else set()
        verdict = (self.rear_decision if rear else self.decision).decide(match, field, joined)
        if verdict is None:
            return None
        detail = self._detail(match, centre)
        if verdict.accepted:
            accept = self.config.rear_accept if rear else self.config.calibrated.accept
            reason = f"accepted: calibrated score {verdict.z:.2f} >= {accept:g} {detail}"
        else:
            reason = f"{verdict.why}: calibrated score {verdict.z:.2f} {detail}"
        return verdict.accepted, reason, verdict.z, verdict.runner_up

    def _detail(self, match: SequenceMatch, centre: float = 0.0) -> str:
        """What the decision looked at; the single-frame score as stage II gave it (not centred)."""
        speed = f", speed {match.speed:g}" if len(self.config.sequence.speeds) > 1 else ""
        return (f"({match.terms}/{self.config.sequence.length} keyframes, {match.direction}{speed}); "
                f"single frame {match.single_score + centre:.3f}")  # fmt: skip

    def _proposal(
        self, match: SequenceMatch, recognition: Recognition, candidates: Candidates, keyframe_id: int,
        accepted: bool, reason: str, camera: Literal["front", "rear"] = "front", z: float | None = None,
        second: float | None = None, centre: float = 0.0,
    ) -> LoopProposal:  # fmt: skip
        assert self.database is not None and match.place is not None
        best = match.place
        ranked = int(np.flatnonzero(recognition.ranked_places == best)[0])
        shift = int(recognition.ranked_shifts[ranked][1])
        yaw = shift * self._yaw_per_column
        if camera == "rear":  # the rear camera looks along -x: the body is turned half a circle from it
            yaw = math.remainder(yaw + math.pi, 2.0 * math.pi)
        in_stage1 = candidates.places == best
        return LoopProposal(
            query_id=keyframe_id,
            match_id=self.database.places[best].frame_id,
            match_place=best,
            score=match.single_score + centre,  # the raw stage-II score, whatever the decision centred
            stage1_score=float(candidates.scores[in_stage1][0]) if np.any(in_stage1) else 0.0,
            column_shift=shift,
            yaw_guess=yaw,
            accepted=accepted,
            reason=reason,
            direction=match.direction,
            prior_map=best < self.prior_places,
            sequence_score=match.score,
            sequence_terms=match.terms,
            camera=camera,
            decision_score=z,
            runner_up_score=second,
        )

    def _decide_absolute(self, match: SequenceMatch, threshold: float, min_single: float) -> tuple[bool, str]:
        """Accept on the raw sequence score; the reason says what was compared."""
        detail = self._detail(match)
        if match.score < threshold:
            return False, f"sequence score {match.score:.3f} < {threshold:.3f} {detail}"
        if match.single_score < min_single:
            return False, (f"single frame {match.single_score:.3f} < {min_single:.3f}: "
                           f"sequence score {match.score:.3f} {detail.split(';')[0]}")  # fmt: skip
        return True, f"accepted: sequence score {match.score:.3f} >= {threshold:.3f} {detail}"


def _preferred(front: LoopProposal | None, rear: LoopProposal | None) -> LoopProposal | None:
    """One proposal per keyframe: an accepted one before a rejected one, then the forward camera
    (its scores are the more telling: a forward revisit sees the place from the same lane)."""
    if rear is None:
        return front
    if front is None:
        return rear
    return rear if rear.accepted and not front.accepted else front


def _check_state(arrays: dict[str, np.ndarray], n_places: int) -> None:
    """Refuse a saved detector state that would resume wrongly without an error: distances that
    are not finite or run backwards, matcher places outside the map, scores or tokens with NaN."""
    saved_ints(arrays, "prior_places", 0, n_places + 1)
    travelled = saved_finite(arrays, "session_travelled")
    if (
        travelled.ndim != 1
        or np.any(np.diff(travelled) < 0)
        or float(saved_finite(arrays, "travelled")) < (travelled[-1] if travelled.size else 0.0)
    ):
        raise LoopClosureInputError("detector state: the distances travelled run backwards")
    last = np.asarray(arrays["last_position"], np.float64)
    if last.shape != (3,) or not (np.isfinite(last).all() or np.isnan(last).all()):
        raise LoopClosureInputError(f"detector state last_position: expected 3 numbers (or NaN), got {last!r:.80}")
    for prefix in ("sequence_", "rear_sequence_"):
        SequenceMatcher.check_state_arrays(arrays, prefix, n_places)
    SequenceGate.check_state_arrays(arrays, n_places)
    for prefix in ("model_", "rear_model_"):
        RunnerUpModel.check_state_arrays(arrays, prefix)
    PlaceLinks.check_state_arrays(arrays, n_places)
    if "segment_starts" not in arrays or "break_pending" not in arrays:
        raise LoopClosureInputError("detector state has no segment_starts: it was saved before sequences knew "
                                    "seams (resume it with the version that wrote it)")  # fmt: skip
    starts = saved_ints(arrays, "segment_starts", 0, n_places + 1)
    if starts.ndim != 1 or not len(starts) or starts[0] != 0 or np.any(np.diff(starts) <= 0):
        raise LoopClosureInputError("detector state segment_starts: expected increasing place indices from 0")
    if np.asarray(arrays["break_pending"]).dtype != bool:
        raise LoopClosureInputError("detector state break_pending: expected true or false")
    if "keyframes_judged" in arrays:
        saved_ints(arrays, "keyframes_judged", 0, 1 << 62)
