"""What a killed or stopped call leaves, and what the next call does with it: a staging folder
whose writer lives is never touched; one whose writer is gone is adopted by `map` when its
settings match (its finished sessions reused) and removed otherwise, and said so; `run`'s
left-over staging is removed. `map` refuses a log given twice, and a cluster address where
no Ray answers is one line within the configured time."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401
from rich.console import Console

from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.multi_session.runner import MapError, check_distinct
from ssmvpr_slam.multi_session.staging import FINISHED, PLAN, MapResumeError, MapStaging, map_plan
from ssmvpr_slam.results.run_folder import staged_results_dir
from ssmvpr_slam.results.staging_lock import LOCK_NAME, StagingLock, in_use, left_over

_HOLD = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
print("held", flush=True)
time.sleep(60)
"""


def _left(base: Path, name: str, stamp: str = "2026-01-01_00-00-00", age_s: float = 3600) -> Path:
    folder = base / f".{name}_{stamp}.abc123.partial"
    folder.mkdir(parents=True)
    (folder / LOCK_NAME).touch()
    old = time.time() - age_s
    os.utime(folder, (old, old))
    return folder


def test_a_folder_whose_writer_lives_is_in_use_and_one_whose_writer_died_is_not(tmp_path):
    folder = _left(tmp_path, "map")
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder / LOCK_NAME)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert in_use(folder) and left_over(tmp_path, "map") == []
    finally:
        holder.kill()
        holder.wait()
    assert not in_use(folder)  # the kernel dropped the dead writer's lock
    assert left_over(tmp_path, "map") == [folder]
    young = tmp_path / ".map_2026-01-02_00-00-00.x.partial"
    young.mkdir()  # made an instant ago, its lock not taken yet: left alone
    assert in_use(young)


def test_a_lock_is_exclusive_and_released_before_publishing(tmp_path):
    lock = StagingLock(tmp_path)
    with pytest.raises(OSError):
        StagingLock(tmp_path)
    assert in_use(tmp_path)
    lock.release()
    assert not (tmp_path / LOCK_NAME).exists()
    StagingLock(tmp_path).release()  # free to take again


def test_run_removes_the_staging_a_killed_run_left_and_says_so(tmp_path, caplog):
    dead = _left(tmp_path, "run")
    (dead / "metrics.json").write_text("{")
    other = _left(tmp_path, "run_other")  # another command's name: not this call's to judge
    with staged_results_dir(tmp_path, "run") as staged:
        (staged.path / "metrics.json").write_text("{}")
    assert not dead.exists() and other.exists()
    assert staged.final is not None and (staged.final / "metrics.json").read_text() == "{}"
    assert not (staged.final / LOCK_NAME).exists()
    assert any("left unfinished by an earlier call that was killed" in r.message for r in caplog.records)


def _config(tmp_path: Path, **map_settings: object):
    return load_config("quick", {"results": {"out_dir": str(tmp_path / "out")}, "map": map_settings})


def test_map_adopts_a_left_over_map_of_its_settings_and_removes_the_others(tmp_path):
    config = _config(tmp_path)
    out = tmp_path / "out"
    plan = map_plan(config, None)
    mine = _left(out, "map", "2026-01-01_00-00-01")
    (mine / PLAN).write_text(json.dumps(plan))
    (mine / "metrics.json").write_text("{")  # what an interrupted final write had begun
    other = _left(out, "map", "2026-01-01_00-00-02")
    (other / PLAN).write_text(json.dumps(map_plan(_config(tmp_path, min_agreeing_loops=4), None)))
    console = Console(record=True, width=200)
    staging = MapStaging.open(out, plan, None, console)
    assert staging.path == mine and staging.adopted
    assert not (mine / "metrics.json").exists() and (mine / FINISHED).exists()
    assert not other.exists() and "a map left unfinished with other settings" in console.export_text()
    assert in_use(mine)  # held by this call now
    staging.keep()
    assert not in_use(mine)


def test_settings_that_only_change_speed_keep_the_plan(tmp_path):
    assert map_plan(_config(tmp_path, workers=3, task_retries=0), None) == map_plan(_config(tmp_path), None)
    assert map_plan(_config(tmp_path), tmp_path) != map_plan(_config(tmp_path), None)


def test_one_weights_file_named_two_ways_keeps_the_plan(tmp_path, monkeypatch):
    weights = tmp_path / "w.pth"
    named = [_config(tmp_path), _config(tmp_path)]
    named[0].vpr.backbone.weights = str(weights)
    monkeypatch.chdir(tmp_path)
    named[1].vpr.backbone.weights = "./w.pth"  # the same file, named another way
    assert map_plan(named[0], None) == map_plan(named[1], None)


def test_resume_refuses_a_folder_of_other_settings_or_not_a_map(tmp_path):
    config = _config(tmp_path)
    out = tmp_path / "out"
    folder = _left(out, "map")
    (folder / PLAN).write_text(json.dumps(map_plan(_config(tmp_path, min_agreeing_loops=4), None)))
    with pytest.raises(MapResumeError, match="the settings differ"):
        MapStaging.open(out, map_plan(config, None), folder, Console(quiet=True))
    with pytest.raises(MapResumeError, match="not a map left unfinished"):
        MapStaging.open(out, map_plan(config, None), tmp_path, Console(quiet=True))


def test_a_finished_session_is_reused_only_for_the_same_unchanged_log(tmp_path):
    config = _config(tmp_path)
    log = tmp_path / "a.mcap"
    log.write_bytes(b"one log")
    staging = MapStaging.open(tmp_path / "out", map_plan(config, None), None, Console(quiet=True))
    (staging.sessions_dir / "s0_a_x").mkdir()
    staging.record_finished({"name": "s0_a", "folder": "sessions/s0_a_x", "error": None}, str(log))
    assert list(staging.reusable([(0, "s0_a", str(log))])) == ["s0_a"]
    assert staging.reusable([(0, "s0_a", str(tmp_path / "b.mcap"))]) == {}
    log.write_bytes(b"another log")  # changed since: run again
    assert staging.reusable([(0, "s0_a", str(log))]) == {}
    staging.staged.discard()


def test_a_log_given_twice_or_already_in_the_map_is_refused(tmp_path):
    log = tmp_path / "a.mcap"
    with pytest.raises(MapError, match="is given twice"):
        check_distinct([log, tmp_path / "." / "a.mcap"], [])
    with pytest.raises(MapError, match="already a session of the map"):
        check_distinct([log], [{"log": str(log)}])
    check_distinct([log, tmp_path / "b.mcap"], [])


def _a_log(folder: Path) -> Path:
    """A log file for the tests refused before any log is read."""
    log = folder / "a.mcap"
    log.write_bytes(b"x")
    return log


def test_map_refuses_the_same_log_twice_on_the_command_line(tmp_path):
    log = _a_log(tmp_path)
    assert_user_error(invoke("map", log, log, "--out", tmp_path / "out"), "is given twice")


def test_ray_address_auto_with_no_cluster_is_one_line(tmp_path, weights_path):
    log = _a_log(tmp_path)
    assert_user_error(invoke("map", log, "--ray-address", "auto", "--weights", weights_path, "--out", tmp_path / "out"),
                      "--ray-address auto: no Ray cluster is running", "ray start --head")  # fmt: skip


def _silent_server() -> tuple[socket.socket, int]:
    """A port that accepts connections and never answers (not a Ray cluster)."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    accepted = []
    threading.Thread(target=lambda: [accepted.append(server.accept()) for _ in range(8)], daemon=True).start()
    return server, server.getsockname()[1]


def test_a_cluster_address_where_no_ray_answers_is_one_line_within_the_timeout(tmp_path, weights_path):
    log = _a_log(tmp_path)
    config = tmp_path / "map.yaml"
    config.write_text("preset: quick\nmap:\n  ray_connect_timeout_s: 6\n")

    def map_at(port: int):  # noqa: ANN202
        return invoke("map", log, "--ray-address", f"127.0.0.1:{port}", "-c", config, "--weights", weights_path,
                      "--out", tmp_path / "out")  # fmt: skip

    server, port = _silent_server()
    try:
        start = time.monotonic()
        result = map_at(port)
        took = time.monotonic() - start
    finally:
        server.close()
    assert_user_error(result, f"--ray-address 127.0.0.1:{port}", "no Ray cluster answered within 6 s")
    assert took < 20, took
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()  # nobody listens there now
    result = map_at(port)
    assert_user_error(result, f"--ray-address 127.0.0.1:{port}")
    assert not list((tmp_path / "out").glob(".map_*"))  # nothing left behind
