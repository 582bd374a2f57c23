"""The simulated world behaves like the real one: route files in their own conventions, a city
laid along any route, and a LiDAR whose returns differ between visits."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from frontend.simulation import SimulationConfig, TraverseSimulator, default_demo_config, read_route_file
from frontend.simulation.city import CAR, FOLIAGE
from frontend.simulation.route_files import CAMERA_TO_BODY
from ssmvpr_common.errors import SsmvprError


@pytest.fixture(scope="module")
def kitti06(shared_dir: Path) -> Path:
    """KITTI odometry 06's ground-truth poses (shared data: skipped, or failed under
    SSMVPR_REQUIRE_SHARED=1, where it is missing)."""
    return shared_dir / "data" / "routes" / "kitti06" / "06.txt"


def _loop(n: int = 400) -> np.ndarray:
    """A closed rounded-rectangle drive with a hill, in a z-up body world (x forward)."""
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    x = 120 * np.sign(np.cos(t)) * np.abs(np.cos(t)) ** 0.3
    y = 60 * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.3
    z = 3.0 * np.sin(t)
    return np.column_stack([x, y, z])


def _body_rotations(pos: np.ndarray) -> np.ndarray:
    d = np.gradient(pos, axis=0)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(pos), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _write_tum(path: Path, pos: np.ndarray, R: np.ndarray) -> None:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()  # x y z w
    path.write_text(
        "".join(
            f"{i * 0.1:.3f} " + " ".join(f"{v:.6f}" for v in (*p, *qq)) + "\n" for i, (p, qq) in enumerate(zip(pos, q))
        )
    )


def _write_kitti(path: Path, pos: np.ndarray, R: np.ndarray) -> None:
    rows = [np.hstack([r, p[:, None]]).ravel() for r, p in zip(R, pos)]
    path.write_text("".join(" ".join(f"{v:.6e}" for v in row) + "\n" for row in rows))


def test_kitti_camera_file_and_tum_body_file_give_the_same_route(tmp_path):
    body = _loop()
    R_body = _body_rotations(body)
    # The same drive seen as KITTI camera-0 poses: p_cam = C^T p_body, R_cam = C^T R_body C.
    C = CAMERA_TO_BODY
    cam_pos = body @ C  # (C^T p)^T = p^T C
    cam_R = np.einsum("ij,njk,kl->nil", C.T, R_body, C)
    _write_tum(tmp_path / "body.tum", body, R_body)
    _write_kitti(tmp_path / "cam.txt", cam_pos, cam_R)
    a = read_route_file(tmp_path / "body.tum")
    b = read_route_file(tmp_path / "cam.txt")
    assert (a.frame, a.file_format) == ("body", "tum")
    assert (b.frame, b.file_format) == ("camera", "kitti")
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-4)
    sims = [
        TraverseSimulator(
            SimulationConfig(
                route={"preset": str(tmp_path / name)}, camera={"enabled": False}, lidar={"enabled": False}
            )
        )
        for name in ("body.tum", "cam.txt")
    ]
    np.testing.assert_allclose(sims[0].route.xy, sims[1].route.xy, atol=1e-3)
    np.testing.assert_allclose(sims[0].route.z, sims[1].route.z, atol=1e-3)
    # The road keeps the file's height profile (3 m hill) and the vehicle pitches with it.
    assert np.ptp(sims[0].road_z) == pytest.approx(6.0, abs=0.2)
    assert np.abs(sims[0].pitch).max() > math.radians(0.5)
    # The forced convention overrides detection (and a wrong one gives a different route).
    forced = read_route_file(tmp_path / "cam.txt", frame="body")
    assert forced.frame == "body" and not np.allclose(forced.positions, a.positions, atol=1.0)


def test_kitti06_route_is_read_as_camera_poses_with_its_length_and_no_frame_in_a_building(kitti06: Path) -> None:
    sim = TraverseSimulator(
        SimulationConfig(route={"preset": str(kitti06)}, camera={"enabled": False}, lidar={"enabled": False})
    )
    assert sim.route_file is not None and sim.route_file.frame == "camera"
    assert sim.route.length_3d == pytest.approx(sim.route_file.length, rel=0.02)
    # KITTI 06 is about 450 m long and 20 m wide: the ground plane really is x-y now.
    extent = np.ptp(sim.route.xy, axis=0)
    assert extent.max() > 400 and extent.min() > 15
    assert 5.0 < np.ptp(sim.road_z) < 15.0
    clearance = sim.building_clearance()
    assert clearance.min() > 3.0, f"frame {int(clearance.argmin())} is {clearance.min():.2f} m from a building"
    # Both sides of the street are built up somewhere along it, and districts differ.
    kinds = set(sim.city.kind.tolist())
    assert {CAR, FOLIAGE} <= kinds
    assert len(set(sim.city.ground.district.ravel().tolist())) >= 3


@pytest.mark.parametrize("preset", ["block_grid", "figure_eight"])
def test_no_frame_inside_a_building_on_preset_routes(preset):
    sim = TraverseSimulator(
        SimulationConfig(route={"preset": preset}, camera={"enabled": False}, lidar={"enabled": False})
    )
    assert sim.building_clearance().min() > 3.0
    assert len(sim.city.footprints) > 10


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("", "no data lines"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n" * 30, "does not move"),
        ("1 0 0 0 0 1 0 0 0 0 1 nan\n" * 3, "NaN or inf"),
        ("".join(f"1 0 0 0 0 1 0 0 0 0 1 {0.1 * i}\n" for i in range(50)), "needs at least"),
        # Travel along the local y axis: neither a camera (z) nor a body (x) convention.
        ("".join(f"1 0 0 0 0 1 0 {2.0 * i} 0 0 1 0\n" for i in range(50)), "fits neither"),
        ("1 2 3\n4 5 6\n", "expected 8 (TUM) or 12 (KITTI)"),
    ],
)
def test_bad_route_files_give_one_line_errors_naming_the_file(tmp_path, content, needle):
    path = tmp_path / "route.txt"
    path.write_text(content)
    with pytest.raises(SsmvprError) as err:  # the file's lines (TrajectoryFileError) or the route they draw
        TraverseSimulator(SimulationConfig(route={"preset": str(path)}))
    message = str(err.value)
    assert str(path) in message and needle in message and "\n" not in message


def test_parked_cars_and_traffic_differ_between_visits():
    sim = TraverseSimulator(default_demo_config(camera={"enabled": False}))
    city = sim.city
    turnover = sim.config.traffic.parked_car_turnover_s
    a, b = city.slots_occupied(0.0), city.slots_occupied(2 * turnover)
    assert len(a) > 20
    assert 0.1 < a.mean() < 0.6 and (a != b).mean() > 0.2
    assert len(sim.traffic) > 0
    parts = [len(sim.traffic.scene_part(t, np.array([1e6, 1e6])).p0) for t in (0.0, 30.0)]
    assert parts[0] > 0 and parts[1] > 0


def test_foliage_is_porous_to_the_lidar(kitti06: Path) -> None:
    sim = TraverseSimulator(SimulationConfig(route={"preset": str(kitti06)}, camera={"enabled": False}, max_frames=400))
    # Frames near a tree: the crown returns scatter from one draw of the noise to the next.
    tree_xy = (sim.city.p0[sim.city.kind[sim.city.surface] == FOLIAGE]).reshape(-1, 2)
    d = np.linalg.norm(sim.xy_yaw[:, None, :2] - tree_xy[None], axis=2).min(axis=1)
    k = int(np.argmin(d))
    assert d[k] < 25.0
    scene = sim.scene(k)
    x, y, yaw = sim.xy_yaw[k]
    scans = [
        sim.lidar.scan(x, y, yaw, np.random.default_rng(seed), road_z=float(sim.road_z[k]), scene=scene)[0]
        for seed in (1, 2)
    ]
    assert abs(len(scans[0]) - len(scans[1])) > 0 or not np.allclose(scans[0], scans[1])


def test_a_distorted_sweep_on_a_slope_is_one_static_world():
    """Each column of a sweep is measured from where the vehicle was at that instant, height
    included: put back through those poses, a perfect unit's ground returns lie on the ground.
    (Rendering every column from the sweep's end height made climbing roads look steeper to the
    scan matcher, an error that was the same on every visit.)"""
    from frontend.simulation.simulator import pose_matrix

    cfg = SimulationConfig.model_validate({
        "route": {"terrain_amplitude_m": 8.0, "terrain_wavelength_m": 120.0},
        "camera": {"enabled": False},
        "lidar": {"range_noise_sigma_m": 0.0, "range_bias_sigma_m": 0.0, "beam_elevation_error_deg": 0.0,
                  "foliage_return_probability": 0.0, "glass_pass_probability": 0.0,
                  "glass_dropout_probability": 0.0, "motion_distortion": True},
        "max_frames": 200,
    })  # fmt: skip
    sim = TraverseSimulator(cfg)
    k = int(np.argmax(np.abs(sim.grade) * (np.arange(len(sim)) > 5)))
    climb = abs(sim.road_z[k] - sim.road_z[k - 1])
    assert climb > 0.1, "the test needs a frame on a slope"
    points, times = sim.render_scan(k)
    t = sim.route_times[k] - sim.lidar.period + times
    arc = sim.route.arc_length_at(t)
    x, y, yaw = sim.route.pose_at(arc)
    z = sim.route.height_at(arc) + cfg.lidar.height_m
    world = np.empty_like(points)
    for c in np.unique(times):  # one pose per column
        sel = times == c
        pose = pose_matrix(x[sel][0], y[sel][0], z[sel][0], yaw[sel][0], float(sim.pitch[k]))
        world[sel] = points[sel] @ pose[:3, :3].T + pose[:3, 3]
    ground = world[:, 2] < sim.city.ground_z(world[:, 0], world[:, 1]) + 0.05
    ground &= np.linalg.norm(points[:, :2], axis=1) < 25.0  # near returns: pitch approximations stay small
    assert ground.sum() > 1000
    err = world[ground, 2] - sim.city.ground_z(world[ground, 0], world[ground, 1])
    assert np.abs(np.median(err)) < 0.01 and np.percentile(np.abs(err), 90) < 0.03, (np.median(err), climb)
    first = times[ground] < np.percentile(times, 25)  # the early columns are where the climb showed
    assert np.abs(np.median(err[first])) < 0.01


def test_beam_azimuth_calibration_error_turns_each_beams_points():
    """A laser firing off its reported azimuth sees the world along its true direction but
    reports it along the nominal one: its points come out turned by its own error."""
    quiet = {"range_noise_sigma_m": 0.0, "foliage_return_probability": 0.0, "beam_azimuth_error_deg": 0.0,
             "glass_pass_probability": 0.0, "glass_dropout_probability": 0.0}  # fmt: skip
    base = {"camera": {"enabled": False}, "max_frames": 3}
    perfect = TraverseSimulator(SimulationConfig.model_validate({**base, "lidar": quiet}))
    faulty = TraverseSimulator(
        SimulationConfig.model_validate({**base, "lidar": {**quiet, "beam_azimuth_error_deg": 1.0}})
    )
    p0, t0 = perfect.render_scan(2)
    p1, t1 = faulty.render_scan(2)
    assert p0.shape == p1.shape and np.array_equal(t0, t1)
    errors = faulty.lidar.azimuth_error
    assert 0.5 < np.degrees(errors.std()) < 1.5 and len(np.unique(errors)) == len(errors)
    # the beam of each point: by elevation, as the unit orders them
    beam = np.argmin(
        np.abs(np.arctan2(p0[:, 2], np.hypot(p0[:, 0], p0[:, 1]))[:, None] - perfect.lidar.elev[None]), axis=1
    )
    turned = np.arctan2(p1[:, 1], p1[:, 0]) - np.arctan2(p0[:, 1], p0[:, 0])
    turned = np.angle(np.exp(1j * turned))
    assert np.allclose(turned, -errors[beam], atol=1e-6)
    assert np.allclose(np.linalg.norm(p1, axis=1), np.linalg.norm(p0, axis=1))
