"""The city traverse simulator: determinism, routes with revisits, images, LiDAR, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.simulation import (
    SimulationConfig,
    TraverseSimulator,
    build_city,
    default_demo_config,
    ground_truth_revisits,
    pose_matrix,
    simulate_traverse,
)
from frontend.simulation.config import CityConfig
from frontend.simulation.render import cast_rays
from frontend.simulation.route import grid_node
from ssmvpr_common.trajectory_io import TrajectoryFileError


@pytest.fixture(scope="module")
def sim() -> TraverseSimulator:
    return TraverseSimulator(default_demo_config())


def _grey_small(img: np.ndarray, size=(40, 30)) -> np.ndarray:
    import cv2

    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float64)
    g = cv2.resize(g, size, interpolation=cv2.INTER_AREA)
    g -= g.mean()
    return g / (np.linalg.norm(g) + 1e-9)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    return float((_grey_small(a) * _grey_small(b)).sum())


# -- determinism -------------------------------------------------------------------------------


def test_same_seed_gives_identical_frames():
    cfg = default_demo_config(max_frames=60)
    a = TraverseSimulator(cfg)
    b = TraverseSimulator(cfg)
    for k in (0, 37, 59):
        fa, fb = a.frame(k), b.frame(k)
        np.testing.assert_array_equal(fa.image, fb.image)
        np.testing.assert_array_equal(fa.points, fb.points)
        np.testing.assert_array_equal(fa.point_times, fb.point_times)
        np.testing.assert_array_equal(fa.gt_pose, fb.gt_pose)
        np.testing.assert_array_equal(fa.logged_pose, fb.logged_pose)
    # Streaming gives the same frames as random access.
    streamed = [f for _, f in zip(range(3), simulate_traverse(cfg))]
    np.testing.assert_array_equal(streamed[2].image, a.frame(2).image)
    np.testing.assert_array_equal(streamed[2].points, a.frame(2).points)


def test_different_seed_changes_textures_and_layout():
    a = TraverseSimulator(default_demo_config(seed=1, max_frames=5))
    b = TraverseSimulator(default_demo_config(seed=2, max_frames=5))
    assert not np.array_equal(a.city.params["base"][:50], b.city.params["base"][:50])
    assert not np.array_equal(a.frame(3).image, b.frame(3).image)
    sid = np.arange(20)
    u = np.linspace(0, 10, 20).astype(np.float32)
    v = np.full(20, 6.0, np.float32)
    ra, _ = a.city.wall_albedo(sid, u, v)
    rb, _ = b.city.wall_albedo(sid, u, v)
    assert not np.allclose(ra, rb)


def test_texture_lookup_is_vectorised_and_pure():
    centre = np.column_stack([np.linspace(0, 300, 601), np.zeros(601), np.zeros(601)])
    city = build_city(CityConfig(district_mix={"dense": 1.0}), seed=3, centre=centre)
    rng = np.random.default_rng(0)
    sid = rng.integers(0, len(city.kind), 5000)
    u = rng.uniform(0, 15, 5000).astype(np.float32)
    v = rng.uniform(0, 20, 5000).astype(np.float32)
    rgb, key = city.wall_albedo(sid, u, v)
    assert rgb.shape == (5000, 3) and rgb.dtype == np.float32 and key.shape == (5000,)
    assert rgb.min() >= 0.0 and rgb.max() <= 1.0
    rgb2, _ = city.wall_albedo(sid[::-1], u[::-1], v[::-1])
    np.testing.assert_array_equal(rgb2, rgb[::-1])
    # Facades are not flat colour: windows, frames and grain vary along a wall.
    one = np.zeros(400, np.int64) + int(np.nonzero(city.kind == 0)[0][0])
    col, _ = city.wall_albedo(one, np.linspace(0, 12, 400).astype(np.float32), np.full(400, 7.0, np.float32))
    assert col.std(axis=0).mean() > 0.03


# -- route ---------------------------------------------------------------------------------------


def test_demo_route_has_revisits_both_ways(sim):
    st = sim.stats()
    assert 550 <= st["frames"] <= 800
    assert st["passes"] == 3
    xy = sim.gt_positions()
    yaw = sim.xy_yaw[:, 2]
    gap = sim.default_min_gap()
    rev = ground_truth_revisits(xy, 4.0, gap)
    later = np.nonzero(rev >= 0)[0]
    assert len(later) > 100
    assert np.all(later - rev[later] >= gap)
    assert np.all(np.linalg.norm(xy[later] - xy[rev[later]], axis=1) <= 4.0)
    same = ground_truth_revisits(xy, 4.0, gap, yaw, math.pi / 4)
    assert (same >= 0).sum() > 80
    # Reverse-direction revisits: near an earlier frame (other lane) facing the other way.
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    dyaw = np.abs(np.angle(np.exp(1j * (yaw[:, None] - yaw[None]))))
    idx = np.arange(len(xy))
    reverse = (d < 6.0) & (dyaw > 3 * math.pi / 4) & (idx[None, :] < idx[:, None] - gap)
    assert reverse.any(axis=1).sum() > 20


def test_trajectory_is_smooth_and_follows_the_road(sim):
    xy = sim.gt_positions()
    steps = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    dt = 1.0 / sim.config.frame_rate_hz
    assert steps.max() / dt <= sim.config.route.speed_mps * (1 + sim.config.route.speed_variation) + 1e-6
    dyaw = np.abs(np.diff(sim.xy_yaw[:, 2]))
    assert dyaw.max() < math.radians(15)
    f = sim.frame(100)
    assert f.gt_pose[2, 3] == pytest.approx(sim.road_z[100] + sim.config.lidar.height_m)
    R = f.gt_pose[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    # The vehicle pitches with the rolling terrain (nose up uphill), but never rolls.
    assert R[2, 2] == pytest.approx(math.cos(sim.pitch[100]))
    assert R[2, 1] == pytest.approx(0.0, abs=1e-12)
    assert np.sign(R[2, 0]) == np.sign(sim.grade[100]) or abs(sim.grade[100]) < 1e-6
    assert np.ptp(sim.road_z) > 0.3 and np.abs(sim.pitch).max() < math.radians(6)


def test_route_keeps_clear_of_walls_cars_and_poles(sim):
    xy = sim.route.xy[::20]
    city = sim.city
    e = city.p1 - city.p0
    w = xy[:, None] - city.p0[None]
    f = np.clip((w * e[None]).sum(-1) / (e * e).sum(-1), 0, 1)
    d = np.linalg.norm(w - f[..., None] * e[None], axis=-1)
    assert d.min() > 1.0  # parked cars at the kerb are the nearest


def test_figure_eight_crosses_itself():
    cfg = SimulationConfig(route={"preset": "figure_eight", "laps": 2}, camera={"enabled": False})
    s = TraverseSimulator(cfg)
    xy = s.gt_positions()
    centre = grid_node(s.config.city.pitch_m, 1, 1)
    near = np.nonzero(np.linalg.norm(xy - centre, axis=1) < 3.0)[0]
    # Passed through the centre crossing heading in two different directions, on both laps.
    headings = {int(np.round((s.xy_yaw[k, 2] % (2 * math.pi)) / (math.pi / 2))) % 4 for k in near}
    assert len(headings) >= 2
    assert (ground_truth_revisits(xy, 4.0, s.default_min_gap()) >= 0).sum() > 50


def test_logged_odometry_drifts_but_starts_at_truth(sim):
    np.testing.assert_allclose(sim.logged_pose(0), sim.gt_pose(0))
    err = [np.linalg.norm(sim.logged_pose(k)[:2, 3] - sim.gt_pose(k)[:2, 3]) for k in range(0, len(sim), 25)]
    assert err[1] < 1.0
    assert max(err) > 3.0
    # Short-term motion is still close to the truth.
    a, b = sim.logged_pose(200), sim.logged_pose(201)
    g0, g1 = sim.gt_pose(200), sim.gt_pose(201)
    rel_l = np.linalg.inv(a) @ b
    rel_g = np.linalg.inv(g0) @ g1
    assert np.linalg.norm(rel_l[:3, 3] - rel_g[:3, 3]) < 0.2


def test_poses_file_routes(tmp_path):
    # A straight drive along the street y = 0, in TUM and KITTI formats.
    xs = np.linspace(2.0, 80.0, 40)
    tum = tmp_path / "route_tum.txt"
    rows = "".join(f"{i * 0.5} {x} -1.5 0 0 0 0 1\n" for i, x in enumerate(xs))
    tum.write_text("# t x y z qx qy qz qw\n" + rows)
    kitti = tmp_path / "route_kitti.txt"
    kitti.write_text("".join(f"1 0 0 {x} 0 1 0 -1.5 0 0 1 0\n" for x in xs))
    for path in (tum, kitti):
        s = TraverseSimulator(SimulationConfig(route={"preset": str(path)}, camera={"enabled": False}))
        xy = s.gt_positions()
        assert len(s) > 10
        np.testing.assert_allclose(xy[:, 1], -1.5, atol=1e-6)
        assert np.all(np.diff(xy[:, 0]) >= 0) and xy[-1, 0] > 60
        np.testing.assert_allclose(s.xy_yaw[5:, 2], 0.0, atol=1e-6)


# -- camera --------------------------------------------------------------------------------------


def test_image_looks_like_a_street(sim):
    f = sim.frame(20)
    img = f.image
    assert isinstance(f, Frame)
    assert img.shape == (240, 320, 3) and img.dtype == np.uint8
    top = img[:20].reshape(-1, 3).astype(float)
    bottom = img[-40:].reshape(-1, 3).astype(float)
    # Sky: bright and blue at the top of the centre columns; road below is darker and grey.
    sky = img[:15, 140:180].reshape(-1, 3).astype(float)
    assert sky[:, 2].mean() > sky[:, 0].mean() + 30
    assert top.mean() > bottom.mean()
    assert (top[:, 2] - top[:, 0]).mean() > (bottom[:, 2] - bottom[:, 0]).mean()
    # Facades at the image sides between the horizon and the top are textured, not flat.
    side = img[40:120, :60].reshape(-1, 3).astype(float)
    assert side.std(axis=0).mean() > 15
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 500


def test_revisited_places_look_more_alike_than_other_places(sim):
    xy = sim.gt_positions()
    yaw = sim.xy_yaw[:, 2]
    rev = ground_truth_revisits(xy, 3.0, sim.default_min_gap(), yaw, math.pi / 8)
    later = np.nonzero(rev >= 0)[0]
    # Same appearance (the first two passes are both "day"); sample across the lap.
    later = later[sim.passes[later] == 1][::12][:10]
    assert len(later) >= 6
    rng = np.random.default_rng(0)
    same, other = [], []
    for k in later:
        img = sim.render_image(int(k))
        same.append(_ncc(img, sim.render_image(int(rev[k]))))
        far = np.nonzero(np.linalg.norm(xy - xy[k], axis=1) > 40.0)[0]
        other.append(_ncc(img, sim.render_image(int(rng.choice(far)))))
    assert np.mean(same) > np.mean(other) + 0.2
    assert np.mean(np.array(same) > np.array(other)) >= 0.8


def test_rear_camera_sees_what_the_forward_camera_saw_on_a_street_driven_the_other_way(sim):
    xy = sim.gt_positions()
    yaw = sim.xy_yaw[:, 2]
    # reverse revisits: an earlier frame nearby, driven the other way (the other lane: ~3 m off)
    rev = ground_truth_revisits(xy, 6.0, sim.default_min_gap())
    turned = np.abs(np.angle(np.exp(1j * (yaw - yaw[rev])))) > 7 * math.pi / 8
    later = np.nonzero((rev >= 0) & turned)[0][::10][:8]
    assert len(later) >= 6
    rear_vs_then, front_vs_then = [], []
    for k in later:
        then = sim.render_image(int(rev[k]))
        rear_vs_then.append(_ncc(sim.render_image(int(k), rear=True), then))
        front_vs_then.append(_ncc(sim.render_image(int(k)), then))
    # grey thumbnails of any street share sky and road; the facades make the difference
    assert np.mean(rear_vs_then) > np.mean(front_vs_then) + 0.1, (rear_vs_then, front_vs_then)
    assert np.mean(np.array(rear_vs_then) > np.array(front_vs_then)) >= 0.75, (rear_vs_then, front_vs_then)


def test_rear_camera_can_be_switched_off_and_leaves_the_forward_images_alone():
    with_rear = TraverseSimulator(default_demo_config(max_frames=2, lidar={"enabled": False}))
    without = TraverseSimulator(default_demo_config(max_frames=2, lidar={"enabled": False}, camera={"rear": False}))
    a, b = with_rear.frame(1), without.frame(1)
    assert a.rear_image is not None and a.rear_image.shape == a.image.shape
    assert b.rear_image is None
    assert np.array_equal(a.image, b.image)
    assert not np.array_equal(a.rear_image, a.image)


def test_appearance_changes_image_statistics():
    base = dict(max_frames=3, lidar={"enabled": False})
    day = TraverseSimulator(default_demo_config(appearance_schedule=["day"], **base)).frame(2).image
    dusk = TraverseSimulator(default_demo_config(appearance_schedule=["dusk"], **base)).frame(2).image
    night = TraverseSimulator(default_demo_config(appearance_schedule=["night"], **base)).frame(2).image
    assert night.mean() < 0.5 * day.mean()
    # Dusk: warmer (more red than blue relative to day) and darker.
    d_rb = day[..., 0].mean() - day[..., 2].mean()
    k_rb = dusk[..., 0].mean() - dusk[..., 2].mean()
    assert k_rb > d_rb and dusk.mean() < day.mean()
    # Night: some windows are lit (bright warm pixels) although the scene is dark.
    warm = (night[..., 0] > 150) & (night[..., 0] > night[..., 2] + 40)
    assert warm.sum() > 50


def test_appearance_schedule_switches_per_pass(sim):
    names = {sim.appearance_name(k) for k in range(len(sim))}
    assert names == {"day", "dusk"}
    first_dusk = next(k for k in range(len(sim)) if sim.appearance_name(k) == "dusk")
    assert sim.passes[first_dusk] == 2


# -- LiDAR ---------------------------------------------------------------------------------------


def _point_to_walls(city, pts_xy: np.ndarray) -> np.ndarray:
    p0, p1 = city.p0, city.p1
    e = p1 - p0
    w = pts_xy[:, None, :] - p0[None]
    f = np.clip((w * e[None]).sum(-1) / (e * e).sum(-1)[None], 0, 1)
    return np.linalg.norm(w - f[..., None] * e[None], axis=-1)


def _ideal_lidar_sim(**overrides) -> TraverseSimulator:
    """The demo with a perfect LiDAR (no calibration error, opaque foliage) and no traffic."""
    lidar = {
        "beam_elevation_error_deg": 0.0,
        "beam_azimuth_error_deg": 0.0,
        "range_bias_sigma_m": 0.0,
        "foliage_return_probability": 1.0,
        "foliage_depth_m": 0.0,
        "glass_pass_probability": 0.0,
        "glass_dropout_probability": 0.0,
        **overrides.pop("lidar", {}),
    }
    city = {"verge_relief_m": 0.0, "kerb_height_m": 0.0, "road_camber": 0.0}
    return TraverseSimulator(
        default_demo_config(
            camera={"enabled": False}, lidar=lidar, city=city, traffic={"oncoming_vehicles_per_km": 0.0}, **overrides
        )
    )


def _world_points(sim: TraverseSimulator, k: int, pts: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Each point in the world with the pose at its own measurement time (pitch of the frame)."""
    t_abs = sim.route_times[k] - sim.config.scan_period_s + times
    arc = sim.route.arc_length_at(t_abs)
    x, y, yaw = sim.route.pose_at(arc)
    z = sim.route.height_at(arc) + sim.config.lidar.height_m  # the vehicle climbs during a sweep
    out = np.empty_like(pts)
    for i, (xi, yi, zi, yi_aw) in enumerate(zip(x, y, z, yaw)):
        out[i] = pose_matrix(xi, yi, zi, yi_aw, float(sim.pitch[k]))[:3] @ np.append(pts[i], 1.0)
    return out


def test_lidar_points_lie_on_walls_and_ground():
    sim = _ideal_lidar_sim(max_frames=160)
    cfg = sim.config.lidar
    k = 150
    f = sim.frame(k)
    pts, times = f.points, f.point_times
    assert pts.dtype == np.float64 and pts.ndim == 2 and pts.shape[1] == 3
    assert len(pts) > 0.5 * cfg.beams * cfg.azimuths
    assert np.all(np.isfinite(pts)) and times.shape == (len(pts),)
    r = np.linalg.norm(pts, axis=1)
    tol = 6 * cfg.range_noise_sigma_m
    assert r.max() <= cfg.max_range_m + tol and r.min() >= cfg.min_range_m - tol
    period = sim.config.scan_period_s
    assert times.min() >= 0 and times.max() < period and np.all(np.diff(times) >= 0)
    assert times.max() - times.min() > 0.9 * period  # deskew-ready: spread over the sweep
    sub = np.arange(0, len(pts), 5)
    w = _world_points(sim, k, pts[sub], times[sub])
    # Ground points lie on the terrain (the height of the nearest road).
    plane = sim.city.ground_z(w[:, 0], w[:, 1])
    ground = np.abs(w[:, 2] - plane) < tol
    assert 0.2 < ground.mean() < 0.8
    scene = sim.scene(k)
    wall = ~ground
    d = _point_to_walls(scene, w[wall][::3, :2]).min(axis=1)
    assert np.percentile(d, 99) < tol
    assert np.all(w[wall, 2] > plane[wall] - 0.5)


def test_lidar_without_motion_distortion_matches_gt_pose():
    s = _ideal_lidar_sim(max_frames=80, lidar={"motion_distortion": False})
    f = s.frame(70)
    w = f.points @ f.gt_pose[:3, :3].T + f.gt_pose[:3, 3]
    on_ground = np.abs(w[:, 2] - s.city.ground_z(w[:, 0], w[:, 1])) < 0.3
    d = _point_to_walls(s.scene(70), w[~on_ground][::9, :2]).min(axis=1)
    assert np.percentile(d, 99) < 0.15


def test_lidar_beam_elevation_errors_bend_the_ground():
    """A real unit: per-beam elevation errors put a flat road's returns off the plane."""

    def ground_offset(elevation_error_deg: float) -> float:
        sim = TraverseSimulator(
            default_demo_config(
                camera={"enabled": False},
                max_frames=60,
                route={"terrain_amplitude_m": 0.0},
                city={"verge_relief_m": 0.0, "kerb_height_m": 0.0, "road_camber": 0.0},
                traffic={"oncoming_vehicles_per_km": 0.0},
                lidar={
                    "beam_elevation_error_deg": elevation_error_deg,
                    "range_bias_sigma_m": 0.0,
                    "motion_distortion": False,
                },
            )
        )
        f = sim.frame(50)
        w = f.points @ f.gt_pose[:3, :3].T + f.gt_pose[:3, 3]
        near = (np.linalg.norm(f.points[:, :2], axis=1) < 20) & (np.abs(w[:, 2]) < 0.3)
        return float(np.mean(np.abs(w[near, 2])))

    assert ground_offset(0.3) > 2.5 * ground_offset(0.0)


def test_lidar_sees_structure_across_the_street_direction(sim):
    """Walls facing along the street (setback steps, side walls, poles, cars) keep ICP well posed."""
    k = 60
    x, y, yaw = sim.xy_yaw[k]
    scene = sim.scene(k)
    ang = yaw + np.linspace(-math.pi, math.pi, 720, endpoint=False)
    t, seg, _ = cast_rays(scene, np.arange(len(scene)), x, y, np.cos(ang), np.sin(ang), 1)
    hit = np.isfinite(t[:, 0]) & (t[:, 0] < 40)
    n = scene.normal[seg[hit, 0]]
    along = np.abs(n @ np.array([math.cos(yaw), math.sin(yaw)]))
    assert (along > 0.7).sum() > 40


def test_kiss_icp_tracks_the_simulated_scans():
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.max_range = 80.0
    cfg.data.deskew = True
    cfg.mapping.voxel_size = 1.0
    odo = KissICP(cfg)
    s = TraverseSimulator(default_demo_config(max_frames=30, camera={"enabled": False}))
    est, gt = [], []
    for f in s.frames():
        odo.register_frame(f.points, f.point_times)
        est.append(odo.last_pose.copy())
        gt.append(f.gt_pose)
    est = np.einsum("ij,njk->nik", gt[0], np.array(est))
    gt = np.array(gt)
    travelled = np.linalg.norm(np.diff(gt[:, :2, 3], axis=0), axis=1).sum()
    assert travelled > 25
    err = np.linalg.norm(est[:, :2, 3] - gt[:, :2, 3], axis=1)
    assert err[-1] < 0.05 * travelled


# -- configuration errors ------------------------------------------------------------------------


def test_negative_speed_is_rejected_naming_the_field():
    with pytest.raises(ValidationError, match="speed_mps"):
        SimulationConfig(route={"speed_mps": -1.0})


def test_unknown_preset_is_rejected_naming_it():
    with pytest.raises(ValidationError, match="preset") as exc:
        SimulationConfig(route={"preset": "spiral_of_doom"})
    assert "spiral_of_doom" in str(exc.value)


def test_unreadable_poses_file_names_the_file(tmp_path):
    bad = tmp_path / "poses.txt"
    bad.write_text("0 1 2 3 0 0 0 1\n0 1 two 3 0 0 0 1\n")
    with pytest.raises(TrajectoryFileError, match=r"poses\.txt:2: not a number"):
        TraverseSimulator(SimulationConfig(route={"preset": str(bad)}))
    odd = tmp_path / "five.txt"
    odd.write_text("1 2 3 4 5\n")
    with pytest.raises(TrajectoryFileError, match="five.txt"):
        simulate_traverse(SimulationConfig(route={"preset": str(odd)}))


def test_other_bad_values_are_rejected():
    with pytest.raises(ValidationError, match="appearance_schedule"):
        SimulationConfig(appearance_schedule=["noon"])
    with pytest.raises(ValidationError, match="frame_rate_hz"):
        SimulationConfig(frame_rate_hz=0)
    with pytest.raises(ValidationError, match="vfov_deg"):
        SimulationConfig(lidar={"vfov_deg": (10.0, -10.0)})
    with pytest.raises(ValidationError, match="sidewalk"):
        SimulationConfig(city={"street_width_m": 6.0, "sidewalk_width_m": 3.0})
    with pytest.raises(ValidationError, match="nonsense"):
        SimulationConfig(nonsense=1)
    with pytest.raises(FrontendInputError, match="turn_radius_m"):
        TraverseSimulator(SimulationConfig(route={"turn_radius_m": 1.0}))


def test_yaml_config_round_trip(tmp_path):
    p = tmp_path / "sim.yaml"
    p.write_text("seed: 4\nroute:\n  preset: figure_eight\n  laps: 1\nappearance_schedule: [night]\n")
    cfg = SimulationConfig.from_yaml(p)
    assert cfg.seed == 4 and cfg.route.preset == "figure_eight" and cfg.appearance_schedule == ["night"]
    missing = tmp_path / "missing.yaml"
    with pytest.raises(FrontendInputError, match="missing.yaml"):
        SimulationConfig.from_yaml(missing)
