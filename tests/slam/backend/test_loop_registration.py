"""Loop registration: kiss-icp scan alignment with yaw seeds, and the camera place prior."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ssmvpr_slam import loop_policy
from ssmvpr_slam.backend.config import LoopRegistrationConfig
from ssmvpr_slam.backend.loop_registration import LoopRegistrar, build_local_map, carry_loop
from ssmvpr_slam.backend.se3 import invert, make_pose, rot_z, rotation_angle, yaw_of
from ssmvpr_slam.backend.two_view import ReducedImage, intrinsics, reduce_image

DENSITY = 10.0  # surface points per m^2
SCAN_RANGE = 25.0
YAW_TOL_DEG = 0.5
TRANS_TOL_M = 0.1


# --------------------------------------------------------------------------- LiDAR scenes
def box_surface(rng, lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    faces = []
    for axis in range(3):
        other = [a for a in range(3) if a != axis]
        n = max(1, int(np.prod(hi[other] - lo[other]) * DENSITY))
        for value in (lo[axis], hi[axis]):
            pts = rng.uniform(lo, hi, (n, 3))
            pts[:, axis] = value
            faces.append(pts)
    return np.concatenate(faces)


BOXES = [  # a 30 x 20 m room with asymmetric pillars and crates
    ([-15, -10, -1], [15, 10, 3]),
    ([-8, -4, -1], [-7, -3, 3]),
    ([4, 2, -1], [5.5, 3.5, 3]),
    ([9, -7, -1], [12, -5, 0.5]),
    ([-12, 5, -1], [-10, 9, 1.5]),
    ([0, -9, -1], [0.5, -2, 2]),
]


def world(seed: int) -> np.ndarray:
    """An independent surface sampling of the same room (like two LiDAR visits)."""
    rng = np.random.default_rng(seed)
    return np.concatenate([box_surface(rng, lo, hi) for lo, hi in BOXES])


def scan(world_pts, pose, seed, noise=0.02):
    local = (world_pts - pose[:3, 3]) @ pose[:3, :3]
    local = local[np.linalg.norm(local, axis=1) < SCAN_RANGE]
    return local + np.random.default_rng(seed).normal(0, noise, local.shape)


T_M = make_pose(rot_z(0.2), [-2.0, 1.0, 0.0])
T_MQ = make_pose(rot_z(np.radians(40.0)), [1.5, -0.8, 0.05])


@pytest.fixture(scope="module")
def scans():
    return scan(world(1), T_M @ T_MQ, seed=11), scan(world(2), T_M, seed=12)


@pytest.fixture(scope="module")
def registrar():
    return LoopRegistrar()


def pose_error(estimate: np.ndarray) -> tuple[float, float]:
    err = invert(T_MQ) @ estimate
    return np.degrees(rotation_angle(err[:3, :3])), float(np.linalg.norm(err[:3, 3]))


def test_icp_recovers_known_yaw_and_translation(scans, registrar):
    query, target = scans
    reg = registrar.register_scans(query, target, yaw_guess=np.radians(35.0))
    assert reg.accepted, reg.reason
    rot_err, trans_err = pose_error(reg.T_mq)
    assert rot_err < YAW_TOL_DEG and trans_err < TRANS_TOL_M
    assert reg.inlier_ratio > 0.9
    np.testing.assert_allclose(reg.T_qm @ reg.T_mq, np.eye(4), atol=1e-12)
    assert reg.sigmas.shape == (6,) and np.all(reg.sigmas > 0)


class _Counted:
    """A kiss-icp Registration that counts its alignments."""

    def __init__(self, inner):
        self.inner, self.calls = inner, 0

    def align_points_to_map(self, **kwargs):
        self.calls += 1
        return self.inner.align_points_to_map(**kwargs)


def test_a_seed_that_already_passes_ends_screening_with_the_pose_of_screening_every_seed(scans):
    """The default ends the search at the first seed whose refined alignment passes acceptance;
    screening all eight and refining each lands on the same pose, at eight times the screening."""
    query, target = scans
    default = LoopRegistrar()
    assert default.config.lidar.early_stop_inlier_ratio is None  # follows min_inlier_ratio
    lidar = default.config.lidar.model_copy(update={"seed_search": "best", "refine_top_k": 8})
    every = LoopRegistrar(default.config.model_copy(update={"lidar": lidar}))
    counted = {}
    for name, registrar in (("default", default), ("every", every)):
        registrar._icp._screen = counted[name] = _Counted(registrar._icp._screen)
    fast = default.register_scans(query, target, yaw_guess=np.radians(35.0))
    slow = every.register_scans(query, target, yaw_guess=np.radians(35.0))
    assert fast.accepted and slow.accepted
    assert counted["default"].calls == 1 and counted["every"].calls == len(lidar.yaw_seed_offsets_deg)
    np.testing.assert_allclose(fast.T_mq, slow.T_mq, atol=1e-6)
    assert pose_error(fast.T_mq)[1] < TRANS_TOL_M


def test_a_pose_guess_is_screened_first_and_ends_screening_when_it_aligns(scans):
    """A carried loop's full pose aligns at once where the visual yaw guess is far off."""
    query, target = scans
    registrar = LoopRegistrar()
    registrar._icp._screen = counted = _Counted(registrar._icp._screen)
    guess = T_MQ @ make_pose(rot_z(np.radians(3.0)), [0.4, -0.3, 0.0])  # near the truth
    reg = registrar.register_scans(query, target, yaw_guess=np.radians(40.0 + 150.0), pose_guess=guess)
    assert reg.accepted, reg.reason
    assert counted.calls == 1
    rot_err, trans_err = pose_error(reg.T_mq)
    assert rot_err < YAW_TOL_DEG and trans_err < TRANS_TOL_M


def _with_lidar(**update) -> LoopRegistrar:
    default = LoopRegistrationConfig()
    return LoopRegistrar(default.model_copy(update={"lidar": default.lidar.model_copy(update=update)}))


def test_the_first_seed_is_refined_at_once_so_a_right_guess_ends_the_search_before_screening_converges(scans):
    """Screening cut short (one iteration) scores the right guess far below min_inlier_ratio;
    refined at once, it passes, so no other seed is screened (reverse revisits on the demo city:
    screening every seed had made them 660 ms a loop)."""
    query, target = scans
    registrar = _with_lidar(screening_iterations=1)
    registrar._icp._screen = counted = _Counted(registrar._icp._screen)
    screen_ratios = []
    quality = registrar._icp._quality

    def recorded(tree, source, pose):
        ratio, rmse = quality(tree, source, pose)
        screen_ratios.append(ratio)
        return ratio, rmse

    registrar._icp._quality = recorded
    guess = T_MQ @ make_pose(rot_z(np.radians(8.0)), [1.5, -1.0, 0.0])
    reg = registrar.register_scans(query, target, yaw_guess=yaw_of(guess), pose_guess=guess)
    assert reg.accepted, reg.reason
    assert counted.calls == 1
    assert screen_ratios[0] < registrar.config.lidar.min_inlier_ratio  # screening alone would go on
    rot_err, trans_err = pose_error(reg.T_mq)
    assert rot_err < YAW_TOL_DEG and trans_err < TRANS_TOL_M


def test_a_refined_seed_that_fails_acceptance_does_not_end_the_search(scans):
    """With an RMSE bound nothing can meet, every seed is screened and the best is reported
    (rejected), rather than the search stopping at the first seed that screened well."""
    query, target = scans
    registrar = _with_lidar(max_rmse=1e-6)
    registrar._icp._screen = counted = _Counted(registrar._icp._screen)
    reg = registrar.register_scans(query, target, yaw_guess=np.radians(40.0))
    assert not reg.accepted and "RMSE" in reg.reason
    assert counted.calls == len(registrar.config.lidar.yaw_seed_offsets_deg)
    assert pose_error(reg.T_mq)[1] < TRANS_TOL_M  # still the best alignment found


def test_carry_loop_is_exact_when_each_visits_odometry_is_exact_over_the_carry():
    """Each visit's odometry is off by its own rigid drift; carried along both, the drifts cancel."""
    truth = {name: make_pose(rot_z(a), [x, y, 0.1 * a]) for name, a, x, y in
             [("m", 0.3, 10.0, 2.0), ("q", 0.35, 11.0, 2.5), ("m2", 0.4, 12.0, 3.0), ("q2", 0.5, 14.0, 3.1)]}  # fmt: skip
    first, second = make_pose(rot_z(0.7), [5.0, -3.0, 1.0]), make_pose(rot_z(-1.1), [-40.0, 8.0, 0.0])
    odom = {"m": first @ truth["m"], "m2": first @ truth["m2"], "q": second @ truth["q"], "q2": second @ truth["q2"]}
    T_mq = invert(truth["m"]) @ truth["q"]
    carried = carry_loop(T_mq, odom["m"], odom["q"], odom["m2"], odom["q2"])
    np.testing.assert_allclose(carried, invert(truth["m2"]) @ truth["q2"], atol=1e-12)
    across = invert(odom["m2"]) @ odom["q2"]  # what the odometry alone says across the visits
    assert np.linalg.norm(across[:3, 3] - carried[:3, 3]) > 10.0


@pytest.mark.parametrize(("guess_offset_deg", "seed_search"), [(-95.0, "first_acceptable"), (175.0, "best")])
def test_icp_recovers_from_a_far_yaw_guess_within_the_seed_set(scans, guess_offset_deg, seed_search):
    query, target = scans
    guess = np.radians(40.0 + guess_offset_deg)
    reg = _with_lidar(seed_search=seed_search).register_scans(query, target, yaw_guess=guess)
    assert reg.accepted, reg.reason
    rot_err, trans_err = pose_error(reg.T_mq)
    assert rot_err < YAW_TOL_DEG and trans_err < TRANS_TOL_M
    assert reg.yaw_seed != pytest.approx(guess)  # another seed than the guess won


def test_first_acceptable_takes_the_alias_nearest_the_guess_where_best_finds_the_truth(scans):
    """The room is nearly symmetric under a half turn: flipped, 94 % of the query's points find a
    wall, above min_inlier_ratio. From a guess near the flip the default search stops there;
    `best` screens every seed and finds the true alignment (every point an inlier)."""
    query, target = scans
    guess = np.radians(40.0 + 175.0)
    first = _with_lidar().register_scans(query, target, yaw_guess=guess)
    best = _with_lidar(seed_search="best").register_scans(query, target, yaw_guess=guess)
    assert first.accepted and pose_error(first.T_mq)[0] > 170.0
    assert best.accepted and pose_error(best.T_mq)[0] < YAW_TOL_DEG
    assert best.inlier_ratio > first.inlier_ratio


def test_a_single_far_seed_fails_so_the_seed_set_matters(scans):
    cfg = LoopRegistrationConfig()
    cfg.lidar.yaw_seed_offsets_deg = [0.0]
    query, target = scans
    reg = LoopRegistrar(cfg).register_scans(query, target, yaw_guess=np.radians(40.0 - 95.0))
    rot_err, _ = pose_error(reg.T_mq)
    assert not reg.accepted or rot_err > 5.0


def test_unrelated_cloud_is_rejected_with_a_reason(scans, registrar):
    query, _ = scans
    unrelated = np.random.default_rng(5).uniform(-15, 15, (20000, 3))
    reg = registrar.register_scans(query, unrelated, yaw_guess=0.0)
    assert not reg.accepted
    assert reg.reason.startswith("poor alignment")


def test_nan_points_are_dropped_and_too_few_points_rejected(scans, registrar):
    query, target = scans
    dirty = query.copy()
    dirty[::7] = np.nan
    dirty[1::11, 2] = np.inf
    reg = registrar.register_scans(dirty, target, yaw_guess=np.radians(40.0))
    assert reg.accepted, reg.reason
    tiny = registrar.register_scans(query[:10], target, yaw_guess=0.0)
    assert not tiny.accepted and "query scan has" in tiny.reason
    empty = registrar.register_scans(np.full((100, 3), np.nan), target)
    assert not empty.accepted and "query scan" in empty.reason
    no_map = registrar.register_scans(query, np.zeros((0, 3)))
    assert not no_map.accepted and "map has 0 points" in no_map.reason


def test_the_odometry_gate_allows_a_base_plus_a_share_of_the_path_and_says_so():
    config = LoopRegistrationConfig()
    gate = config.odometry_gate
    assert gate.sources == ["kiss_icp"]  # logged poses (wheel odometry of any drift) are not gated by default
    assert gate.limit(0.0) == 10.0 and gate.limit(500.0) == pytest.approx(20.0)
    refused = loop_policy.implausible(config, 107.25, 95.0)
    assert not refused.accepted and refused.method == "implausible"
    assert refused.reason.startswith("implausible: odometry puts the keyframes 107.2 m apart, beyond 11.9 m")
    assert "10 m + 0.02 x 95 m driven between them" in refused.reason


def test_bad_shapes_and_yaw_are_value_errors(registrar):
    with pytest.raises(ValueError, match="query_points"):
        registrar.register_scans(np.zeros((10, 2)), np.zeros((10, 3)))
    with pytest.raises(ValueError, match="yaw_guess"):
        registrar.register_scans(np.zeros((10, 3)), np.zeros((10, 3)), yaw_guess=float("nan"))


def test_local_map_from_neighbouring_keyframes(registrar):
    """Map of keyframes m-1..m+1 in m's frame; the query registers against it."""
    pts = world(3)
    poses = [T_M @ make_pose(rot_z(0.05 * k), [2.0 * k, 0.0, 0.0]) for k in (-1, 0, 1)]
    scans_k = [scan(pts, p, seed=20 + k) for k, p in enumerate(poses)]
    local = build_local_map(scans_k, poses, anchor_pose=T_M, max_range=100.0)
    query = scan(world(4), T_M @ T_MQ, seed=30)
    reg = registrar.register_scans(query, local, yaw_guess=np.radians(40.0))
    assert reg.accepted, reg.reason
    rot_err, trans_err = pose_error(reg.T_mq)
    assert rot_err < YAW_TOL_DEG and trans_err < TRANS_TOL_M
    with pytest.raises(ValueError, match="poses"):
        build_local_map([pts], [], anchor_pose=T_M, max_range=100.0)


# --------------------------------------------------------------------------- camera scenes
H_PX, W_PX = 480, 640


def texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (H_PX // 8, W_PX // 8), dtype=np.uint8)
    img = cv2.resize(img, (W_PX, H_PX), interpolation=cv2.INTER_NEAREST)
    for _ in range(300):
        centre = tuple(int(v) for v in rng.integers(0, [W_PX, H_PX]))
        cv2.circle(img, centre, int(rng.integers(3, 25)), int(rng.integers(0, 256)), -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


@pytest.fixture(scope="module")
def camera():
    """ORB's path (`two_view.method: orb`); the deep-feature path is tested below on the same scenes."""
    cfg = LoopRegistrationConfig()
    cfg = cfg.model_copy(update={"two_view": cfg.two_view.model_copy(update={"method": "orb"})})
    body_from_cam = np.asarray(cfg.two_view.body_from_camera)
    k = intrinsics(cfg.two_view, W_PX, H_PX)
    return cfg, body_from_cam, k, texture(0)


def cam_rotation_qm(body_from_cam, yaw_deg):
    """R_qm in optical axes for a body yaw (left turn positive) of q relative to m."""
    r_mq_cam = body_from_cam.T @ rot_z(np.radians(yaw_deg)) @ body_from_cam
    return r_mq_cam.T


@pytest.mark.parametrize("yaw_deg", [6.0, -9.0, 15.0])
def test_pure_rotation_yaw_is_recovered(camera, yaw_deg):
    cfg, body_from_cam, k, img_m = camera
    h = k @ cam_rotation_qm(body_from_cam, yaw_deg) @ np.linalg.inv(k)
    img_q = cv2.warpPerspective(img_m, h, (W_PX, H_PX))
    reg = LoopRegistrar(cfg).register_images(img_q, img_m, yaw_guess=0.0)
    assert reg.accepted and reg.method == "two_view_homography", reg.reason
    assert np.degrees(yaw_of(reg.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=1.0)
    np.testing.assert_allclose(reg.T_mq[:3, 3], 0.0)
    assert reg.sigmas[3] == cfg.two_view.translation_sigma


def _corner_view(
    img_m: np.ndarray, k: np.ndarray, r_qm: np.ndarray, t_mq_cam: list[float], split_px: int
) -> np.ndarray:
    """The query view of a concave corner of two textured walls 6 m away (the left wall up to
    column `split_px` of the matched image), after the camera moved by (r_qm, t_mq_cam)."""
    t_qm = -r_qm @ np.asarray(t_mq_cam)
    left = np.zeros((H_PX, W_PX), np.float32)
    left[:, :split_px] = 1.0
    img_q = np.zeros((H_PX, W_PX), np.float32)
    depth = 6.0
    for normal, mask in (((-1, 0, 1), left), ((1, 0, 1), 1.0 - left)):
        n = np.asarray(normal, float) / np.sqrt(2.0)
        h = k @ (r_qm + np.outer(t_qm, n) / (depth / np.sqrt(2.0))) @ np.linalg.inv(k)
        warped = cv2.warpPerspective(img_m.astype(np.float32), h, (W_PX, H_PX))
        img_q += warped * cv2.warpPerspective(mask, h, (W_PX, H_PX), flags=cv2.INTER_NEAREST)
    return img_q.astype(np.uint8)


@pytest.mark.parametrize(("yaw_deg", "t_mq_cam"), [(10.0, [1.0, 0.0, 0.3]), (-6.0, [-1.5, 0.0, 0.5])])
def test_essential_matrix_yaw_with_baseline(camera, yaw_deg, t_mq_cam):
    """A concave corner of two textured walls 6 m away, seen after a sideways step."""
    cfg, body_from_cam, k, img_m = camera
    img_q = _corner_view(img_m, k, cam_rotation_qm(body_from_cam, yaw_deg), t_mq_cam, W_PX // 2)
    reg = LoopRegistrar(cfg).register_images(img_q, img_m, yaw_guess=0.0)
    assert reg.accepted and reg.method == "two_view_essential", reg.reason
    assert np.degrees(yaw_of(reg.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=2.5)


@pytest.mark.parametrize("yaw_deg", [8.0, -12.0])
def test_rear_camera_images_give_the_body_rotation_turned_half_a_circle(camera, yaw_deg):
    """The query's rear camera saw the place the match's forward camera saw, turned by yaw_deg:
    the body is turned by yaw_deg + 180 deg."""
    cfg, body_from_cam, k, img_m = camera
    h = k @ cam_rotation_qm(body_from_cam, yaw_deg) @ np.linalg.inv(k)
    img_rear = cv2.warpPerspective(img_m, h, (W_PX, H_PX))
    reg = LoopRegistrar(cfg).register_images(img_rear, img_m, yaw_guess=np.pi, query_yaw_offset=np.pi)
    assert reg.accepted and reg.method == "two_view_homography", reg.reason
    yaw = np.degrees(yaw_of(reg.T_mq[:3, :3]))
    assert np.degrees(np.angle(np.exp(1j * np.radians(yaw - yaw_deg - 180.0)))) == pytest.approx(0.0, abs=1.0)
    np.testing.assert_allclose(reg.T_mq[:3, :3] @ reg.T_mq[:3, :3].T, np.eye(3), atol=1e-9)


def test_featureless_images_fall_back_to_the_yaw_guess(camera):
    cfg, _, _, img_m = camera
    blank = np.zeros((H_PX, W_PX, 3), np.uint8)
    reg = LoopRegistrar(cfg).register_images(blank, img_m, yaw_guess=0.3)
    assert reg.accepted and reg.method == "yaw_prior"
    assert yaw_of(reg.T_mq[:3, :3]) == pytest.approx(0.3)
    assert reg.sigmas[2] == cfg.two_view.yaw_prior_yaw_sigma
    assert reg.to_dict()["rmse"] is None


def test_featureless_images_are_rejected_when_configured(camera):
    """on_geometry_failure: reject turns the fallback into a rejection (no factor), and only
    when the images gave no rotation: a pair that does give one is accepted as before."""
    cfg, body_from_cam, k, img_m = camera
    strict = cfg.model_copy(update={"two_view": cfg.two_view.model_copy(update={"on_geometry_failure": "reject"})})
    registrar = LoopRegistrar(strict)
    reg = registrar.register_images(np.zeros((H_PX, W_PX, 3), np.uint8), img_m, yaw_guess=0.3)
    assert not reg.accepted and reg.method == "two_view_failed"
    assert reg.reason.startswith("two-view geometry failed: ")
    assert yaw_of(reg.T_mq[:3, :3]) == pytest.approx(0.3)  # the guess, for the record
    h = k @ cam_rotation_qm(body_from_cam, 8.0) @ np.linalg.inv(k)
    reg = registrar.register_images(cv2.warpPerspective(img_m, h, (W_PX, H_PX)), img_m)
    assert reg.accepted and reg.method == "two_view_homography", reg.reason


def test_bad_images_are_value_errors(camera):
    cfg, _, _, img_m = camera
    registrar = LoopRegistrar(cfg)
    with pytest.raises(ValueError, match="query_image"):
        registrar.register_images(np.zeros((4, 4, 2)), img_m)
    with pytest.raises(ValueError, match="match_image"):
        registrar.register_images(img_m, "not an image")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="NaN"):
        registrar.register_images(np.full((8, 8), np.nan), img_m)


# --------------------------------------------------------------------------- kept (reduced) images
KEPT_PIXELS = 76800  # the default budget (pipeline.keyframe_image_pixels): 320 x 240, half of this 640 x 480


def test_reduce_image_keeps_a_grey_copy_within_the_pixel_budget(camera):
    _, _, _, img_m = camera
    rgb = np.dstack([img_m, img_m // 2, 255 - img_m])
    kept = reduce_image(rgb, KEPT_PIXELS)
    assert kept.gray.shape == (240, 320) and kept.gray.dtype == np.uint8 and (kept.width, kept.height) == (320, 240)
    assert (kept.full_width, kept.full_height) == (W_PX, H_PX) and kept.scale == (0.5, 0.5)
    np.testing.assert_array_equal(kept.gray, cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (320, 240),
                                                        interpolation=cv2.INTER_AREA))  # fmt: skip
    assert kept.nbytes == len(kept.png) < 320 * 240  # held as lossless PNG bytes
    assert ReducedImage.from_png(kept.png, W_PX, H_PX) == kept
    odd = reduce_image(np.zeros((376, 1241, 3), np.uint8), KEPT_PIXELS)  # a KITTI image
    assert odd.gray.size <= KEPT_PIXELS and abs(odd.gray.shape[1] / odd.gray.shape[0] - 1241 / 376) < 0.02
    small = reduce_image(img_m[:100, :100], KEPT_PIXELS)  # already within budget: full size
    assert small.gray.shape == (100, 100) and small.scale == (1.0, 1.0)
    assert reduce_image(img_m, None).gray.shape == (H_PX, W_PX)


def test_intrinsics_of_a_kept_image_are_the_full_ones_scaled(camera):
    cfg = camera[0].two_view
    # from hfov and the image size: the same K whether computed at the kept size or scaled
    np.testing.assert_allclose(intrinsics(cfg, W_PX, H_PX, (0.5, 0.5)), intrinsics(cfg, 320, 240), atol=1e-12)
    calibrated = cfg.model_copy(update={"fx": 500.0, "fy": 510.0, "cx": 300.0, "cy": 250.0})
    k = intrinsics(calibrated, W_PX, H_PX, (0.5, 0.25))
    np.testing.assert_allclose(k, [[250.0, 0.0, 149.75], [0.0, 127.5, 62.125], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("yaw_deg", [6.0, -9.0, 15.0])
def test_pure_rotation_yaw_is_recovered_on_the_kept_images(camera, yaw_deg):
    """The keyframes' grey copies at the default budget (half of this camera) give the same yaw."""
    cfg, body_from_cam, k, img_m = camera
    h = k @ cam_rotation_qm(body_from_cam, yaw_deg) @ np.linalg.inv(k)
    img_q = cv2.warpPerspective(img_m, h, (W_PX, H_PX))
    reg = LoopRegistrar(cfg).register_images(reduce_image(img_q, KEPT_PIXELS), reduce_image(img_m, KEPT_PIXELS))
    assert reg.accepted and reg.method == "two_view_homography", reg.reason
    assert np.degrees(yaw_of(reg.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=1.0)


@pytest.mark.parametrize(("yaw_deg", "t_mq_cam"), [(10.0, [1.0, 0.0, 0.3]), (-6.0, [-1.5, 0.0, 0.5])])
def test_essential_matrix_yaw_on_the_kept_images_with_calibrated_intrinsics(camera, yaw_deg, t_mq_cam):
    """A calibration given for the full image (off-centre principal point, fx from no hfov)
    stays valid on the kept copies: K is scaled with them."""
    cfg, body_from_cam, _, img_m = camera
    two_view = cfg.two_view.model_copy(update={"fx": 520.0, "fy": 520.0, "cx": 300.0, "cy": 260.0})
    k = intrinsics(two_view, W_PX, H_PX)
    img_q = _corner_view(img_m, k, cam_rotation_qm(body_from_cam, yaw_deg), t_mq_cam, 300)
    registrar = LoopRegistrar(cfg.model_copy(update={"two_view": two_view}))
    reg = registrar.register_images(reduce_image(img_q, KEPT_PIXELS), reduce_image(img_m, KEPT_PIXELS))
    assert reg.accepted and reg.method == "two_view_essential", reg.reason
    assert np.degrees(yaw_of(reg.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=2.5)


def test_kept_images_from_different_cameras_fall_back_to_the_yaw_guess(camera):
    cfg, _, _, img_m = camera
    reg = LoopRegistrar(cfg).register_images(reduce_image(img_m, KEPT_PIXELS), reduce_image(img_m[:, :600], KEPT_PIXELS),
                                             yaw_guess=0.2)  # fmt: skip
    assert reg.method == "yaw_prior" and "sizes differ" in reg.reason
    assert not reg.views_refused  # nothing was judged


# --------------------------------------------------------------------------- deep features (the default)
@pytest.fixture(scope="module")
def deep(weights_path):
    from loopclosure.backbone import load_backbone
    from loopclosure.config import BackboneConfig
    from loopclosure.pair_verifier import PairVerifier

    cfg = LoopRegistrationConfig()
    assert cfg.two_view.method == "deep"
    verifier = PairVerifier(load_backbone(BackboneConfig(weights=str(weights_path), device="cpu")), cfg.two_view.deep)
    return LoopRegistrar(cfg, verifier)


@pytest.mark.parametrize(("yaw_deg", "t_mq_cam"), [(10.0, [1.0, 0.0, 0.3]), (-6.0, [-1.5, 0.0, 0.5])])
def test_deep_features_give_the_yaw_with_a_baseline_on_the_kept_images(camera, deep, yaw_deg, t_mq_cam):
    """The corner scene on the keyframes' grey copies: conv4_2 matches verify it and the
    essential matrix of their inliers gives the yaw; the translation stays the place prior."""
    _, body_from_cam, k, img_m = camera
    img_q = _corner_view(img_m, k, cam_rotation_qm(body_from_cam, yaw_deg), t_mq_cam, W_PX // 2)
    reg = deep.register_images(reduce_image(img_q, KEPT_PIXELS), reduce_image(img_m, KEPT_PIXELS), yaw_guess=0.0)
    assert reg.accepted and reg.method == "two_view_deep", reg.reason
    assert "essential matrix" in reg.reason
    assert np.degrees(yaw_of(reg.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=2.5)
    np.testing.assert_allclose(reg.T_mq[:3, 3], 0.0)
    two_view = deep.config.two_view
    assert "rotation from ORB" in reg.reason  # same light: ORB's keypoints agree and give the rotation
    assert reg.sigmas[0] == two_view.rot_sigma and reg.sigmas[3] == two_view.translation_sigma
    alone = LoopRegistrar(
        deep.config.model_copy(update={"two_view": two_view.model_copy(update={"orb_refines_deep": False})}),
        deep.verifier,
    ).register_images(reduce_image(img_q, KEPT_PIXELS), reduce_image(img_m, KEPT_PIXELS), yaw_guess=0.0)
    assert alone.method == "two_view_deep" and "rotation from ORB" not in alone.reason
    assert alone.sigmas[0] == two_view.deep_rot_sigma  # the cells' coarser rotation, a looser factor
    assert np.degrees(yaw_of(alone.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=2.5)


@pytest.mark.parametrize("yaw_deg", [6.0, -9.0])
def test_deep_features_read_a_pure_rotation_from_the_homography(camera, deep, yaw_deg):
    _, body_from_cam, k, img_m = camera
    h = k @ cam_rotation_qm(body_from_cam, yaw_deg) @ np.linalg.inv(k)
    img_q = cv2.warpPerspective(img_m, h, (W_PX, H_PX))
    reg = deep.register_images(reduce_image(img_q, KEPT_PIXELS), reduce_image(img_m, KEPT_PIXELS))
    assert reg.accepted and reg.method == "two_view_deep" and "a rotation only" in reg.reason, reg.reason
    assert np.degrees(yaw_of(reg.T_mq[:3, :3])) == pytest.approx(yaw_deg, abs=1.5)


def test_deep_features_refuse_another_scene_and_fall_back_as_configured(camera, deep):
    """Two different textures look alike to no geometry: the yaw prior, which the policy admits
    only once earlier loops of the revisit agree (on_geometry_failure: consistent)."""
    _, _, _, img_m = camera
    reg = deep.register_images(texture(7), img_m, yaw_guess=0.25)
    assert reg.method == "yaw_prior" and "fundamental matrix" in reg.reason, reg.reason
    assert reg.views_refused  # judged and refused: only verified loops may vouch for it
    assert yaw_of(reg.T_mq[:3, :3]) == pytest.approx(0.25)
