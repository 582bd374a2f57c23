"""`map` of camera-only sessions (no LiDAR loops, the logs' wheel odometry) end to end on a local
Ray, with the real VGG16 weights: two sessions of the simulated city that set off along the same
street are joined through cross-session loops the deep two-view verifier accepted, under the
same agreement rule as ICP loops; the merged map keeps its places' images, so `run --map`
can register loops to it by two views as well."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from map_sessions import linked_session_logs, map_config
from rich.console import Console

from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.multi_session.runner import map_logs
from ssmvpr_slam.prior_map import PriorMap

pytestmark = pytest.mark.slow

FRAMES = 45  # sessions 0 and 4 both set off east along the city's first street


def camera_only(config: SlamConfig) -> SlamConfig:
    """The map tests' settings without LiDAR loops, over the logs' (drifting) wheel odometry."""
    config = config.model_copy(deep=True)
    config.pipeline.use_lidar_for_loops = False
    config.frontend.odometry.kind = "logged"
    config.map.workers = 1
    # the renderer's field of view where a log carries no calibration (a log that does wins)
    config.backend.registration.two_view.hfov_deg = config.simulation.camera.hfov_deg
    return config


@pytest.fixture(scope="module")
def camera_map(weights_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    out = tmp_path_factory.mktemp("camera_map")
    logs = linked_session_logs(weights_path, out, FRAMES, (0, 4))
    config = camera_only(map_config(weights_path, out, None))
    folder, metrics = map_logs(logs, config, Console(quiet=True))
    return {"folder": folder, "metrics": metrics, "config": config, "logs": logs}


def test_camera_only_sessions_join_through_loops_two_views_verified(camera_map):
    metrics = camera_map["metrics"]
    assert metrics["maps"] == [["s0_session0", "s1_session4"]], metrics["unjoined_pairs"]
    assert metrics["links"][0]["loops"] >= 3  # map.min_agreeing_loops
    loops = metrics["cross_session_loops"]
    assert loops["in_graph"] >= 6, loops
    assert metrics["cross_session_precision"] == 1.0
    assert metrics["ate_merged_m"] < 2.0, metrics["ate_merged_m"]
    rows = list(csv.DictReader((camera_map["folder"] / "cross_session_loops.csv").open()))
    linked = [r for r in rows if r["linked"] == "1"]
    assert linked and all(r["registration"] == "two_view_deep" for r in linked)
    # a loop the views did not verify is listed, never taken
    assert all(r["registration_accepted"] == "0" for r in rows if r["registration"] != "two_view_deep")
    assert all(r["in_graph"] == "0" for r in rows if r["registration_accepted"] == "0")


def test_the_camera_only_map_keeps_its_places_images_for_run_map(camera_map):
    """`run --map` registers its loops to these places by two views (`LoopPolicy._register_to_map`;
    tests/multi_session/test_camera_loops.py)."""
    config: SlamConfig = camera_map["config"]
    prior = PriorMap.load(camera_map["folder"], config.vpr)
    assert prior.scans == {} and len(prior.poses) == len(prior.database)
    assert sorted(prior.images.front) == list(range(len(prior.database)))  # every place: no scan, an image
    assert sorted(prior.images.rear) == sorted(prior.images.front)
    assert np.isfinite(prior.images.cameras[0][0])  # the fx the sessions took from their logs (or the config)
    first = sum(p.extra["session"] == "s0_session0" for p in prior.database.places)
    second = camera_map["metrics"]["session_results"][1]
    session = PriorMap.load(camera_map["folder"] / second["folder"] / "database", config.vpr)
    assert prior.images.front[first].png == session.images.front[0].png  # each session's from its first place on
