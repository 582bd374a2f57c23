"""`map` end to end on a local Ray, with the real VGG16 weights, on sessions simulated in one
city (and one in another city): two sessions sharing a street merge through their
cross-session loops; a session of another city stays a separate map; a log that is not a log
fails by name while the others go on; `--map ... --add` joins a new session to a map; the
merged map opens as a prior map for `run --map`."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401
from map_sessions import map_config, session_log
from processes import descends_from, session_workers
from rich.console import Console
from scipy.spatial import cKDTree

from ssmvpr_slam.multi_session.runner import map_logs
from ssmvpr_slam.prior_map import PriorMap

pytestmark = pytest.mark.slow

# sessions 0 and 4 both set off east along the city's first street (0 by day round the lower
# blocks, 4 at dusk round the outer streets: `SESSION_LOOPS`), so their first frames revisit
# each other's; "elsewhere" is a session in another city (another seed)
FRAMES = {"s0": 45, "s1": 45, "elsewhere": 40}


class _WorkerKiller(threading.Thread):
    """Kills one Ray worker of this process's Ray with SIGKILL a few seconds into its session
    (once): a worker that dies mid-session, as one killed for memory would."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.stop = threading.Event()
        self.killed: list[int] = []

    def run(self) -> None:
        seen: dict[int, float] = {}
        while not self.stop.wait(0.5) and not self.killed:
            for pid in session_workers():
                if not descends_from(pid, os.getpid()):
                    continue
                if time.monotonic() - seen.setdefault(pid, time.monotonic()) > 8.0:
                    os.kill(pid, signal.SIGKILL)
                    self.killed.append(pid)
                    return


@pytest.fixture(scope="module")
def maps(weights_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    out = tmp_path_factory.mktemp("maps")
    logs = {}
    for name, index, seed in (("s0", 0, 0), ("s1", 4, 0), ("elsewhere", 2, 11)):
        logs[name] = out / f"{'session' + str(index) if seed == 0 else name}.mcap"  # the session's name
        logs[name].symlink_to(session_log(weights_path, out, FRAMES[name], index, seed))
    garbage = out / "not_a_log.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    config = map_config(weights_path, out, None)
    killer = _WorkerKiller()
    killer.start()
    try:
        first, first_metrics = map_logs([logs["s0"], logs["elsewhere"], garbage], config, Console(quiet=True))
    finally:
        killer.stop.set()
        killer.join()
    # one log to add: one worker, given every core (under map.workers 2 its session would get half of them)
    one_worker = config.model_copy(update={"map": config.map.model_copy(update={"workers": 1})})
    second, second_metrics = map_logs([logs["s1"]], one_worker, Console(quiet=True), add_to=first)
    return {"first": first, "first_metrics": first_metrics, "second": second, "second_metrics": second_metrics,
            "config": config, "killed": killer.killed}  # fmt: skip


def test_a_session_of_another_city_stays_a_separate_map_and_a_bad_log_fails_by_name(maps):
    metrics = maps["first_metrics"]
    assert metrics["sessions"] == 3
    assert metrics["maps"] == [["s0_session0"], ["s1_elsewhere"]]  # the longer session's map first
    failed = [r for r in metrics["session_results"] if r["error"] is not None]
    assert [r["name"] for r in failed] == ["s2_not_a_log"]
    assert "not_a_log.mcap" in failed[0]["error"]
    assert metrics["sessions_merged"] == 1 and metrics["links"] == []
    assert metrics["cross_session_loops"]["in_graph"] == 0


def test_a_worker_killed_mid_session_is_replaced_and_its_session_run_again(maps):
    assert len(maps["killed"]) == 1  # one worker died mid-session
    results = {r["name"]: r for r in maps["first_metrics"]["session_results"]}
    assert results["s0_session0"]["error"] is None and results["s1_elsewhere"]["error"] is None
    sessions = maps["first"] / "sessions"
    assert not list(sessions.glob(".*"))  # nothing half-written left behind
    assert sorted(p.name.split("_20")[0] for p in sessions.iterdir() if not p.is_symlink()) == [
        "s0_session0", "s1_elsewhere"]  # fmt: skip


def test_an_added_session_merges_through_correct_cross_session_loops(maps):
    metrics = maps["second_metrics"]
    names = [r["name"] for r in metrics["session_results"]]
    assert names == ["s0_session0", "s1_elsewhere", "s2_not_a_log", "s3_session4"]
    main = metrics["maps"][0]
    assert sorted(main) == ["s0_session0", "s3_session4"]  # merged; the other city's session is still apart
    assert len(metrics["maps"]) == 2
    loops = metrics["cross_session_loops"]
    assert loops["in_graph"] >= 10, loops
    assert metrics["cross_session_precision"] == 1.0
    # short sessions: a sequence needs 8 keyframes before it decides, so their first revisits go unclosed
    assert metrics["cross_session_recall"] > 0.25, metrics["cross_session_recall"]
    assert metrics["ate_merged_m"] < 1.5, metrics["ate_merged_m"]


def test_the_map_folder_holds_every_output_and_opens_as_a_prior_map(maps):
    folder: Path = maps["second"]
    for name in ("map.json", "metrics.json", "codebooks.npz", "map.g2o", "cross_session_loops.csv",
                 "map_top_view.png", "config.yaml", "trajectories/s0_session0.tum", "trajectories/s3_session4.kitti"):  # fmt: skip
        assert (folder / name).is_file(), name
    manifest = json.loads((folder / "map.json").read_text())
    assert [s["name"] for s in manifest["sessions"]] == ["s0_session0", "s1_elsewhere", "s2_not_a_log", "s3_session4"]
    # the earlier map's session results are shared, not copied (hard links) and not changed
    first = maps["first"]
    s0 = next(s for s in manifest["sessions"] if s["name"] == "s0_session0")
    graph_file = Path(s0["folder"]) / "pose_graph.g2o"
    assert (folder / graph_file).stat().st_ino == (first / graph_file).stat().st_ino
    prior = PriorMap.load(folder, maps["config"].vpr)  # `run --map MAPDIR` reads the map's database/
    sessions = {p.extra["session"] for p in prior.database.places}
    assert sessions == {"s0_session0", "s3_session4"}
    first_session = sum(p.extra["session"] == "s0_session0" for p in prior.database.places)
    assert prior.session_starts() == [first_session]  # where `run --map` stops sequences at the seam
    assert len(prior.poses) == len(prior.database) and len(prior.scans) == len(prior.database)
    # every place posed in the one map frame: where the two sessions drove the same street, their
    # places lie where the ground truth says, relative to each other
    session = np.array([p.extra["session"] == "s3_session4" for p in prior.database.places])
    truth = np.array([prior.gt_poses[k][:3, 3] for k in range(len(prior.database))])
    posed = np.array([prior.poses[k][:3, 3] for k in range(len(prior.database))])
    nearest = cKDTree(truth[~session]).query(truth[session])
    shared = nearest[0] < 2.0
    assert shared.sum() >= 10
    apart_posed = np.linalg.norm(posed[session][shared] - posed[~session][nearest[1][shared]], axis=1)
    assert np.median(apart_posed) < 2.0 and apart_posed.max() < 4.0, apart_posed


def test_map_options_are_checked_before_any_work(tmp_path):
    assert_user_error(invoke("map", "--add", tmp_path / "x.mcap"), "--add needs --map")
    assert_user_error(invoke("map"), "no logs")


def test_an_add_whose_only_log_fails_exits_2_and_leaves_the_map_as_it_was(maps, tmp_path, weights_path):
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"\x89MCAP0\r\n" + bytes(64))
    out = tmp_path / "out"
    result = invoke("map", "--map", maps["first"], "--add", broken, "-c", "quick", "--weights", weights_path,
                    "--workers", "1", "--out", out)  # fmt: skip
    assert_user_error(result, "no added log succeeded (1 failed", f"the map at {maps['first']} is unchanged")
    assert "broken.mcap" in result.stdout  # the failure, by name, above the error
    assert not list(out.glob("map_*")) and not list(out.glob(".map_*"))  # nothing published, nothing left
