"""How an accepted loop proposal becomes a registration (or is refused): the odometry gate (a
match facing the wrong way, or further than the odometry allows), a revisit's loops spaced out
by one registered a moment ago, ICP against a local map around the match, two views of the
images, and a loop no geometry verified admitted only when earlier loops of its revisit agree
(`loop_consistency`). The policy reads the run's keyframes and loops as the core hands them in,
so a run resumed from its checkpoint decides as the uninterrupted one did. The verdicts it gives
a loop it refuses or holds back (implausible, turned, spaced, unverified, confirmed) are written
here too: a loop's whole story reads in this module; `LoopRegistrar` only registers."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from loopclosure.detector import LoopDetector, LoopProposal
from loopclosure.pair_verifier import PairVerifier
from ssmvpr_slam.backend.config import LoopRegistrationConfig
from ssmvpr_slam.backend.loop_consistency import LoopPose, support
from ssmvpr_slam.backend.loop_registration import LoopRegistrar, LoopRegistration, build_local_map, carry_loop
from ssmvpr_slam.backend.se3 import yaw_of
from ssmvpr_slam.backend.two_view import ReducedImage
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.run_result import Keyframe, LoopRecord

# registrations whose T_mq says where the loop puts its two keyframes (a poor ICP alignment and an
# implausible loop do not)
_VERIFIED_METHODS = frozenset({"icp", "two_view_deep", "two_view_essential", "two_view_homography"})
_POSED_METHODS = _VERIFIED_METHODS | {"yaw_prior", "unverified", "spaced"}


class LoopPolicy:
    """`register(kf, proposal, keyframes, loops)`: the registration of one accepted proposal."""

    def __init__(self, config: SlamConfig, detector: LoopDetector, prior_map: PriorMap | None) -> None:
        self.registration_config = config.backend.registration
        self.odometry_kind = config.frontend.odometry.kind
        self.registrar = LoopRegistrar(self.registration_config, _deep_verifier(self.registration_config, detector))
        self.detector = detector
        self.prior_map = prior_map

    def register(
        self,
        kf: Keyframe,
        proposal: LoopProposal,
        keyframes: Sequence[Keyframe],
        loops: Sequence[LoopRecord],
        travelled_since: float,
    ) -> LoopRegistration:
        """ICP against a local map around the match when both have scans, else a place prior;
        none when the odometry puts the two keyframes too far apart (`odometry_gate`) or a
        recent ICP loop of the same revisit spaces this one out. travelled_since: the metres
        driven from the matched place to `kf`, taken when the proposal was made (a worker
        registers it while later keyframes move the detector on)."""
        if proposal.prior_map:
            return self._register_to_map(kf, proposal, keyframes, loops)
        match = keyframes[proposal.match_id]
        gate = self.registration_config.odometry_gate
        if gate.max_heading_deg is not None:
            odometry_yaw = yaw_of(np.linalg.inv(match.odom_pose)[:3, :3] @ kf.odom_pose[:3, :3])
            off = abs(math.degrees(math.remainder(proposal.yaw_guess - odometry_yaw, 2.0 * math.pi)))
            if off > gate.max_heading_deg:
                return turned(self.registration_config, proposal.yaw_guess, odometry_yaw)
        if self.odometry_kind in gate.sources:
            offset = float(np.linalg.norm(kf.odom_pose[:3, 3] - match.odom_pose[:3, 3]))
            if offset > gate.limit(travelled_since):
                return implausible(self.registration_config, offset, travelled_since)
        if kf.scan is not None and match.scan is not None:
            lidar = self.registration_config.lidar
            recent = self._carried(keyframes, loops, kf, match, lidar.loop_spacing_keyframes - 1)
            if recent is not None:  # registered a moment ago: the odometry carries it here
                record, carried = recent
                return spaced(self.registration_config, carried, record.proposal.query_id,
                                       record.proposal.match_id)  # fmt: skip
            half = lidar.local_map_half_window
            window = keyframes[max(0, match.id - half) : match.id + half + 1]
            with_scans = [(k.scan.points, k.odom_pose) for k in window if k.scan is not None]
            local_map = build_local_map(
                [scan for scan, _ in with_scans], [pose for _, pose in with_scans], match.odom_pose, lidar.max_range
            )
            seed = self._carried(keyframes, loops, kf, match, lidar.carry_loop_keyframes)
            return self.registrar.register_scans(
                kf.scan.points, local_map, proposal.yaw_guess, None if seed is None else seed[1]
            )
        return self._checked(
            keyframes, loops, kf, proposal, self._register_images(kf, match.image, proposal, "the matched keyframe")
        )

    def _register_images(
        self, kf: Keyframe, place_image: ReducedImage | None, proposal: LoopProposal, place: str
    ) -> LoopRegistration:
        """The keyframe's image (its rear one for a rear match: it saw what the place's forward
        camera saw) against the place's kept forward image; the yaw prior where either was not
        kept. place: what the place is, for the reason."""
        rear = proposal.camera == "rear"
        image = kf.rear_image if rear else kf.image
        if image is None:
            why = "rear camera match: no rear image kept" if rear else "the keyframe kept no image"
            return self.registrar.yaw_prior(proposal.yaw_guess, why)
        if place_image is None:
            return self.registrar.yaw_prior(proposal.yaw_guess, f"{place} kept no image")
        return self.registrar.register_images(image, place_image, proposal.yaw_guess, math.pi if rear else 0.0)

    def _checked(
        self,
        keyframes: Sequence[Keyframe],
        loops: Sequence[LoopRecord],
        kf: Keyframe,
        proposal: LoopProposal,
        registration: LoopRegistration,
    ) -> LoopRegistration:
        """A loop no geometry verified (a yaw prior) becomes a factor only as
        `two_view.on_geometry_failure` says: with `consistent`, once enough earlier loops of its
        revisit agree with it under odometry (`loop_consistency`), else it is refused. A loop whose
        views the deep features refused counts only loops a scan or two views verified: a stretch
        of look-alikes refused one by one agrees with itself under odometry (a parallel street)."""
        registration_config = self.registration_config
        if registration.method != "yaw_prior" or registration_config.two_view.on_geometry_failure != "consistent":
            return registration
        loop = self._loop_pose(keyframes, proposal, registration.T_mq)
        if loop is None:
            return unverified(registration_config, registration, 0)
        vouching = _VERIFIED_METHODS if registration.views_refused else _POSED_METHODS
        earlier = [
            e
            for r in loops
            if r.proposal.accepted
            and r.proposal.prior_map == proposal.prior_map
            and r.registration is not None
            and r.registration.method in vouching
            and (e := self._loop_pose(keyframes, r.proposal, r.registration.T_mq)) is not None
        ]
        agreeing = support(loop, earlier, registration_config.consistency)
        if agreeing < registration_config.consistency.min_support:
            return unverified(registration_config, registration, agreeing)
        return confirmed(registration, agreeing)

    def _loop_pose(self, keyframes: Sequence[Keyframe], proposal: LoopProposal, T_mq: np.ndarray) -> LoopPose | None:
        """The loop's ends for the consistency check (None: a prior-map place without a pose)."""
        kfs, detector = keyframes, self.detector
        if proposal.prior_map:
            pose = self.prior_map.pose(proposal.match_place) if self.prior_map is not None else None
            if pose is None:
                return None
            match_pose, match_travelled = pose, math.nan
        else:
            match_pose = kfs[proposal.match_id].odom_pose
            match_travelled = detector.travelled_at(detector.place_of(proposal.match_id))
        return LoopPose(
            proposal.query_id, proposal.match_place if proposal.prior_map else proposal.match_id,
            kfs[proposal.query_id].odom_pose, match_pose, T_mq,
            detector.travelled_at(detector.place_of(proposal.query_id)), match_travelled,
        )  # fmt: skip

    def _carried(
        self, keyframes: Sequence[Keyframe], loops: Sequence[LoopRecord], kf: Keyframe, match: Keyframe, reach: int
    ) -> tuple[LoopRecord, np.ndarray] | None:
        """A recent accepted ICP loop of this revisit (see `loop_to_carry`) and its T_mq moved
        to (match, kf) by odometry, else None. Read from the recorded loops, so a run resumed
        from its checkpoint carries on as the uninterrupted one."""
        record = loop_to_carry(loops, kf.id, match.id, reach)
        if record is None:
            return None
        assert record.registration is not None  # checked by loop_to_carry
        kfs, q, m = keyframes, record.proposal.query_id, record.proposal.match_id
        moved = carry_loop(record.registration.T_mq, kfs[m].odom_pose, kfs[q].odom_pose, match.odom_pose, kf.odom_pose)
        return record, moved

    def _register_to_map(
        self, kf: Keyframe, proposal: LoopProposal, keyframes: Sequence[Keyframe], loops: Sequence[LoopRecord]
    ) -> LoopRegistration:
        """ICP against the prior map's scans around the place, else two views of the keyframe and
        the place's kept image (a camera-only map), else the visual place prior."""
        place = proposal.match_place
        pose = self.prior_map.pose(place) if self.prior_map is not None else None
        if pose is None or self.prior_map is None:
            reason = "prior place has no pose in its map (its session was never anchored)"
            return LoopRegistration(np.eye(4), False, reason, np.nan, np.nan)
        lidar = self.registration_config.lidar
        parts = self.prior_map.neighbourhood(place, lidar.local_map_half_window)
        if kf.scan is not None and parts:
            scans, poses = zip(*parts)
            local_map = build_local_map(scans, poses, pose, lidar.max_range)
            return self.registrar.register_scans(kf.scan.points, local_map, proposal.yaw_guess)
        return self._checked(
            keyframes,
            loops,
            kf,
            proposal,
            self._register_images(
                kf, self.prior_map.images.front.get(place), proposal, "the prior-map place (no scans)"
            ),
        )


def _deep_verifier(config: LoopRegistrationConfig, detector: LoopDetector) -> PairVerifier | None:
    """The two-view verifier on the detector's own backbone (`two_view.method` deep), or None: ORB
    is asked for, or the detector matches stored codes and has no backbone."""
    if config.two_view.method != "deep" or not detector.has_encoder:
        return None
    return PairVerifier(detector.encoder.backbone, config.two_view.deep)


def _session_icp_loop(record: LoopRecord) -> bool:
    """An accepted ICP loop between two of the session's keyframes (what `_carried` carries on)."""
    reg = record.registration
    return reg is not None and reg.accepted and reg.method == "icp" and not record.proposal.prior_map


def loop_to_carry(loops: Sequence[LoopRecord], query_id: int, match_id: int, reach: int) -> LoopRecord | None:
    """The latest accepted ICP loop q -> m of the session with q at most `reach` keyframes before
    `query_id` and m within `reach` of `match_id`: the same revisit, a little further back.
    `loops` are in query order (as recorded, and as a resume replays them).

    Not simply the latest loop: where a street was driven twice before, a revisit's matches
    alternate between the two earlier visits (the demo's reverse streets: 533 -> 353,
    534 -> 115, 540 -> 348), so the latest loop often belongs to the other one."""
    for record in reversed(loops):
        q, m = record.proposal.query_id, record.proposal.match_id
        if query_id - q > reach:
            return None
        if q < query_id and abs(match_id - m) <= reach and _session_icp_loop(record):
            return record
    return None


_VERIFIED_ONLY = "the views refused it, so only loops a scan or two views verified count"
"""Said of a loop whose views the deep features refused (`LoopRegistration.views_refused`)."""

# ---- the verdicts: what the policy decided for a loop it did not (or not yet) let in, and why,
# naming the setting that decided; registration only registers


def spaced(config: LoopRegistrationConfig, carried: np.ndarray, query_id: int, match_id: int) -> LoopRegistration:
    """No registration: the accepted ICP loop query_id -> match_id of the same revisit is
    within `lidar.loop_spacing_keyframes`. Not a factor (accepted False); T_mq is that loop
    carried here by odometry (`carry_loop`), what the graph already implies."""
    spacing = config.lidar.loop_spacing_keyframes
    return LoopRegistration(
        T_mq=carried,
        accepted=False,
        reason=f"spaced: loop {query_id} -> {match_id} of this revisit is within {spacing} keyframes "
        "(backend.registration.lidar.loop_spacing_keyframes)",
        inlier_ratio=float("nan"),
        rmse=float("nan"),
        method="spaced",
    )


def implausible(config: LoopRegistrationConfig, offset_m: float, travelled_m: float) -> LoopRegistration:
    """No registration: odometry puts the two keyframes `offset_m` apart after `travelled_m`
    of driving between them, beyond what its drift explains (`odometry_gate`)."""
    gate = config.odometry_gate
    return _refused(
        f"implausible: odometry puts the keyframes {offset_m:.1f} m apart, beyond "
        f"{gate.limit(travelled_m):.1f} m ({gate.base_m:g} m + {gate.per_m_travelled:g} x {travelled_m:.0f} m "
        "driven between them; backend.registration.odometry_gate)"
    )


def turned(config: LoopRegistrationConfig, claimed_yaw: float, odometry_yaw: float) -> LoopRegistration:
    """No registration: the match says the query faces `claimed_yaw` relative to the place,
    the odometry says `odometry_yaw`, more than `odometry_gate.max_heading_deg` apart."""
    gate = config.odometry_gate
    return _refused(
        f"implausible: the match puts the heading at {math.degrees(claimed_yaw):.0f} deg to the place, "
        f"the odometry at {math.degrees(odometry_yaw):.0f} deg, more than {gate.max_heading_deg:g} deg apart "
        "(backend.registration.odometry_gate.max_heading_deg)"
    )


def unverified(config: LoopRegistrationConfig, prior: LoopRegistration, agreeing: int) -> LoopRegistration:
    """No factor: nothing verified the loop's geometry and too few earlier loops of its revisit
    agree with it (`consistency`). T_mq stays the place prior, for the loops after it to check against."""
    need = config.consistency.min_support
    only = f"; {_VERIFIED_ONLY}" if prior.views_refused else ""
    return replace(
        prior,
        accepted=False,
        reason=f"unverified: {agreeing} of the {need} earlier loops of the revisit needed agree "
        f"(backend.registration.consistency{only}); {prior.reason}",
        sigmas=np.full(6, np.nan),
        method="unverified",
    )


def confirmed(prior: LoopRegistration, agreeing: int) -> LoopRegistration:
    """The place prior as a factor: `agreeing` earlier loops of the revisit vouch for it."""
    only = f" ({_VERIFIED_ONLY})" if prior.views_refused else ""
    return replace(prior, reason=f"{prior.reason}; {agreeing} earlier loops of the revisit agree{only}")


def _refused(reason: str) -> LoopRegistration:
    """A loop the odometry gate refuses before any registration: no pose, never a factor."""
    return LoopRegistration(
        T_mq=np.eye(4), accepted=False, reason=reason, inlier_ratio=float("nan"), rmse=float("nan"),
        method="implausible",
    )  # fmt: skip
