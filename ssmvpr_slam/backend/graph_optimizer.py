"""Optimise a pose graph read from a file (g2o / TORO): robust kernel solve (one batch solve,
iSAM2 in vertex order, or both from an odometry start), GNC, a leave-one-out check of the loops
GNC keeps, loop inlier/outlier classification, ATE.

No file I/O here: `optimize_graph` takes a :class:`~ssmvpr_slam.backend.g2o_io.PoseGraphData`
and returns a frozen :class:`OptimizationResult`; the command line writes the outputs.

* Edges between consecutive vertex ids are odometry (Gaussian); every other edge is a loop
  candidate wrapped in the robust kernel (built by ``noise.make_kernel``, the one place that
  defines kernels, with the back end's default scales).
* Initial values: the stored vertex poses, or, when they are all zero (or absent), odometry
  chained from the first vertex. In iSAM2 mode each new vertex starts at the current estimate
  of its predecessor composed with the odometry, as a stream would.
* Two starts from odometry (solver 'auto', the default): a graph with its own estimate gets one
  batch kernel solve; a graph chained from odometry gets both a batch solve and iSAM2 in vertex
  order, each followed by GNC and the check, and the answer with the lower TLS objective wins.
  Neither start holds alone from odometry (batch took in false loops on manhattan at 50 %,
  iSAM2 on ringCity at 20 % grouped), and in both cases the objective picked the one that held.
* Graduated kernel scale (``refine_scales``, default DCS Phi = 10 then 1): the first solve
  (iSAM2 or batch) uses the generous scale so that true loops closing a long drift are kept;
  one batch solve per further scale then starts from that solution. With a good start, the
  tight scale drops the false loops the generous one still averaged in.
* Variables: Pose2 for a 2-D graph (its lifted measurements and information restricted to x,
  y, theta), Pose3 for a 3-D one. Same optimum as the lifted Pose3 problem (tested), but 3x3
  blocks: the long edges of random false loops make the elimination nearly dense, and each LM
  step on manhattan with 50 % false loops took 0.7 s instead of 3.9 s.
* GNC (``gnc=True``, the default): after the kernel solve, GTSAM's ``GncLMOptimizer``
  (truncated least squares, GTSAM's linear mu schedule) runs over the whole graph from the kernel
  solution, odometry and prior as known inliers. Its inlier threshold is the chi2 quantile for
  the residual's dimension: 3 for 2-D graphs, 6 for 3-D.
* Leave-one-out check (``verify=True``, with GNC): GNC, like every local method, can end in a
  minimum where a false loop is kept and the map is bent to satisfy it. On ringCity a single
  false loop across a loop-free stretch costs only 25-150 (GTSAM error units) of odometry strain,
  far above the TLS price of rejecting it (0.5 chi2 quantile = 5.7) but nothing a local solver
  climbs out of. So after GNC the loops it kept are solved by least squares; those that almost
  nothing else in the graph measures (leverage >= `verify_leverage`, from GTSAM's Marginals), or
  whose linearised leave-one-out innovation exceeds the chi2 quantile, are each removed in turn:
  if the rest of the graph then gets cheaper by more than the TLS rejection price, the loop is an
  outlier (the move that lowers the TLS objective). When no single removal pays, the suspects
  are removed together and each offered back alone (false loops that hold one bend together).
  Loops whose residual is below the quantile
  at the checked solution are kept again, and a last least-squares solve over odometry and the
  kept loops gives the poses. Last, the kernel solution (least squares over the loops under the
  chi2 quantile) is the answer instead when its TLS objective is lower.
* Classification of loops: with GNC, the kept set above (GNC weight >= 0.5, minus the loops the
  check removed, plus those it re-admitted; or the chi2 test below when the kernel solution is
  the answer); without GNC, a loop is an outlier when its whitened
  (Mahalanobis) residual squared after optimisation exceeds the chi2 quantile `outlier_quantile`
  (0.99) with 3 degrees of freedom for 2-D graphs, 6 for 3-D.

Over 400 lines: the kernel solve, GNC, the leave-one-out check and the choice between the two
starts are one algorithm whose steps hand each other GTSAM values and graphs; each step is a
function of its own.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Literal

import gtsam
import numpy as np
from scipy.stats import chi2 as chi2_dist

from ssmvpr_slam.backend import noise
from ssmvpr_slam.backend.config import GncConfig, ISAM2Config, RobustKernelConfig
from ssmvpr_slam.backend.g2o_io import (
    PoseGraphData,
    chain_odometry,
    information_pose3_to_planar,
    planar_of,
    planar_pose,
)  # fmt: skip
from ssmvpr_slam.backend.gtsam_errors import gtsam_reason

KERNEL_NAMES: dict[str, str] = {
    "cauchy": "cauchy",
    "huber": "huber",
    "dcs": "dcs",
    "gm": "geman_mcclure",
    "tukey": "tukey",
    "none": "none",
}
"""Command-line kernel name -> `RobustKernelConfig.kind`."""

DEFAULT_KERNEL = "dcs"
DEFAULT_GNC = True
"""Default of `optimize` (docs/backend_benchmarks.md): the kernel solve below, then GNC and the
leave-one-out check. Without GNC, DCS alone ends at 17.7x the optimum on ringCity with 50 %
random false loops (two false loops kept bend the map and 302 true loops are lost)."""
DEFAULT_SOLVER = "auto"
"""Kernel solve: one batch solve from a graph's own estimate (iSAM2 first did not finish on
manhattan with 50 % false loops within 480 s); from an odometry start, both a batch solve and
iSAM2 in vertex order, each followed by GNC and the check, and the answer with the lower TLS
objective is kept (zero-initialised, batch alone ended at 9.8x on manhattan at 50 % random false
loops and iSAM2 alone at 32.9x on ringCity at 20 % grouped; in both the other start held and
had the lower objective)."""
SOLVERS = ("auto", "batch", "isam2")
DEFAULT_REFINE_SCALES: tuple[float, ...] = (1.0,)
"""DCS at scale 10 (Phi, on the squared whitened error), then one batch DCS solve at Phi = 1
from that solution. Phi = 1 alone rejects every true loop of ring/ringCity from their drifted
odometry start (ATE 5.8x / 3.45x the optimum without any false loop); Phi = 10 alone lets false
loops pull manhattan (2.03x at 50 %)."""

_PRIOR_SIGMA = 1e-6


@dataclass(frozen=True)
class OptimizerSettings:
    """How `optimize_graph` solves."""

    kernel: str = DEFAULT_KERNEL
    """cauchy | huber | dcs | gm | tukey | none"""
    kernel_scale: float | None = None
    """None = the back end's default scale for the kernel (``DEFAULT_KERNEL_SCALES``)."""
    gnc: bool = DEFAULT_GNC
    refine_scales: tuple[float, ...] = DEFAULT_REFINE_SCALES
    """After the first solve, one batch solve per scale with the same kernel, each from the
    previous solution (graduated scale: a generous scale closes loops after long drift, a tight
    one then drops the false loops it averaged in). Empty: no refinement; ignored for 'none'."""
    solver: str = DEFAULT_SOLVER
    """Kernel solve: 'batch' (one Levenberg-Marquardt solve), 'isam2' (vertex order, as a stream
    would) or 'auto' (batch from the graph's own estimate, both from an odometry start unless the
    kernel is 'none'; with or without GNC, the lower TLS objective is kept)."""
    gnc_config: GncConfig = field(default_factory=lambda: GncConfig(enabled=True, init="current"))
    """init 'current': GNC starts from the kernel solution ('odometry': from the initial values).
    From the odometry start GNC kept the wrong side of ring's 30 % / 50 % grouped false loops
    (5.9x); from the kernel solution it held (1.000)."""
    verify: bool = True
    """Leave-one-out check of the loops GNC kept (module docstring); only with GNC."""
    verify_leverage: float = 0.75
    """Loops whose leverage (mean eigenvalue of the hat matrix block) is at least this are checked
    (ringCity: false loops GNC kept 0.92-0.99, true loops at most 0.60)."""
    verify_rounds: int = 10
    """At most this many loops are removed by the check (one per round)."""
    verify_group: int = 8
    """Loops of largest leave-one-out innovation that join the high-leverage ones in the joint
    removal (in a sparse graph true loops have high leverage too, so leverage alone misses)."""
    verify_max_suspects: int = 50
    """Leave-one-out solves per round at most: high-leverage loops first, then by innovation."""
    outlier_quantile: float = 0.99
    isam2: ISAM2Config = field(default_factory=ISAM2Config)
    final_isam2_updates: int = 5
    """Extra iSAM2 iterations after the last vertex (relinearisation settles)."""
    lm_max_iterations: int = 100
    gnc_inner_iterations: int = 10
    """Levenberg-Marquardt iterations per GNC step (GTSAM's default 100 made GNC 5x slower
    on ring for the same classification)."""

    def __post_init__(self) -> None:
        if self.solver not in SOLVERS:
            raise ValueError(f"solver: expected one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.kernel not in KERNEL_NAMES:
            raise ValueError(f"kernel: expected one of {', '.join(KERNEL_NAMES)}, got {self.kernel!r}")
        if any(not scale > 0.0 for scale in self.refine_scales):
            raise ValueError(f"refine_scales: every scale must be > 0, got {list(self.refine_scales)}")
        if not 0.0 < self.outlier_quantile < 1.0:
            raise ValueError(f"outlier_quantile: must be in (0, 1), got {self.outlier_quantile}")
        if not 0.0 < self.verify_leverage <= 1.0:
            raise ValueError(f"verify_leverage: must be in (0, 1], got {self.verify_leverage}")
        if self.verify_rounds < 1 or self.verify_max_suspects < 1 or self.verify_group < 0:
            raise ValueError(f"verify_rounds, verify_max_suspects: must be >= 1, got {self.verify_rounds}, "
                             f"{self.verify_max_suspects}")  # fmt: skip

    def starts(self, from_odometry: bool) -> tuple[Literal["batch", "isam2"], ...]:
        """The kernel solves to run: both only for 'auto' from an odometry start with a robust
        kernel (plain least squares has one answer)."""
        if self.solver == "batch":
            return ("batch",)
        if self.solver == "isam2":
            return ("isam2",)
        return ("batch", "isam2") if from_odometry and self.kernel != "none" else ("batch",)


@dataclass(frozen=True)
class OptimizationResult:
    """Poses in ``ids`` order and the classification of the loop candidates."""

    ids: tuple[int, ...]
    poses: np.ndarray
    loop_indices: np.ndarray
    """Index into the graph's edges of each loop candidate."""
    loop_inlier: np.ndarray
    loop_weight: np.ndarray
    """GNC weight (with GNC) or the kernel's weight at the final residual."""
    loop_chi2: np.ndarray
    """Squared whitened residual of each loop (its Gaussian part) at the final estimate."""
    initialised_from_odometry: bool
    seconds: float
    settings: OptimizerSettings
    classification: str
    before_gnc: OptimizationResult | None = None
    """With GNC: the kernel solution GNC started from."""
    check_removed: int = 0
    """With GNC and the check: loops GNC kept that the leave-one-out check removed."""
    check_readmitted: int = 0
    """With GNC and the check: loops GNC rejected that fit the checked solution (kept again)."""
    check_seconds: float = 0.0
    """Of `seconds`: the leave-one-out check and the comparison with the kernel solution."""
    from_kernel: bool = False
    """With GNC and the check: the kernel solution (least squares over the loops it kept) had
    the lower TLS objective and is the answer."""
    solver: str = "batch"
    """The kernel solve this answer started from: 'batch' or 'isam2'."""
    start_tls: tuple[tuple[str, float], ...] = ()
    """(solver, TLS objective) of each start compared (solver 'auto' from an odometry start);
    empty when one start ran."""
    check_error: str | None = None
    """Why the leave-one-out check could not run (GTSAM failed in it); GNC's answer was kept."""

    @property
    def n_loops(self) -> int:
        return int(len(self.loop_indices))

    @property
    def n_outliers(self) -> int:
        return int(np.sum(~self.loop_inlier))


def _key(index: int) -> int:
    return gtsam.symbol("x", index)


def make_loop_kernel(
    settings: OptimizerSettings, scale: float | None = None
) -> gtsam.noiseModel.mEstimator.Base | None:
    """The loop kernel at `scale` (default: the settings' scale)."""
    scale = settings.kernel_scale if scale is None else scale
    return noise.make_kernel(RobustKernelConfig(kind=KERNEL_NAMES[settings.kernel], scale=scale))


def initial_poses(graph: PoseGraphData) -> tuple[np.ndarray, bool]:
    """(initial poses, whether they were chained from odometry)."""
    if graph.has_initial_estimate():
        return graph.poses.copy(), False
    return chain_odometry(graph), True


def _gtsam_pose(pose: np.ndarray, dim: int) -> gtsam.Pose2 | gtsam.Pose3:
    return gtsam.Pose2(*planar_of(pose)) if dim == 2 else gtsam.Pose3(pose)


def _between(dim: int, i: int, j: int, measured: np.ndarray, model: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    if dim == 2:
        return gtsam.BetweenFactorPose2(_key(i), _key(j), gtsam.Pose2(*planar_of(measured)), model)
    return gtsam.BetweenFactorPose3(_key(i), _key(j), gtsam.Pose3(measured), model)


def _prior(dim: int, pose: np.ndarray) -> gtsam.NonlinearFactor:
    """Holds the first vertex where it starts."""
    if dim == 2:
        return gtsam.PriorFactorPose2(_key(0), gtsam.Pose2(*planar_of(pose)), noise.gaussian(np.full(3, _PRIOR_SIGMA)))
    return gtsam.PriorFactorPose3(_key(0), gtsam.Pose3(pose), noise.gaussian(np.full(6, _PRIOR_SIGMA)))


class _Factors:
    """GTSAM factors of the graph, built once: Pose2 for a 2-D graph, Pose3 for a 3-D one (the
    module docstring says why)."""

    def __init__(self, graph: PoseGraphData, initial: np.ndarray, kernel) -> None:  # noqa: ANN001
        self.graph = graph
        self.dim = graph.dim
        self.index = {v: k for k, v in enumerate(graph.ids)}
        self.prior = _prior(self.dim, initial[0])
        self.odometry: list[tuple[int, gtsam.NonlinearFactor]] = []  # (later vertex index, factor)
        self.loops: list[tuple[int, gtsam.NonlinearFactor, gtsam.NonlinearFactor]] = []  # robust, gaussian
        self.loop_indices: list[int] = []
        for n, e in enumerate(graph.edges):
            i, j = self.index[e.i], self.index[e.j]
            information = information_pose3_to_planar(e.information) if self.dim == 2 else e.information
            gaussian = noise.gaussian_from_information(information)
            plain = _between(self.dim, i, j, e.measured, gaussian)
            if e.is_odometry:
                self.odometry.append((max(i, j), plain))
            else:
                robust = _between(self.dim, i, j, e.measured, noise.robustify(gaussian, kernel))
                self.loops.append((max(i, j), robust, plain))
                self.loop_indices.append(n)

    def robust_graph(self) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        g.add(self.prior)
        for _, f in self.odometry:
            g.add(f)
        for _, f, _ in self.loops:
            g.add(f)
        return g

    def values(self, poses: np.ndarray) -> gtsam.Values:
        values = gtsam.Values()
        for k, pose in enumerate(poses):
            values.insert(_key(k), _gtsam_pose(pose, self.dim))
        return values

    def pose(self, values: gtsam.Values, k: int) -> np.ndarray:
        if self.dim == 2:
            p = values.atPose2(_key(k))
            return planar_pose(p.x(), p.y(), p.theta())
        return values.atPose3(_key(k)).matrix()

    def poses(self, values: gtsam.Values) -> np.ndarray:
        return np.array([self.pose(values, k) for k in range(len(self.graph.ids))])


def _solve_batch(factors: _Factors, initial: np.ndarray, settings: OptimizerSettings) -> np.ndarray:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.lm_max_iterations)
    values = gtsam.LevenbergMarquardtOptimizer(factors.robust_graph(), factors.values(initial), params).optimize()
    return factors.poses(values)


def _solve_isam2(factors: _Factors, initial: np.ndarray, settings: OptimizerSettings) -> np.ndarray:
    """Vertices in id order; each step adds the vertex and every edge it completes."""
    n = len(initial)
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(settings.isam2.relinearize_threshold)
    params.relinearizeSkip = settings.isam2.relinearize_skip
    isam = gtsam.ISAM2(params)
    by_vertex: list[list[gtsam.NonlinearFactor]] = [[] for _ in range(n)]
    odo_rel: dict[int, np.ndarray] = {}
    for later, f in factors.odometry:
        by_vertex[later].append(f)
    for e in factors.graph.edges:
        if e.is_odometry:
            i, j = factors.index[e.i], factors.index[e.j]
            if j == i + 1:
                odo_rel.setdefault(j, e.measured)
            elif i == j + 1:
                odo_rel.setdefault(i, np.linalg.inv(e.measured))
    for later, f, _ in factors.loops:
        by_vertex[later].append(f)
    by_vertex[0].insert(0, factors.prior)
    estimate = gtsam.Values()
    previous = initial[0]
    for k in range(n):
        graph = gtsam.NonlinearFactorGraph()
        for f in by_vertex[k]:
            graph.add(f)
        values = gtsam.Values()
        # a stream places a new vertex by odometry from where its predecessor is now
        guess = previous @ odo_rel[k] if k in odo_rel else initial[k]
        values.insert(_key(k), _gtsam_pose(guess, factors.dim))
        isam.update(graph, values)
        estimate = isam.calculateEstimate()
        previous = factors.pose(estimate, k)
    for _ in range(settings.final_isam2_updates):
        isam.update()
    estimate = isam.calculateEstimate()
    return factors.poses(estimate)


def _loop_chi2(factors: _Factors, values: gtsam.Values) -> np.ndarray:
    """Squared whitened residual of each loop (its Gaussian part) at `values`."""
    return np.array([2.0 * plain.error(values) for _, _, plain in factors.loops])


def optimize_graph(graph: PoseGraphData, settings: OptimizerSettings | None = None) -> OptimizationResult:
    """Optimise `graph` (see the module docstring); does not modify it."""
    settings = settings or OptimizerSettings()
    return refine_and_choose(graph, kernel_solutions(graph, settings), settings)


def kernel_solutions(graph: PoseGraphData, settings: OptimizerSettings) -> list[OptimizationResult]:
    """The robust-kernel solve (first solve, then the refine scales) from each start that
    ``settings.starts`` names, without GNC."""
    initial, from_odometry = initial_poses(graph)
    return [_kernel_solve(graph, settings, initial, from_odometry, s) for s in settings.starts(from_odometry)]


def refine_and_choose(
    graph: PoseGraphData, kernel_results: list[OptimizationResult], settings: OptimizerSettings
) -> OptimizationResult:
    """Each start's kernel solution through GNC and the check (``settings.gnc``), then the answer
    with the lowest TLS objective (`tls_cost`): its `seconds` cover every start and the
    comparison, its `start_tls` records each start's objective. One start is returned as it is."""
    if settings.gnc and len(kernel_results[0].loop_indices):
        results = [refine_with_gnc(graph, k, settings) for k in kernel_results]
    else:
        results = [replace(k, settings=settings) for k in kernel_results]
    if len(results) == 1:
        return results[0]
    start = time.perf_counter()
    factors = _Factors(graph, initial_poses(graph)[0], None)  # the prior every start was held by
    _, threshold = chi2_threshold(graph, settings.gnc_config.inlier_probability)
    costs = [tls_cost(factors, factors.values(r.poses), threshold) for r in results]
    best = results[int(np.argmin(costs))]
    seconds = sum(r.seconds for r in results) + time.perf_counter() - start
    return replace(best, seconds=seconds, start_tls=tuple((r.solver, c) for r, c in zip(results, costs)))


def _kernel_solve(
    graph: PoseGraphData,
    settings: OptimizerSettings,
    initial: np.ndarray,
    from_odometry: bool,
    solver: Literal["batch", "isam2"],
) -> OptimizationResult:
    start = time.perf_counter()
    kernel = make_loop_kernel(settings)
    factors = _Factors(graph, initial, kernel)
    if solver == "batch":
        poses = _solve_batch(factors, initial, settings)
    else:
        poses = _solve_isam2(factors, initial, settings)
    if kernel is not None:
        for scale in settings.refine_scales:
            kernel = make_loop_kernel(settings, scale)
            factors = _Factors(graph, initial, kernel)
            poses = _solve_batch(factors, poses, settings)
    dof, threshold = chi2_threshold(graph, settings.outlier_quantile)
    chi2 = _loop_chi2(factors, factors.values(poses))
    weights = np.array([1.0 if kernel is None else float(kernel.weight(np.sqrt(c))) for c in chi2])  # type: ignore[attr-defined]
    return OptimizationResult(
        ids=graph.ids, poses=poses, loop_indices=np.asarray(factors.loop_indices, dtype=int),
        loop_inlier=chi2 <= threshold, loop_weight=weights, loop_chi2=chi2,
        initialised_from_odometry=from_odometry, seconds=time.perf_counter() - start,
        settings=replace(settings, gnc=False), solver=solver,
        classification=f"outlier if whitened residual^2 > chi2({dof}) quantile {settings.outlier_quantile} "
                       f"= {threshold:.2f}",
    )  # fmt: skip


def chi2_threshold(graph: PoseGraphData, quantile: float) -> tuple[int, float]:
    """(degrees of freedom, chi2 quantile) of one loop residual: 3 for a 2-D graph (Pose2), 6 for
    a 3-D one."""
    dof = 3 if graph.dim == 2 else 6
    return dof, float(chi2_dist.ppf(quantile, dof))


def refine_with_gnc(
    graph: PoseGraphData,
    kernel_result: OptimizationResult,
    settings: OptimizerSettings,
) -> OptimizationResult:
    """GNC (GTSAM's GncLMOptimizer, truncated least squares) over the whole graph from the
    kernel solution, odometry and prior as known inliers, then (``settings.verify``) the
    leave-one-out check and a least-squares solve over the known inliers plus the kept loops
    (inner LM solves are capped at `gnc_inner_iterations`, so that solve gives the converged
    optimum)."""
    start = time.perf_counter() - kernel_result.seconds
    initial, _ = initial_poses(graph)
    factors = _Factors(graph, initial, None)  # GNC and the check use the Gaussian loop factors only
    cfg = settings.gnc_config
    init = kernel_result.poses if cfg.init == "current" else initial
    _, threshold = chi2_threshold(graph, cfg.inlier_probability)
    values, weights = _gnc(factors, factors.values(init), 0.5 * threshold, settings)
    keep = weights >= cfg.weight_threshold
    values = _least_squares(factors, keep, values, settings.lm_max_iterations)
    removed = readmitted = 0
    check_start = time.perf_counter()
    check_error: str | None = None
    from_kernel = False
    if settings.verify and factors.loops:
        try:
            values, keep, removed, readmitted, from_kernel = _check_and_compare(
                factors, keep, values, kernel_result, threshold, settings
            )
        except RuntimeError as exc:  # GTSAM could not solve a step of the check: GNC's answer stands
            check_error = (
                f"the leave-one-out check could not solve ({gtsam_reason(exc)}); GNC's solution is kept unchecked"
            )
    check_seconds = time.perf_counter() - check_start
    poses = factors.poses(values)
    return OptimizationResult(
        ids=graph.ids, poses=poses, loop_indices=kernel_result.loop_indices,
        loop_inlier=keep, loop_weight=weights, loop_chi2=_loop_chi2(factors, values),
        initialised_from_odometry=kernel_result.initialised_from_odometry,
        seconds=time.perf_counter() - start, settings=replace(settings, gnc=True),
        classification=f"outlier if GNC ({cfg.loss}) weight < {cfg.weight_threshold}"
                       + (", then the leave-one-out check" if settings.verify and check_error is None else ""),
        before_gnc=kernel_result, solver=kernel_result.solver, from_kernel=from_kernel,
        check_removed=removed, check_readmitted=readmitted, check_seconds=check_seconds if settings.verify else 0.0,
        check_error=check_error,
    )  # fmt: skip


def _check_and_compare(
    factors: _Factors,
    keep: np.ndarray,
    values: gtsam.Values,
    kernel_result: OptimizationResult,
    threshold: float,
    settings: OptimizerSettings,
) -> tuple[gtsam.Values, np.ndarray, int, int, bool]:
    """The leave-one-out check of GNC's loops, loops that fit the checked map readmitted, then the
    kernel's answer taken instead when its TLS objective is lower: (values, keep, removed,
    readmitted, from the kernel)."""
    values, checked = _leave_one_out_check(factors, keep, values, threshold, settings)
    removed = int(np.sum(keep & ~checked))
    fits = _loop_chi2(factors, values) <= threshold
    readmitted = int(np.sum(fits & ~checked))
    keep = checked | fits
    if readmitted:
        values = _least_squares(factors, keep, values, settings.lm_max_iterations)
    # GNC is a heuristic for the TLS objective: keep the kernel's answer when it is cheaper
    # (ringCity, 50 % grouped: GNC settled on a false group, 5.0x; DCS alone held, 0.95x)
    kernel_keep = kernel_result.loop_chi2 <= threshold
    kernel_values = _least_squares(
        factors, kernel_keep, factors.values(kernel_result.poses), settings.lm_max_iterations
    )
    from_kernel = tls_cost(factors, kernel_values, threshold) < tls_cost(factors, values, threshold)
    if from_kernel:
        values = kernel_values
        keep = _loop_chi2(factors, values) <= threshold
    return values, keep, removed, readmitted, from_kernel


def _gnc(
    factors: _Factors, initial: gtsam.Values, cost_threshold: float, settings: OptimizerSettings
) -> tuple[gtsam.Values, np.ndarray]:
    """GTSAM's GncLMOptimizer; (values, loop weights). Every step restarts from `initial` (the
    kernel solution): a variant warm-started from the previous step was 1.6-3.2x faster but kept
    two groups of false loops on ringCity (10 % grouped, 19x) whose bent map has the lower TLS
    objective; anchored to the kernel solution GTSAM's stays out of that minimum."""
    cfg = settings.gnc_config
    known = _known_graph(factors)
    n_known = known.size()
    full = gtsam.NonlinearFactorGraph(known)
    for _, _, plain in factors.loops:
        full.add(plain)
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(settings.gnc_inner_iterations)
    params = gtsam.GncLMParams(lm)
    params.setLossType(gtsam.GncLossType.TLS if cfg.loss == "tls" else gtsam.GncLossType.GM)
    if params.maxIterations != cfg.max_iterations:  # GTSAM prints a warning on every set
        params.setMaxIterations(cfg.max_iterations)
    params.setKnownInliers(list(range(n_known)))
    optimizer = gtsam.GncLMOptimizer(full, initial, params)
    optimizer.setInlierCostThresholds(cost_threshold)  # known inliers ignore it
    values = optimizer.optimize()
    return values, np.asarray(optimizer.getWeights())[n_known:]


def tls_cost(factors: _Factors, values: gtsam.Values, threshold: float) -> float:
    """The truncated-least-squares objective GNC (TLS) minimises, in GTSAM's 0.5 * chi2 units:
    prior and odometry in full, each loop capped at 0.5 * `threshold`."""
    cap = 0.5 * threshold
    return float(
        _known_graph(factors).error(values) + sum(min(plain.error(values), cap) for _, _, plain in factors.loops)
    )


def check_kept_loops(
    graph: PoseGraphData, poses: np.ndarray, keep: np.ndarray, settings: OptimizerSettings | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The leave-one-out check alone (module docstring) on the loops `keep` marks (one flag per
    loop candidate, in edge order) from `poses`: returns (least-squares poses over odometry and
    the loops that pass, the loops that pass). No re-admission here."""
    settings = settings or OptimizerSettings()
    initial, _ = initial_poses(graph)
    factors = _Factors(graph, initial, None)
    _, threshold = chi2_threshold(graph, settings.gnc_config.inlier_probability)
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (len(factors.loops),):
        raise ValueError(f"keep: expected {len(factors.loops)} flags (one per loop), got shape {keep.shape}")
    values = _least_squares(factors, keep, factors.values(poses), settings.lm_max_iterations)
    values, passed = _leave_one_out_check(factors, keep, values, threshold, settings)
    return factors.poses(values), passed


def _known_graph(factors: _Factors) -> gtsam.NonlinearFactorGraph:
    """Prior and odometry: the factors GNC treats as known inliers."""
    known = gtsam.NonlinearFactorGraph()
    known.add(factors.prior)
    for _, f in factors.odometry:
        known.add(f)
    return known


def _inlier_graph(
    factors: _Factors, keep: np.ndarray, skip: int | None = None
) -> tuple[gtsam.NonlinearFactorGraph, dict[int, int]]:
    """Least-squares graph of the known inliers and the kept loops (but `skip`); loop -> slot."""
    graph = _known_graph(factors)
    slots: dict[int, int] = {}
    for k, (_, _, plain) in enumerate(factors.loops):
        if keep[k] and k != skip:
            slots[k] = graph.size()
            graph.add(plain)
    return graph, slots


def _least_squares(factors: _Factors, keep: np.ndarray, values: gtsam.Values, iterations: int) -> gtsam.Values:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    return gtsam.LevenbergMarquardtOptimizer(_inlier_graph(factors, keep)[0], values, params).optimize()


def _leverage_and_innovation(
    graph: gtsam.NonlinearFactorGraph, slots: dict[int, int], values: gtsam.Values
) -> dict[int, tuple[float, float]]:
    """Per loop: leverage (mean eigenvalue of the whitened hat-matrix block H = A Sigma A^T, with
    Sigma the joint marginal covariance of its two poses) and the linearised leave-one-out
    innovation e^T (I - H)^-1 e. Leverage near 1: nothing else in the graph measures this
    relative pose, so its own residual says nothing about whether it is true."""
    marginals = gtsam.Marginals(graph, values)
    out: dict[int, tuple[float, float]] = {}
    for k, slot in slots.items():
        factor = graph.at(slot)
        jacobian, rhs = factor.linearize(values).jacobian()  # whitened; rhs = -whitened error
        keys = gtsam.KeyVector()
        for key in factor.keys():
            keys.append(key)
        hat = jacobian @ marginals.jointMarginalCovariance(keys).fullMatrix() @ jacobian.T
        rest = np.eye(len(rhs)) - hat
        try:
            innovation = float(rhs @ np.linalg.solve(rest, rhs))
        except np.linalg.LinAlgError:
            innovation = float("inf")
        out[k] = (float(np.trace(hat)) / len(rhs), innovation)
    return out


def _leave_one_out_check(
    factors: _Factors, keep: np.ndarray, values: gtsam.Values, threshold: float, settings: OptimizerSettings
) -> tuple[gtsam.Values, np.ndarray]:
    """Greedy TLS descent over the kept loops (module docstring). Each round, every suspect is
    removed in turn and the one whose removal saves the most is dropped if that saving exceeds
    the TLS rejection price: one loop per round, because while a false loop bends the map the
    true loops around it look strained too. When no single removal pays, the high-leverage
    suspects and the `verify_group` loops of largest innovation are removed together (two or
    three false loops bending the same stretch each hold the bend alone: ringCity 30 %, each
    saves 4-16, together 76) and each is then offered back alone; the move is kept if the TLS
    objective drops. Returns (least-squares values over
    the loops that pass, the loops that pass)."""
    keep = keep.copy()
    price = 0.5 * threshold  # TLS cost of rejecting a loop, in GTSAM's 0.5 * chi2 units
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.lm_max_iterations)

    def solve(mask: np.ndarray, start: gtsam.Values, skip: int | None = None) -> tuple[float, gtsam.Values]:
        graph, _ = _inlier_graph(factors, mask, skip)
        solved = gtsam.LevenbergMarquardtOptimizer(graph, start, params).optimize()
        return graph.error(solved), solved

    for _ in range(settings.verify_rounds):
        graph, slots = _inlier_graph(factors, keep)
        if not slots:
            break
        stats = _leverage_and_innovation(graph, slots, values)
        levered = sorted(
            (k for k, (lev, _) in stats.items() if lev >= settings.verify_leverage), key=lambda k: -stats[k][0]
        )
        strained = sorted((k for k, (lev, inn) in stats.items() if lev < settings.verify_leverage and inn > threshold),
                          key=lambda k: -stats[k][1])  # fmt: skip
        suspects = (levered + strained)[: settings.verify_max_suspects]
        cost = graph.error(values)
        best, best_saving = None, price
        for k in suspects:
            saving = cost - solve(keep, values, skip=k)[0]
            if saving > best_saving:
                best, best_saving = k, saving
        if best is not None:
            keep[best] = False
            values = _least_squares(factors, keep, values, settings.lm_max_iterations)
            continue
        by_innovation = sorted(stats, key=lambda k: -stats[k][1])[: settings.verify_group]
        group = sorted(set(levered) | set(by_innovation), key=lambda k: stats[k][1])[: settings.verify_max_suspects]
        if len(group) < 2:
            break
        trial = keep.copy()
        trial[group] = False
        trial_cost, trial_values = solve(trial, values)
        for k in group:  # offered back alone, least strained first: true loops fit the unbent map
            trial[k] = True
            with_k, with_values = solve(trial, trial_values)
            if with_k - trial_cost <= price:
                trial_cost, trial_values = with_k, with_values
            else:
                trial[k] = False
        removed = int(np.sum(keep & ~trial))
        if removed == 0 or trial_cost + removed * price >= cost:
            break
        keep, values = trial, trial_values
    return values, keep
