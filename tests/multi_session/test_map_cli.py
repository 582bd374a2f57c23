"""`map` and `simulate --sessions` from the command line, where no Ray is needed: what is
refused before any work starts, and the session logs the simulator writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401

from frontend.sources import open_source
from ssmvpr_slam.config.slam import load_config


def test_a_folder_that_is_not_a_map_is_refused_by_name(tmp_path: Path) -> None:
    result = invoke("map", "--map", tmp_path, "--add", tmp_path / "day.mcap", "--out", tmp_path / "out")
    assert_user_error(result, str(tmp_path), "not a map folder")
    assert not (tmp_path / "out").exists()  # nothing made for a refused call


def test_a_map_whose_session_results_are_gone_is_refused(tmp_path: Path) -> None:
    manifest = {"version": 1, "codebooks": "codebooks.npz", "maps": [["s0_a"]],
                "sessions": [{"name": "s0_a", "log": "a.mcap", "folder": "sessions/s0_a_x", "error": None}]}  # fmt: skip
    (tmp_path / "map.json").write_text(json.dumps(manifest))
    assert_user_error(invoke("map", "--map", tmp_path, "--add", tmp_path / "b.mcap"), "s0_a", "missing")
    (tmp_path / "map.json").write_text("{not json")
    assert_user_error(invoke("map", "--map", tmp_path, "--add", tmp_path / "b.mcap"), "not a map manifest")


def test_simulate_sessions_writes_one_log_per_session_in_one_world(tmp_path: Path) -> None:
    out = tmp_path / "city"
    result = invoke("simulate", "--sessions", 2, "--first-session", 1, "--frames", 3, "--out", out,
                    "-c", "quick")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == ["session1.mcap", "session2.mcap"]
    config = load_config("quick")
    starts = []
    for name in ("session1.mcap", "session2.mcap"):
        frames = list(open_source(out / name, config.frontend.source, config.frontend.pose_files))
        assert len(frames) == 3 and all(f.image is not None and f.rear_image is None for f in frames)
        starts.append(frames[0].gt_pose[:3, 3])
    # two loops of one grid, started at two crossings: 1 from (3, 1), 2 from (1, 0) (30 m blocks)
    assert np.linalg.norm(starts[0][:2] - starts[1][:2]) > 50.0
    assert_user_error(invoke("simulate", "--sessions", 0, "--out", tmp_path / "none"), "--sessions")


def test_workers_take_the_gpus_ray_sees_unless_told() -> None:
    from ssmvpr_slam.multi_session.workers import worker_gpus

    config = load_config(None, {"map": {"workers": 4}})
    assert worker_gpus(config, 0.0) == 0.0  # no GPU: the backbone on the CPU
    assert worker_gpus(config, 2.0) == 0.5  # two GPUs shared by four workers
    assert worker_gpus(config.model_copy(update={"map": config.map.model_copy(update={"workers": 1})}), 8.0) == 1.0
    told = load_config(None, {"map": {"workers": 4, "worker_gpus": 0.0}})
    assert worker_gpus(told, 2.0) == 0.0


def test_workers_share_the_cpus_ray_sees_unless_told() -> None:
    from ssmvpr_slam.multi_session.workers import worker_cpus

    one = load_config(None, {"map": {"workers": 1}})
    assert worker_cpus(one, 2.0) == 2.0  # one worker on two cores: its backbone runs on both
    assert worker_cpus(load_config(None, {"map": {"workers": 2}}), 2.0) == 1.0
    assert worker_cpus(load_config(None, {"map": {"workers": 4}}), 2.0) == 1.0  # at least one each
    assert worker_cpus(load_config(None, {"map": {"workers": 1, "worker_cpus": 0.5}}), 2.0) == 0.5
