"""Incremental pose graph over GTSAM iSAM2: odometry chain plus robust loop factors.

Conventions
-----------
* Poses are 4x4 float64 body-to-world matrices; one `Pose3` variable ``x<kf_id>`` per keyframe.
* A relative pose ``T_ij`` is the pose of keyframe j expressed in the frame of keyframe i,
  ``T_ij = inv(T_i) @ T_j`` (GTSAM's ``BetweenFactorPose3(i, j, T_ij)``, ``T_i.between(T_j)``).
* Sigmas are in Pose3 tangent order: (rx, ry, rz) in rad, then (tx, ty, tz) in m.
* A prior map (places of an earlier session, posed in that session's frame) joins through one
  anchor variable ``a0`` = the map frame expressed in this session's frame: a map place p
  becomes a node ``m<p>`` tied rigidly to the anchor at its map pose, and a loop to it is an
  ordinary robust loop factor. One map loop places the session in the map frame; more loops
  correct the session's trajectory against the (fixed) map.

Changes (keyframes, loops, loop removals) are queued and applied by `update()`; the read
methods (`optimized_poses`, `loop_residuals`) flush the queue first so they always describe
the current graph.

An iSAM2 step that fails (GTSAM's indeterminate-system error: with Cholesky, an odometry step of
some 3e4 m already loses the rotation's precision to the lever arm) leaves iSAM2 half-updated, so
`update()` never retries on it. It rebuilds iSAM2 from the graph's own records: first with QR
factorisation (the condition number is not squared; used from then on), then, should that fail
too, without the new loops, then also with the new keyframes' odometry edges cut (each starts a
segment held by a prior at its odometry guess). Each fallback is a `GraphRecovery` the caller warns
about; only when the last one fails too is a `PoseGraphError` raised, with the estimate so far kept.

Over 400 lines because the recovery ladder above and the prior-map anchor share the graph's own
records (keyframes, loops, removals) with the ordinary update: split apart, each would need its
own copy of them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NoReturn

import gtsam
import numpy as np

from ssmvpr_slam.backend import noise
from ssmvpr_slam.backend.config import PoseGraphConfig
from ssmvpr_slam.backend.g2o_io import GraphEdge, PoseGraphData
from ssmvpr_slam.backend.graph_optimizer import OptimizerSettings, optimize_graph
from ssmvpr_slam.backend.gtsam_errors import gtsam_reason
from ssmvpr_slam.backend.se3 import as_pose, relative
from ssmvpr_slam.errors import SlamError

_KEY_CHAR = "x"
_ANCHOR_KEY = gtsam.symbol("a", 0)
# The anchor is free until map loops fix it; a weak link to the keyframe of the first map
# loop only keeps the system well posed (and connected: iSAM2 fails on a component cut off
# by removals) should every map loop be removed again.
_ANCHOR_PRIOR_SIGMAS = np.array([1.0, 1.0, 1.0, 100.0, 100.0, 100.0])


def _key(kf_id: int) -> int:
    return gtsam.symbol(_KEY_CHAR, kf_id)


def _map_key(place: int) -> int:
    return gtsam.symbol("m", place)


def _loop_key(i: int, on_map: bool) -> int:
    """Variable of a loop's first end: a prior-map place node or a keyframe."""
    return _map_key(i) if on_map else _key(i)


class PoseGraphError(SlamError, RuntimeError):
    """iSAM2 could not take the graph's latest keyframes or loops, even after every fallback
    (a RuntimeError too, as GTSAM's own errors were before: callers catching that still do)."""


@dataclass(frozen=True)
class FinalSolve:
    """The final robust pass's answer; handles are `add_loop`'s."""

    poses: dict[int, np.ndarray]
    inliers: list[int]
    outliers: list[int]
    weights: dict[int, float]  # GNC's weight of each loop


@dataclass(frozen=True)
class GraphRecovery:
    """An iSAM2 step that failed and how the graph went on (the caller warns, naming frames)."""

    keyframes: tuple[int, ...]
    """Keyframes added in the failed step."""
    what: str
    """One line: what failed and what the graph did instead."""


def _isolation_text(cut: list[int], dropped: list[int]) -> str:
    """What the recovery cut and dropped, for its warning."""
    parts = []
    if cut:
        parts.append(f"keyframe(s) {', '.join(map(str, cut))} start a new graph segment (odometry edge cut)")
    if dropped:
        parts.append(f"{len(dropped)} new loop(s) dropped")
    return " and ".join(parts) or "re-solved with QR factorisation"


def _check_kf_id(name: str, kf_id: object) -> int:
    if isinstance(kf_id, bool) or not isinstance(kf_id, (int, np.integer)):
        raise ValueError(f"{name}: keyframe id must be an int, got {type(kf_id).__name__}")
    if kf_id < 0:
        raise ValueError(f"{name}: keyframe id must be >= 0, got {kf_id}")
    return int(kf_id)


@dataclass(frozen=True)
class LoopResidual:
    """How well the current estimate agrees with one loop factor."""

    handle: int
    i: int
    j: int
    chi2: float
    """Squared Mahalanobis distance of the (non-robust) factor error."""
    whitened_norm: float
    """sqrt(chi2): the quantity the robust kernel sees."""
    weight: float
    """Robust kernel weight at this error (1.0 without a kernel)."""


@dataclass
class _Edge:
    i: int
    j: int
    measured: np.ndarray
    gaussian: gtsam.noiseModel.Gaussian


@dataclass
class _Loop(_Edge):
    factor: gtsam.BetweenFactorPose3
    index: int | None = None  # iSAM2 factor index once applied
    on_map: bool = False  # i is a prior-map place, not a keyframe of this session

    @property
    def key_i(self) -> int:
        return _loop_key(self.i, self.on_map)


class PoseGraph:
    """Keyframe pose graph solved incrementally with iSAM2."""

    def __init__(self, config: PoseGraphConfig | None = None) -> None:
        self.config = config or PoseGraphConfig()
        self._factorization = "CHOLESKY"  # GTSAM's default; QR after a failed step (see the module docstring)
        self._isam = self._new_isam()
        self._kernel = noise.make_kernel(self.config.robust)
        self._odom: dict[int, np.ndarray] = {}
        self._order: list[int] = []
        self._prior: tuple[int, np.ndarray, gtsam.noiseModel.Base] | None = None
        self._odom_edges: list[_Edge] = []
        self._loops: dict[int, _Loop] = {}
        self._next_handle = 0
        self._pending_factors: list[tuple[gtsam.NonlinearFactor, int | None]] = []
        self._pending_values = gtsam.Values()
        self._pending_removals: list[int] = []
        self._estimate = gtsam.Values()
        self._map_places: dict[int, tuple[np.ndarray, gtsam.noiseModel.Base]] = {}
        self._anchor_initial: np.ndarray | None = None
        self._anchor_link: tuple[int, np.ndarray] | None = None
        # keyframes whose odometry edge iSAM2 could not take: a prior at their guess holds them
        # instead (the edge stays in `_odom_edges`, the record of what the odometry measured)
        self._segment_priors: dict[int, tuple[np.ndarray, gtsam.noiseModel.Base]] = {}
        self._failed: str | None = None
        self.recoveries: list[GraphRecovery] = []

    # ------------------------------------------------------------------ building
    @property
    def keyframe_ids(self) -> list[int]:
        """Keyframe ids in insertion order."""
        return list(self._order)

    @property
    def loop_handles(self) -> list[int]:
        """Handles of the loops currently in the graph (applied or queued)."""
        return list(self._loops)

    def loop_edge(self, handle: int) -> tuple[int, int, np.ndarray]:
        """(i, j, T_ij) of a loop."""
        loop = self._get_loop(handle)
        return loop.i, loop.j, loop.measured.copy()

    def solved_edges(self) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """(i, j, T_ij, 6x6 information) of each between factor on the session's keyframes that
        the graph solves: the odometry edges, less those a recovery cut (a prior at its guess
        holds such a keyframe instead), then the loops. What `pose_graph.g2o` lists, so that
        re-optimising the file optimises this graph, not one with the edge that broke iSAM2.
        Prior-map loops are left out: their first end is a map place, not a keyframe."""
        edges = [(e.i, e.j, e.measured.copy(), np.asarray(e.gaussian.information()))
                 for e in self._odom_edges if e.j not in self._segment_priors]  # fmt: skip
        edges += [(lp.i, lp.j, lp.measured.copy(), np.asarray(lp.gaussian.information()))
                  for lp in self._loops.values() if not lp.on_map]  # fmt: skip
        return edges

    @property
    def segment_starts(self) -> list[int]:
        """Keyframes whose odometry edge a recovery cut: each starts a new graph segment."""
        return sorted(self._segment_priors)

    def add_keyframe(self, kf_id: int, odom_pose: np.ndarray) -> None:
        """Add a keyframe with its odometry pose (body-to-world, odometry frame).

        The first keyframe is anchored by a prior at its odometry pose; each later one is
        linked to the previous keyframe by the odometry displacement between them. Ids must
        increase.
        """
        kf_id = _check_kf_id("kf_id", kf_id)
        pose = as_pose(f"odom_pose of keyframe {kf_id}", odom_pose, self.config.rotation_tolerance)
        if kf_id in self._odom:
            raise ValueError(f"kf_id: keyframe {kf_id} was already added")
        if self._order and kf_id <= self._order[-1]:
            raise ValueError(f"kf_id: keyframe ids must increase, got {kf_id} after {self._order[-1]}")
        key = _key(kf_id)
        if not self._order:
            pcfg = self.config.prior
            prior_noise = noise.gaussian(noise.sigmas6(pcfg.rot_sigma, pcfg.trans_sigma))
            self._prior = (kf_id, pose, prior_noise)
            prior = gtsam.PriorFactorPose3(key, gtsam.Pose3(pose), prior_noise)
            self._pending_factors.append((prior, None))
            self._pending_values.insert(key, gtsam.Pose3(pose))
        else:
            prev = self._order[-1]
            delta = relative(self._odom[prev], pose)
            odom_noise = noise.gaussian(self._odometry_sigmas(float(np.linalg.norm(delta[:3, 3]))))
            self._odom_edges.append(_Edge(prev, kf_id, delta, odom_noise))
            factor = gtsam.BetweenFactorPose3(_key(prev), key, gtsam.Pose3(delta), odom_noise)
            self._pending_factors.append((factor, None))
            guess = self._current_pose(prev) @ delta
            self._pending_values.insert(key, gtsam.Pose3(guess))
        self._odom[kf_id] = pose
        self._order.append(kf_id)

    def add_loop(
        self,
        i: int,
        j: int,
        T_ij: np.ndarray,
        sigmas: Sequence[float] | np.ndarray | None = None,
        information: np.ndarray | None = None,
    ) -> int:
        """Queue a robust loop factor saying keyframe j sits at ``T_ij = inv(T_i) @ T_j``.

        `sigmas` (6, tangent order) or `information` (6x6) override the configured loop noise;
        giving both is an error. Returns a handle for `remove_loop` and the residual reports.
        """
        i = _check_kf_id("i", i)
        j = _check_kf_id("j", j)
        for name, kf in (("i", i), ("j", j)):
            if kf not in self._odom:
                raise ValueError(f"{name}: keyframe {kf} has not been added")
        if i == j:
            raise ValueError(f"i, j: a loop needs two different keyframes, got {i} twice")
        measured = as_pose("T_ij", T_ij, self.config.rotation_tolerance)
        return self._queue_loop(i, j, measured, self._loop_noise(sigmas, information), on_map=False)

    def add_map_loop(
        self,
        place: int,
        place_pose: np.ndarray,
        j: int,
        T_pj: np.ndarray,
        sigmas: Sequence[float] | np.ndarray | None = None,
    ) -> int:
        """Queue a robust loop saying keyframe j sits at ``T_pj`` in the frame of prior-map
        place `place`, whose pose in the map frame is `place_pose`. Returns a loop handle."""
        place = _check_kf_id("place", place)
        j = _check_kf_id("j", j)
        if j not in self._odom:
            raise ValueError(f"j: keyframe {j} has not been added")
        pose = as_pose(f"place_pose of map place {place}", place_pose, self.config.rotation_tolerance)
        measured = as_pose("T_pj", T_pj, self.config.rotation_tolerance)
        if place in self._map_places and not np.allclose(self._map_places[place][0], pose, atol=1e-9):
            raise ValueError(f"place_pose: map place {place} was added before with another pose")
        if self._anchor_initial is None:
            # keyframe j solved first: creating the anchor in the same iSAM2 step as a new
            # keyframe with a loose (place prior) loop was reported indeterminate
            self._flush()
            # the first map loop fixes the anchor: map pose p @ T_pj is keyframe j's pose
            anchor = self._current_pose(j) @ np.linalg.inv(measured) @ np.linalg.inv(pose)
            self._anchor_initial = anchor
            self._pending_values.insert(_ANCHOR_KEY, gtsam.Pose3(anchor))
            self._anchor_link = (j, relative(self._current_pose(j), anchor))
            self._pending_factors.append((self._anchor_link_factor(), None))
        if place not in self._map_places:
            pcfg = self.config.prior
            rigid = noise.gaussian(noise.sigmas6(pcfg.rot_sigma, pcfg.trans_sigma))
            self._map_places[place] = (pose, rigid)
            self._pending_values.insert(_map_key(place), gtsam.Pose3(self._anchor_pose() @ pose))
            tie = gtsam.BetweenFactorPose3(_ANCHOR_KEY, _map_key(place), gtsam.Pose3(pose), rigid)
            self._pending_factors.append((tie, None))
        return self._queue_loop(place, j, measured, self._loop_noise(sigmas, None), on_map=True)

    def anchor(self) -> np.ndarray | None:
        """The prior map's frame expressed in this session's frame (None before a map loop).

        A pose P in the map frame is ``anchor() @ P`` in this session; a session pose X is
        ``inv(anchor()) @ X`` in the map frame.
        """
        if self._anchor_initial is None:
            return None
        self._flush()
        return self._anchor_pose()

    def remove_loop(self, handle: int) -> None:
        """Take a loop out of the graph (applied at the next `update()`)."""
        loop = self._get_loop(handle)
        del self._loops[handle]
        if loop.index is None:
            self._pending_factors = [(f, h) for f, h in self._pending_factors if h != handle]
        else:
            self._pending_removals.append(loop.index)

    # ------------------------------------------------------------------ solving
    def update(self) -> None:
        """One incremental iSAM2 step with everything queued; extra steps after loop changes.

        A failing step is recovered from (see the module docstring); PoseGraphError when it
        cannot be, and on every later call: the graph then keeps the estimate it had."""
        if not self._order:
            return
        if self._failed is not None:
            self._keep_guesses()
            raise PoseGraphError(self._failed)
        try:
            self._step()
        except RuntimeError as error:  # GTSAM's exceptions reach Python as RuntimeError
            self._recover(error)

    def _step(self) -> None:
        """The queue into iSAM2; the queue is cleared only once every iSAM2 call succeeded."""
        graph = gtsam.NonlinearFactorGraph()
        loop_slots: list[tuple[int, int]] = []
        for factor, handle in self._pending_factors:
            if handle is not None:
                loop_slots.append((graph.size(), handle))
            graph.add(factor)
        loops_changed = bool(loop_slots or self._pending_removals)
        # One removal per iSAM2 step: removing the last two map loops in one step made iSAM2
        # report an indeterminate system at the anchor; one at a time it re-solves cleanly.
        first, rest = self._pending_removals[:1], self._pending_removals[1:]
        result = self._isam.update(graph, self._pending_values, first)
        for index in rest:
            self._isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), [index])
        new_indices = list(result.getNewFactorsIndices())
        if loops_changed:
            for _ in range(self.config.isam2.extra_updates_after_loop):
                self._isam.update()
        self._estimate = self._isam.calculateEstimate()
        # only now are the new loops in the graph: a failure above leaves them new, so a
        # recovery drops them rather than rebuilding with them
        for slot, handle in loop_slots:
            self._loops[handle].index = int(new_indices[slot])
        self._clear_queue()

    def _clear_queue(self) -> None:
        self._pending_factors = []
        self._pending_values = gtsam.Values()
        self._pending_removals = []

    def _recover(self, error: RuntimeError) -> None:
        """After a failed step, rebuild with QR: as the graph is, then without the step's new
        loops, then also with the new keyframes cut loose; PoseGraphError (estimate kept) when
        even that fails. Each stage that has nothing to change is passed over."""
        new = tuple(kf for kf in self._order if not self._estimate.exists(_key(kf)))
        reason = gtsam_reason(error)
        dropped: list[int] = []
        for stage in ("qr", "loops", "odometry"):
            if stage == "qr":
                if self._factorization == "QR":
                    continue
                what = "re-solved with QR factorisation, used from now on"
            elif stage == "loops":  # a new loop is the likelier culprit: keep the odometry if it solves without
                dropped = self._drop_new_loops()
                if not dropped:
                    continue
                what = _isolation_text([], dropped)
            else:
                what = _isolation_text(self._cut_odometry(new), dropped)
            try:
                self._rebuild_with_qr()
            except RuntimeError as again:
                reason = gtsam_reason(again)
                continue
            self._note(new, f"iSAM2 failed ({reason}){self._steps_text(new)}; {what}")
            return
        self._give_up(new, reason)

    def _note(self, keyframes: tuple[int, ...], what: str) -> None:
        self.recoveries.append(GraphRecovery(keyframes, what))

    def _steps_text(self, keyframes: tuple[int, ...]) -> str:
        """', odometry step of 1.0e+05 m': the usual cause, when one of the new edges is long."""
        steps = [float(np.linalg.norm(e.measured[:3, 3])) for e in self._odom_edges if e.j in keyframes]
        return f", odometry step of {max(steps):.1e} m" if steps and max(steps) >= 1e3 else ""

    def _drop_new_loops(self) -> list[int]:
        """Forget the loops not yet in iSAM2; returns their handles."""
        dropped = [h for h, loop in self._loops.items() if loop.index is None]
        for handle in dropped:
            del self._loops[handle]
        return dropped

    def _cut_odometry(self, keyframes: tuple[int, ...]) -> list[int]:
        """Cut the odometry edges into `keyframes` (a prior at the guess holds each); returns them."""
        if not keyframes:
            return []
        assert self._prior is not None  # set with the first keyframe, and `keyframes` are the graph's
        first, _, prior_noise = self._prior  # the first keyframe's prior noise holds each cut one too
        cut = [kf for kf in keyframes if kf != first]
        for kf in cut:
            self._segment_priors[kf] = (self._pending_values.atPose3(_key(kf)).matrix(), prior_noise)
        return cut

    def _rebuild_with_qr(self) -> None:
        """A fresh iSAM2 with QR factorisation holding the whole recorded graph (queue included),
        started from the last estimate and the queued guesses; the failed iSAM2 is never used again."""
        self._factorization = "QR"
        isam = self._new_isam()
        graph = gtsam.NonlinearFactorGraph()
        for factor in self._known_factors():
            graph.add(factor)
        slots = []
        for handle, loop in self._loops.items():
            slots.append((graph.size(), handle))
            graph.add(loop.factor)
        indices = list(isam.update(graph, self._with_guesses()).getNewFactorsIndices())
        for _ in range(self.config.isam2.extra_updates_after_loop):
            isam.update()
        estimate = isam.calculateEstimate()
        for slot, handle in slots:
            self._loops[handle].index = int(indices[slot])
        self._isam, self._estimate = isam, estimate
        self._clear_queue()

    def _with_guesses(self) -> gtsam.Values:
        """A copy of the last estimate with each queued variable it lacks at its guess."""
        values = gtsam.Values(self._estimate)
        for key in self._pending_values.keys():
            if not values.exists(key):
                values.insert(key, self._pending_values.atPose3(key))
        return values

    def _give_up(self, keyframes: tuple[int, ...], reason: str) -> NoReturn:
        """Keep the estimate so far (new keyframes at their odometry guesses) and refuse from now on."""
        self._keep_guesses()
        ids = ", ".join(map(str, keyframes)) or "none"
        self._failed = (f"iSAM2 cannot solve the pose graph with keyframe(s) {ids} ({reason}), even with "
                        "their odometry edges cut and the new loops dropped; the estimate up to there is kept")  # fmt: skip
        raise PoseGraphError(self._failed)

    def _keep_guesses(self) -> None:
        """The queue out of the way without iSAM2: new variables join the estimate at their
        guesses (the odometry's word), queued loops and removals are forgotten."""
        self._estimate = self._with_guesses()
        self._drop_new_loops()
        self._clear_queue()

    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.isam2.relinearize_threshold)
        params.relinearizeSkip = self.config.isam2.relinearize_skip
        params.setFactorization(self._factorization)
        return gtsam.ISAM2(params)

    def optimized_poses(self) -> dict[int, np.ndarray]:
        """Current estimate of every keyframe pose (world frame of the first odometry pose)."""
        self._flush()
        return {kf: self._estimate.atPose3(_key(kf)).matrix() for kf in self._order}

    def loop_residuals(self) -> list[LoopResidual]:
        """Per-loop chi2 / whitened error of the current estimate, in handle order."""
        self._flush()
        out = []
        for handle, loop in self._loops.items():
            pred = relative(self._estimate.atPose3(loop.key_i).matrix(), self._pose_of(loop.j))
            err = gtsam.Pose3(loop.measured).localCoordinates(gtsam.Pose3(pred))
            white = np.asarray(loop.gaussian.whiten(err))
            chi2 = float(white @ white)
            norm = float(np.sqrt(chi2))
            weight = 1.0 if self._kernel is None else float(self._kernel.weight(norm))  # type: ignore[attr-defined]
            out.append(LoopResidual(handle, loop.i, loop.j, chi2, norm, weight))
        return out

    def final_solve(self) -> FinalSolve:
        """`optimize`'s robust solve (`graph_optimizer.optimize_graph` with its defaults: the
        kernel solve from each start, GNC, the leave-one-out check) over the session's keyframes
        and the factors between them, with this graph's GNC settings; classifies the loops by
        handle. Does not change the iSAM2 state. Only for a graph that `final_solve_refusal`
        passes: one odometry chain, no prior-map loops."""
        self._flush()
        index = {kf: k for k, kf in enumerate(self._order)}
        odometry = [GraphEdge(index[e.i], index[e.j], e.measured, np.asarray(e.gaussian.information()))
                    for e in self._odom_edges]  # fmt: skip
        handles = list(self._loops)
        loops = [GraphEdge(index[lp.i], index[lp.j], lp.measured, np.asarray(lp.gaussian.information()))
                 for lp in self._loops.values()]  # fmt: skip
        poses = np.stack([self._pose_of(kf) for kf in self._order])
        data = PoseGraphData(3, tuple(range(len(self._order))), poses, (*odometry, *loops), "run")
        gnc = self.config.gnc
        if gnc.init == "odometry":  # both starts from the odometry chain, the lower TLS objective kept
            data = data.without_estimate()
        result = optimize_graph(data, OptimizerSettings(gnc_config=gnc.model_copy(update={"init": "current"})))
        kept = {handles[int(k) - len(odometry)]: bool(inlier)
                for k, inlier in zip(result.loop_indices, result.loop_inlier)}  # fmt: skip
        weights = {handles[int(k) - len(odometry)]: float(w) for k, w in zip(result.loop_indices, result.loop_weight)}
        return FinalSolve(
            poses={kf: result.poses[index[kf]] for kf in self._order},
            inliers=[h for h in handles if kept[h]],
            outliers=[h for h in handles if not kept[h]],
            weights=weights,
        )

    def final_solve_refusal(self) -> str | None:
        """Why `final_solve` cannot take this graph, or None: it solves one chain of keyframes
        with loops between them (what a g2o file holds), not a prior map's places nor segments
        a recovery cut apart."""
        if not self._order or self._prior is None:
            return "an empty graph"
        if any(lp.on_map for lp in self._loops.values()):
            return "a session with prior-map loops"
        if self._segment_priors:
            return "a graph a recovery cut into segments"
        if any(abs(self._order.index(lp.j) - self._order.index(lp.i)) == 1 for lp in self._loops.values()):
            return "a loop between consecutive keyframes (it would be read as odometry)"
        return None

    def finalize(self) -> dict[int, np.ndarray]:
        """Final poses: iSAM2's estimate, or, with `gnc.enabled`, `final_solve`'s after the loops
        it rejects are removed from the iSAM2 graph too. iSAM2's estimate, noted in
        `recoveries`, where the final solve cannot take the graph or GTSAM fails in it: the run's
        result must not be lost to it."""
        if not self.config.gnc.enabled or self._failed is not None:
            return self.optimized_poses()
        refusal = self.final_solve_refusal()
        if refusal is not None:
            if self._order:
                self._note((), f"the final robust pass does not run on {refusal}; iSAM2's estimate is kept")
            return self.optimized_poses()
        try:
            result = self.final_solve()
        except RuntimeError as error:  # the batch solve hit what iSAM2 had to work around
            self._note((), f"the final robust pass failed ({gtsam_reason(error)}); iSAM2's estimate is kept")
            return self.optimized_poses()
        for handle in result.outliers:
            self.remove_loop(handle)
        self._flush()
        return result.poses

    # ------------------------------------------------------------------ internals
    def _known_factors(self) -> list[gtsam.NonlinearFactor]:
        """Every factor but the loops: the first keyframe's prior, segment priors, the odometry
        edges iSAM2 took, and the prior map's anchor link and place ties."""
        known: list[gtsam.NonlinearFactor] = []
        if self._prior is not None:
            kf0, pose0, prior_noise = self._prior
            known.append(gtsam.PriorFactorPose3(_key(kf0), gtsam.Pose3(pose0), prior_noise))
        known += [gtsam.PriorFactorPose3(_key(kf), gtsam.Pose3(pose), model)
                  for kf, (pose, model) in self._segment_priors.items()]  # fmt: skip
        known += [gtsam.BetweenFactorPose3(_key(e.i), _key(e.j), gtsam.Pose3(e.measured), e.gaussian)
                  for e in self._odom_edges if e.j not in self._segment_priors]  # fmt: skip
        if self._anchor_initial is not None:
            known.append(self._anchor_link_factor())
            known += [gtsam.BetweenFactorPose3(_ANCHOR_KEY, _map_key(p), gtsam.Pose3(pose), rigid)
                      for p, (pose, rigid) in self._map_places.items()]  # fmt: skip
        return known

    def _odometry_sigmas(self, distance: float) -> np.ndarray:
        ocfg = self.config.odometry
        return noise.sigmas6(
            ocfg.rot_sigma + ocfg.rot_sigma_per_m * distance,
            ocfg.trans_sigma + ocfg.trans_sigma_per_m * distance,
        )

    def _flush(self) -> None:
        """Apply the queue before a read; after a PoseGraphError, only place what it holds."""
        if self._failed is not None:
            self._keep_guesses()
        elif self._pending_factors or self._pending_removals or self._pending_values.size():
            self.update()

    def _current_pose(self, kf_id: int) -> np.ndarray:
        key = _key(kf_id)
        if self._pending_values.exists(key):
            return self._pending_values.atPose3(key).matrix()
        return self._estimate.atPose3(key).matrix()

    def _pose_of(self, kf_id: int) -> np.ndarray:
        return self._estimate.atPose3(_key(kf_id)).matrix()

    def _loop_noise(
        self, sigmas: Sequence[float] | np.ndarray | None, information: np.ndarray | None
    ) -> gtsam.noiseModel.Gaussian:
        """The Gaussian part of a loop factor: given sigmas or information, else the configured loop noise."""
        if sigmas is not None and information is not None:
            raise ValueError("sigmas, information: give one of them, not both")
        if information is not None:
            return noise.gaussian_from_information(noise.check_information("information", information))
        if sigmas is None:
            return noise.gaussian(noise.sigmas6(self.config.loop.rot_sigma, self.config.loop.trans_sigma))
        return noise.gaussian(noise.check_sigmas("sigmas", sigmas))

    def _queue_loop(self, i: int, j: int, measured: np.ndarray, base: gtsam.noiseModel.Gaussian, on_map: bool) -> int:
        factor = gtsam.BetweenFactorPose3(
            _loop_key(i, on_map), _key(j), gtsam.Pose3(measured), noise.robustify(base, self._kernel)
        )
        handle = self._next_handle
        self._next_handle += 1
        self._loops[handle] = _Loop(i, j, measured, base, factor, on_map=on_map)
        self._pending_factors.append((factor, handle))
        return handle

    def _anchor_link_factor(self) -> gtsam.BetweenFactorPose3:
        assert self._anchor_link is not None, "set by the first prior-map loop"
        kf, measured = self._anchor_link
        return gtsam.BetweenFactorPose3(
            _key(kf), _ANCHOR_KEY, gtsam.Pose3(measured), noise.gaussian(_ANCHOR_PRIOR_SIGMAS)
        )

    def _anchor_pose(self) -> np.ndarray:
        if self._pending_values.exists(_ANCHOR_KEY):
            return self._pending_values.atPose3(_ANCHOR_KEY).matrix()
        return self._estimate.atPose3(_ANCHOR_KEY).matrix()

    def _get_loop(self, handle: int) -> _Loop:
        if isinstance(handle, bool) or not isinstance(handle, (int, np.integer)):
            raise ValueError(f"handle: expected an int loop handle, got {type(handle).__name__}")
        try:
            return self._loops[int(handle)]
        except KeyError:
            raise ValueError(f"handle: no loop with handle {handle} in the graph") from None
