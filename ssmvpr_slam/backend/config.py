"""Tunables of the back end: pose graph (iSAM2, noise, robust kernels, GNC) and loop registration.

Every number the back end uses lives here so that YAML presets can override it. Noise sigmas
are in GTSAM's Pose3 tangent order: rotation (rad) first, then translation (m).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from loopclosure.config import VerifierConfig
from ssmvpr_common.settings_model import SettingsModel

RobustKernelKind = Literal["cauchy", "huber", "dcs", "geman_mcclure", "tukey", "none"]
OdometryKind = Literal["kiss_icp", "logged"]  # frontend.odometry.kind once `auto` is resolved

DEFAULT_KERNEL_SCALES: dict[str, float] = {
    "cauchy": 1.0,
    "huber": 1.345,
    # Redescending kernels ignore residuals far beyond their scale. The first true loop after
    # a long drift has a large whitened error, so their scales must be generous or it would be
    # discarded (seen in tests/slam/backend/test_pose_graph.py's simulation: DCS 1.0 and Tukey 4.685
    # leave the odometry uncorrected; these values keep the correction and reject outliers).
    "dcs": 10.0,
    "geman_mcclure": 10.0,
    "tukey": 30.0,
}


class PriorNoiseConfig(SettingsModel):
    """Anchors the first keyframe; tight so the graph has no gauge freedom."""

    rot_sigma: float = Field(1e-3, gt=0, description="rad")
    trans_sigma: float = Field(1e-3, gt=0, description="m")


class OdometryNoiseConfig(SettingsModel):
    """Odometry factor sigmas: a floor plus an optional part proportional to distance travelled."""

    rot_sigma: float = Field(0.01, gt=0, description="rad per odometry edge")
    trans_sigma: float = Field(0.05, gt=0, description="m per odometry edge")
    rot_sigma_per_m: float = Field(0.0, ge=0, description="rad added per metre travelled")
    trans_sigma_per_m: float = Field(0.0, ge=0, description="m added per metre travelled")


class LoopNoiseConfig(SettingsModel):
    """Default loop factor sigmas, used when the caller gives no sigmas / information."""

    rot_sigma: float = Field(0.05, gt=0, description="rad")
    trans_sigma: float = Field(0.2, gt=0, description="m")


class RobustKernelConfig(SettingsModel):
    """M-estimator wrapped around every loop factor (odometry stays Gaussian)."""

    kind: RobustKernelKind = Field("cauchy", description="M-estimator of the loop factors; none: plain least squares")
    scale: float | None = Field(
        None,
        gt=0,
        description="kernel parameter (k or c) on the whitened error norm; "
        "None = the kind's entry in DEFAULT_KERNEL_SCALES",
    )

    def resolved_scale(self) -> float | None:
        """The scale to use (None for kind 'none')."""
        if self.kind == "none":
            return None
        return self.scale if self.scale is not None else DEFAULT_KERNEL_SCALES[self.kind]


class ISAM2Config(SettingsModel):
    """Incremental solver settings."""

    relinearize_threshold: float = Field(
        0.01, gt=0, description="variables whose linear delta exceeds this are relinearised (GTSAM)"
    )
    relinearize_skip: int = Field(1, ge=1, description="relinearisation is checked every this many iSAM2 updates")
    extra_updates_after_loop: int = Field(
        3, ge=0, description="extra iSAM2 iterations after a loop is added or removed"
    )


class GncConfig(SettingsModel):
    """GNC's settings: of `optimize`, and of a run's optional final robust pass (`enabled`)."""

    enabled: bool = Field(
        False,
        description="at the end of a run, `optimize`'s robust solve (kernel, GNC, leave-one-out check) over the "
        "session's graph, and remove the loops it rejects (not with prior-map loops: iSAM2's estimate is kept)",
    )
    loss: Literal["tls", "gm"] = Field("tls", description="GNC loss: truncated least squares or Geman-McClure")
    inlier_probability: float = Field(0.99, gt=0, lt=1, description="chi2 quantile that sets the inlier cost threshold")
    weight_threshold: float = Field(
        0.5, ge=0, le=1, description="loops whose final GNC weight is at least this are inliers"
    )
    max_iterations: int = Field(100, ge=1, description="GNC iterations at most (GTSAM GncParams)")
    init: Literal["odometry", "current"] = Field(
        "odometry",
        description="where the solve starts: the odometry chain (both of optimize's starts, the lower TLS "
        "objective kept) or the current iSAM2 estimate; GNC then starts from the kernel solution",
    )


class PoseGraphConfig(SettingsModel):
    """Everything `PoseGraph` needs."""

    prior: PriorNoiseConfig = PriorNoiseConfig()
    odometry: OdometryNoiseConfig = Field(
        OdometryNoiseConfig(), description="odometry factors of a source without its own entry in odometry_by_source"
    )
    odometry_by_source: dict[OdometryKind, OdometryNoiseConfig] = Field(
        default_factory=lambda: {"kiss_icp": OdometryNoiseConfig(rot_sigma=1e-3, trans_sigma=0.05)},  # type: ignore[arg-type,dict-item]
        description=(
            "odometry sigmas per source (frontend.odometry.kind). LiDAR odometry turns far more "
            "accurately than wheels: with wheel-like rotation sigmas the graph bends the trajectory to "
            "close a loop instead of undoing the stretch kiss-icp actually made (bench_loop_oracle, KITTI 06 route)"
        ),
    )
    loop: LoopNoiseConfig = LoopNoiseConfig()
    robust: RobustKernelConfig = RobustKernelConfig()
    isam2: ISAM2Config = ISAM2Config()
    gnc: GncConfig = GncConfig()
    rotation_tolerance: float = Field(
        1e-4, gt=0, description="max |R^T R - I| and |det R - 1| accepted for an input pose"
    )

    def for_odometry(self, source: str) -> PoseGraphConfig:
        """This config with the odometry sigmas of `source` (a `frontend.odometry.kind`)."""
        noise = self.odometry_by_source.get(source)  # type: ignore[call-overload]
        return self if noise is None else self.model_copy(update={"odometry": noise})


class IcpStageConfig(SettingsModel):
    """One pass of kiss-icp's point-to-point ICP; stages run coarse to fine."""

    max_correspondence_distance: float = Field(gt=0, description="m")
    kernel: float = Field(gt=0, description="kiss-icp robust kernel scale, m")
    max_iterations: int = Field(200, ge=1)


def _default_stages() -> list[IcpStageConfig]:
    return [
        IcpStageConfig(max_correspondence_distance=3.0, kernel=1.0),
        IcpStageConfig(max_correspondence_distance=1.0, kernel=0.3),
    ]


class LidarRegistrationConfig(SettingsModel):
    """Scan-to-(local)map registration of a loop with kiss-icp."""

    voxel_size: float = Field(1.0, gt=0, description="m; kiss-icp map voxel size")
    map_downsample_factor: float = Field(0.5, gt=0, description="x voxel_size, as kiss-icp")
    source_downsample_factor: float = Field(1.5, gt=0, description="x voxel_size, as kiss-icp")
    max_points_per_voxel: int = Field(20, ge=1, description="points kept per voxel of the target map")
    max_range: float = Field(100.0, gt=0, description="m; points farther away are dropped")
    convergence_criterion: float = Field(1e-4, gt=0, description="ICP stops once a pose update's norm is below this")
    max_num_threads: int = Field(
        8,
        ge=0,
        description="Threads of the loop ICP, at most the cores (0 = all cores), as the odometry's (the same "
        "default, so that a run whose odometry shares its process keeps both): kiss-icp fixes "
        "one cap per process at its first registration "
        "(frontend/odometry/kiss_threads.py): where the odometry runs in the main process (pipeline.overlap "
        "false), the first built of this and frontend.odometry.kiss_icp.max_num_threads counts for both",
    )
    stages: list[IcpStageConfig] = Field(
        default_factory=_default_stages,
        min_length=1,
        description="ICP passes, coarse to fine: max_correspondence_distance, kernel (m), max_iterations",
    )
    yaw_seed_offsets_deg: list[float] = Field(
        default_factory=lambda: [0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0, 180.0],
        min_length=1,
        description="yaw seeds tried around the caller's guess, in this order",
    )
    screening_iterations: int = Field(
        50, ge=1, description="ICP iterations of the first stage when screening each seed"
    )
    seed_search: Literal["first_acceptable", "best"] = Field(
        "first_acceptable",
        description="first_acceptable: seeds nearest the guess first; the first seed, and any that screens at "
        "early_stop_inlier_ratio, is refined at once, and the first that passes acceptance ends the search (faster "
        "for the same decisions: docs/slam_demo.md). Where a scene has an acceptable "
        "alias (a half-turn symmetric hall) it takes the one nearest the guess. best: screen every seed, refine "
        "the refine_top_k best, keep the best",
    )
    refine_top_k: int = Field(2, ge=1, description="best screened seeds that run all stages")
    early_stop_inlier_ratio: float | None = Field(
        None,
        ge=0,
        le=1,
        description="first_acceptable only (best ignores it): a screened seed this good is refined at once, as "
        "the first seed always is. None: min_inlier_ratio",
    )
    inlier_distance: float = Field(0.5, gt=0, description="m; distance to the nearest raw map point counted as inlier")
    min_inlier_ratio: float = Field(
        0.8, ge=0, le=1, description="share of inliers to accept (demo: true loops >= 0.89, aliased streets <= 0.69)"
    )
    max_rmse: float = Field(0.3, gt=0, description="m; RMSE of the inlier distances")
    min_points: int = Field(50, ge=3, description="after down-sampling, per cloud")
    local_map_half_window: int = Field(2, ge=0, description="keyframes m-k..m+k make the target local map")
    carry_loop_keyframes: int = Field(
        8,
        ge=0,
        description="an ICP loop of the same revisit, its query at most this many keyframes back and its match "
        "within as many of the new match, moved "
        "along both by odometry, is the first seed of the next registration (revisits come as runs of loops, "
        "the demo's reverse ones with gaps of up to 7 keyframes); 0: never",
    )
    loop_spacing_keyframes: int = Field(
        1,
        ge=1,
        description="ICP loops of one revisit are registered at least this many keyframes apart: a proposal "
        "whose query is fewer keyframes after an accepted ICP loop's query, with its match as near that "
        "loop's match, is recorded (method 'spaced') but not registered, as odometry already carries that "
        "loop's correction to it. Registration is most of a revisit keyframe's back-end cost: the fast preset's 4 "
        "took the demo log from 329 to 287 core-ms a keyframe with the same ATE after the loops (docs/slam_demo.md). "
        "1: register every accepted loop",
    )
    rot_sigma: float = Field(0.02, gt=0, description="rad; factor sigma of an accepted ICP loop")
    trans_sigma: float = Field(0.1, gt=0, description="m; factor sigma of an accepted ICP loop")


def _optical_to_flu() -> list[list[float]]:
    # Camera optical frame (x right, y down, z forward) expressed in a body frame
    # (x forward, y left, z up): body_x = cam_z, body_y = -cam_x, body_z = -cam_y.
    return [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]


class TwoViewConfig(SettingsModel):
    """Place prior without LiDAR: rotation from two-view geometry, translation from a radius."""

    fx: float | None = Field(None, gt=0, description="px; None = from hfov_deg and image width")
    fy: float | None = Field(None, gt=0, description="px; None = fx")
    cx: float | None = Field(None, description="px; None = image centre")
    cy: float | None = Field(None, description="px; None = image centre")
    hfov_deg: float = Field(60.0, gt=0, lt=180, description="used only when fx is None")
    body_from_camera: list[list[float]] = Field(
        default_factory=_optical_to_flu, description="3x3 rotation, camera axes in body frame"
    )
    method: Literal["deep", "orb"] = Field(
        "deep",
        description="deep: the backbone's conv4_2 cells matched and an essential matrix fitted by MAGSAC "
        "(loopclosure/pair_verifier.py, settings in `deep`), which holds across day and night; orb: ORB "
        "features, an essential matrix or a pure-rotation homography (the settings below)",
    )
    deep: VerifierConfig = Field(default_factory=VerifierConfig, description="the deep-feature verifier")
    orb_refines_deep: bool = Field(
        True, description="deep: where ORB also gives a rotation (same light) that agrees, use ORB's (sub-pixel)"
    )
    orb_agreement_deg: float = Field(5.0, gt=0, description="deep: how far ORB's rotation may be from the deep one")
    orb_features: int = Field(2000, ge=8, description="ORB keypoints detected per image at most")
    ratio_test: float = Field(0.8, gt=0, le=1, description="Lowe ratio for ORB matches")
    ransac_confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC confidence of the E and H fits")
    ransac_threshold_px: float = Field(1.0, gt=0, description="essential matrix (epipolar)")
    homography_threshold_px: float = Field(
        2.0, gt=0, description="homography transfer error; 2-D, so looser than the epipolar one"
    )
    min_inliers: int = Field(30, ge=5, description="below this the geometry has failed (see on_geometry_failure)")
    on_geometry_failure: Literal["consistent", "yaw_prior", "reject"] = Field(
        "consistent",
        description="when two images give no rotation (and for a loop no image or scan can check): consistent: "
        "a factor on the yaw guess only once earlier loops of the same revisit agree with it under odometry "
        "(backend.registration.consistency), else none; yaw_prior: a factor on the yaw guess, unchecked; "
        "reject: no factor, as ICP rejects a poor alignment",
    )
    homography_share: float = Field(0.8, gt=0, description="H inliers / E inliers above which pure rotation is tested")
    rotation_singular_tol: float = Field(
        0.05, gt=0, description="K^-1 H K counts as a rotation if s_min/s_max >= 1 - tol"
    )
    translation_sigma: float = Field(
        3.0, gt=0, description="m; the place prior's zero translation. Two views of one place lie a few metres "
        "apart, and the loops of one revisit share their offset (another lane), so they are not independent: "
        "each is weighted at 1.5x the 2 m place radius (docs/loop_verification.md has the sweep)"
    )  # fmt: skip
    rot_sigma: float = Field(
        0.03, gt=0, description="rad; a rotation from keypoints (ORB; with method deep, ORB agreeing with the deep "
        "features): 0.6-0.8 deg median error, 1.5-1.8 deg p90 on the demo's loops (docs/loop_verification.md)"
    )  # fmt: skip
    deep_rot_sigma: float = Field(
        0.05, gt=0, description="rad; a rotation from the deep features' cells alone (no agreeing ORB rotation, as "
        "across light): 1.3 deg median error, 2.8 deg p90 on the demo's loops"
    )  # fmt: skip
    yaw_prior_yaw_sigma: float = Field(0.35, gt=0, description="rad; fallback yaw sigma")
    yaw_prior_tilt_sigma: float = Field(0.1, gt=0, description="rad; fallback roll/pitch")

    @field_validator("body_from_camera")
    @classmethod
    def _is_3x3(cls, value: list[list[float]]) -> list[list[float]]:
        if len(value) != 3 or any(len(row) != 3 for row in value):
            raise ValueError("body_from_camera must be a 3x3 matrix")
        return value


def _gated_sources() -> list[OdometryKind]:
    return ["kiss_icp"]


class OdometryGateConfig(SettingsModel):
    """A session loop is refused before registration when the odometry puts its two keyframes
    farther apart than the odometry's drift over the path between them could explain. Appearance
    aliases across a city (the rear camera on the KITTI 06 route shape: 197 wrong loops 17-385 m
    away) then cost no failed ICP, and a camera-only run keeps them out of the graph."""

    sources: list[OdometryKind] = Field(
        default_factory=_gated_sources,
        description="odometry kinds (frontend.odometry.kind) whose drift the bound below holds for; logged "
        "poses may be wheel odometry of any drift, so they are not gated unless named",
    )
    base_m: float = Field(10.0, gt=0, description="m allowed whatever the path (the place radius and more)")
    per_m_travelled: float = Field(
        0.02,
        ge=0,
        description="m allowed per metre driven between the two keyframes: above the odometry's drift (docs/method.md)",
    )
    max_heading_deg: float | None = Field(
        90.0,
        gt=0,
        le=180,
        description="deg: a loop (any odometry) whose heading, as the match claims it (the rear camera's turned "
        "half round), differs from the odometry's by more than this is refused: a rear camera that matches "
        "a street it drives the same way, a symmetric street seen backwards (the test city: wrong rear loops "
        "11-49 m off). None: no heading check",
    )

    def limit(self, travelled_m: float) -> float:
        """The largest odometry offset of a loop across `travelled_m` metres of driving."""
        return self.base_m + self.per_m_travelled * travelled_m


class LoopConsistencyConfig(SettingsModel):
    """When a loop no geometry verified may still become a factor (two_view.on_geometry_failure:
    consistent): earlier loops of the same revisit must agree with it. Loops q_j -> m_j and
    q -> m agree when loop j, carried along both visits by odometry to (m, q), lands within these
    bounds of loop q's own place prior: the two stretches of path have the same shape, as they do
    where one street was driven twice, and an isolated wrong match does not."""

    min_support: int = Field(2, ge=1, description="earlier loops of the revisit that must agree")
    window_keyframes: int = Field(
        10, ge=1, description="how far back (query keyframes) and apart (match keyframes) a supporting loop may lie"
    )
    max_translation_m: float = Field(
        1.5, gt=0, description="m of disagreement allowed whatever the path (right loops of one revisit agree "
        "within their places' spread; a symmetric street seen backwards slides two keyframe spacings a keyframe)"
    )  # fmt: skip
    per_m_travelled: float = Field(
        0.1, ge=0, description="m allowed per metre driven on the two stretches between the loops: above a "
        "wheel odometry's drift"
    )  # fmt: skip
    max_rotation_deg: float = Field(25.0, gt=0, le=180, description="deg of disagreement in rotation")


class LoopRegistrationConfig(SettingsModel):
    """Both registration paths, and the odometry check before either."""

    lidar: LidarRegistrationConfig = LidarRegistrationConfig()
    two_view: TwoViewConfig = TwoViewConfig()
    odometry_gate: OdometryGateConfig = OdometryGateConfig()
    consistency: LoopConsistencyConfig = LoopConsistencyConfig()


class BackendConfig(SettingsModel):
    """Root of the back end's configuration."""

    pose_graph: PoseGraphConfig = PoseGraphConfig()
    registration: LoopRegistrationConfig = LoopRegistrationConfig()
