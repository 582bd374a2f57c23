"""One session's keyframes recognised among the other sessions' places, and verified.

The query session's stored codes go through the same detector as within a session: stage I
against every other session's places (one merged database, with a seam at each session's
start so no sequence runs across two), stage II, the sequence matcher and the calibrated
decision, its runner-up model seeded with what wrong matches scored on every session's stream,
the query session's own last (it weighs most). The forward camera finds streets driven the same way; the rear codes, where the
session kept them, find streets driven the other way. Each accepted proposal is registered
with ICP of the query keyframe's kept scan against a local map of the matched session's scans
around the place, in that session's frame; between sessions that kept images instead of scans
(camera-only runs), by two views the deep-feature verifier accepts (`register_cross_views`).
The relative start poses of two sessions are unknown, so nothing but the images and the scans
says where a loop puts them, and a loop no geometry verified never joins two sessions.
"""

from __future__ import annotations

import bisect
import functools
import math
from dataclasses import dataclass, replace

import numpy as np

from loopclosure.backbone import load_backbone
from loopclosure.config import BackboneConfig, VerifierConfig
from loopclosure.database import PlaceDatabase
from loopclosure.detector import PLACE_LINKS_KEY, RUNNER_UPS_KEY, LoopDetector, LoopProposal
from loopclosure.pair_verifier import PairVerifier
from ssmvpr_slam.backend.loop_registration import LoopRegistrar, LoopRegistration, build_local_map, carry_loop
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.multi_session.session_map import SessionMap


@dataclass(frozen=True)
class CrossLoop:
    """Keyframe `query_kf` of session `query` recognised as keyframe `match_kf` of session `match`
    (indices into the map's session list), with the registration that verified it (or not)."""

    query: int
    query_kf: int
    match: int
    match_kf: int
    proposal: LoopProposal
    registration: LoopRegistration

    @property
    def verified(self) -> bool:
        return self.registration.accepted

    @property
    def information(self) -> np.ndarray:
        """6x6 information of the loop factor (Pose3 tangent order), from the registration's sigmas."""
        return np.diag(1.0 / np.square(self.registration.sigmas))


def find_cross_loops(
    query_index: int, sessions: list[SessionMap], config: SlamConfig, verifier: PairVerifier | None = None
) -> list[CrossLoop]:
    """Accepted proposals of session `query_index`'s keyframes among the other sessions' places,
    each with its registration (accepted or not). verifier: the two-view verifier for sessions
    that kept images (`views_verifier`); without one, their loops stay unverified."""
    query = sessions[query_index]
    others = [k for k in range(len(sessions)) if k != query_index]
    if not others:
        return []
    merged, starts = PlaceDatabase.merged([sessions[k].places.database for k in others], config.vpr.database)
    merged.extra[RUNNER_UPS_KEY] = _runner_ups([sessions[k] for k in others] + [query])
    merged.extra[PLACE_LINKS_KEY] = merged_place_links([sessions[k] for k in others], starts)
    detector = LoopDetector(config.vpr, config.detector, None, merged)
    detector.mark_segments(starts)
    detector.links_from_decisions = False  # the query keyframes are never places here
    registrar = LoopRegistrar(config.backend.registration, verifier)
    rear_rows = query.places.rear_codes_by_keyframe()
    front_codes = query.places.database
    out: list[CrossLoop] = []
    for kf in range(len(query)):
        rear = None
        if query.places.rear is not None and kf in rear_rows:
            rear = query.places.rear.codes_of([rear_rows[kf]])
        proposal = detector.match_stored(front_codes.codes_of([kf]), kf, rear)
        if proposal is None or not proposal.accepted:
            continue
        which = bisect.bisect_right(starts, proposal.match_place) - 1
        match_index, match_kf = others[which], proposal.match_place - starts[which]
        match = sessions[match_index]
        guess = _carried(out, query, kf, match, match_index, match_kf, config)
        registration = register_cross_loop(query, kf, match, match_kf, proposal, registrar, config, guess)
        out.append(CrossLoop(query_index, kf, match_index, match_kf, proposal, registration))
    return out


def _carried(
    found: list[CrossLoop], query: SessionMap, kf: int, match: SessionMap, match_index: int, match_kf: int,
    config: SlamConfig,
) -> np.ndarray | None:  # fmt: skip
    """The guess for T_mq from the latest verified loop of the same revisit (the same other
    session, both ends a few keyframes back), each end carried by its own session's poses: ICP
    then starts where that loop left off instead of screening every yaw seed from zero (what a
    session does within itself, `carry_loop_keyframes`)."""
    reach = config.backend.registration.lidar.carry_loop_keyframes
    for loop in reversed(found):
        if kf - loop.query_kf > reach:
            return None
        if loop.match == match_index and loop.verified and abs(match_kf - loop.match_kf) <= reach:
            return carry_loop(loop.registration.T_mq, match.poses[loop.match_kf], query.poses[loop.query_kf],
                              match.poses[match_kf], query.poses[kf])  # fmt: skip
    return None


def merged_place_links(sessions: list[SessionMap], starts: list[int]) -> list[list[int]]:
    """The place pairs each session's accepted loops joined, in the indices of a database that
    merged the sessions' places from `starts` on: a place a session visited twice stays one place."""
    return [
        [start + int(a), start + int(b)]
        for session, start in zip(sessions, starts)
        for a, b in session.places.database.extra.get(PLACE_LINKS_KEY) or []
    ]


def _runner_ups(sessions: list[SessionMap]) -> dict[str, list[float]]:
    """The sessions' saved runner-up scores per camera, the last session's last: the decision
    judges a winner by what wrong matches scored in this city, the query session's own stream
    weighing most (the model keeps the newest); a short session borrows the others' warm-up."""
    out: dict[str, list[float]] = {"front": [], "rear": []}
    for session in sessions:
        saved = session.places.database.extra.get(RUNNER_UPS_KEY) or {}
        for camera in out:
            out[camera].extend(float(v) for v in saved.get(camera, []))
    return out


def register_cross_loop(
    query: SessionMap,
    query_kf: int,
    match: SessionMap,
    match_kf: int,
    proposal: LoopProposal,
    registrar: LoopRegistrar,
    config: SlamConfig,
    guess: np.ndarray | None = None,
) -> LoopRegistration:
    """ICP of the query keyframe's scan against the matched session's scans around the place
    (from `guess`, a carried T_mq, first when there is one); without scans on both sides, the
    two views (`register_cross_views`)."""
    lidar = config.backend.registration.lidar
    scan = query.places.scans.get(query_kf)
    anchor = match.places.pose(match_kf)
    parts = match.places.neighbourhood(match_kf, lidar.local_map_half_window)
    if scan is None or anchor is None or not parts:
        return register_cross_views(query, query_kf, match, match_kf, proposal, registrar)
    scans, poses = zip(*parts)
    local_map = build_local_map(scans, poses, anchor, lidar.max_range)
    return registrar.register_scans(scan, local_map, proposal.yaw_guess, guess)


def register_cross_views(
    query: SessionMap,
    query_kf: int,
    match: SessionMap,
    match_kf: int,
    proposal: LoopProposal,
    registrar: LoopRegistrar,
) -> LoopRegistration:
    """Two views of a loop between sessions that kept images instead of scans (camera-only runs),
    in the calibration the matched place's images were kept with. Verified only when the
    deep-feature verifier accepts the pair and gives its rotation (method `two_view_deep`): T_mq
    is then the place prior (the views' rotation, zero translation within
    `two_view.translation_sigma`). Anything less (the yaw prior a `run` falls back to, ORB) is
    no verification here: a loop between sessions is never taken on the images alone."""
    rear = proposal.camera == "rear"  # the query's rear camera saw what the place's forward camera saw
    query_image = (query.places.images.rear if rear else query.places.images.front).get(query_kf)
    match_image = match.places.images.front.get(match_kf)
    if query_image is None or match_image is None:
        return _unverified("no kept scans nor images on both sides to verify a cross-session loop")
    if registrar.verifier is None:
        return _unverified("no two-view verifier: between sessions images verify a loop by the deep features only "
                           "(backend.registration.two_view.method: deep)")  # fmt: skip
    two_view = match.places.images.two_view(match_kf, registrar.config.two_view)
    if two_view != registrar.config.two_view:
        registrar = LoopRegistrar(registrar.config.model_copy(update={"two_view": two_view}), registrar.verifier)
    registration = registrar.register_images(query_image, match_image, proposal.yaw_guess, math.pi if rear else 0.0)
    if registration.method == "two_view_deep":
        return registration
    return replace(registration, accepted=False, reason=f"two views did not verify it ({registration.reason})",
                   sigmas=np.full(6, np.nan), method="unverified")  # fmt: skip


def _unverified(why: str) -> LoopRegistration:
    """No geometry to check the loop with: never a join."""
    return LoopRegistration(np.eye(4), False, why, math.nan, math.nan, method="unverified")


def views_verifier(query_index: int, sessions: list[SessionMap], config: SlamConfig) -> PairVerifier | None:
    """The deep two-view verifier when session `query_index` and another session kept images (no
    scans) and `two_view.method` is deep, else None: a LiDAR map never loads a backbone for it.
    Loaded once per process (a Ray worker that runs several sessions' matching keeps it)."""
    two_view = config.backend.registration.two_view
    if two_view.method != "deep" or not sessions[query_index].places.images:
        return None
    if not any(s.places.images.front for k, s in enumerate(sessions) if k != query_index):
        return None
    return _loaded_verifier(config.vpr.backbone.model_dump_json(), two_view.deep.model_dump_json())


@functools.lru_cache(maxsize=1)
def _loaded_verifier(backbone: str, verifier: str) -> PairVerifier:
    return PairVerifier(
        load_backbone(BackboneConfig.model_validate_json(backbone)), VerifierConfig.model_validate_json(verifier)
    )
