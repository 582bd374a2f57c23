"""Crash safety: a `run` killed with SIGKILL midway keeps its last checkpoint; the checkpoint
reads as a partial result and opens as `--map`; `run LOG --resume DIR` finishes the run, and
its trajectory equals an uninterrupted run's.

Log: the block_grid route in a city of 10 m blocks, 5 Hz, 120 frames, camera only, with the
logged odometry drifting (heading bias, scale error); a keyframe every second frame (60), the
first revisit from keyframe ~33. Small settings keep it to about a minute on 2 shared cores:
input 112 px, 8 PCA dimensions, PCA fitted on 15 keyframes, a checkpoint every 5 keyframes.
The kill comes once a checkpoint holds 40 keyframes, so loop factors are in the restored graph
and more come after the resume.

The killed and resumed runs overlap their stages (`pipeline.overlap`: the checkpoints are
written while the front end runs ahead, and the encoder's thread encodes keyframes ahead,
`pipeline.encode_ahead`), the uninterrupted one does not: equal results also show the two paths
agree.

Tolerance: the resumed trajectory equals the uninterrupted one to 1e-6 (m, and per element of
the rotation matrices), which is the 9 decimals of the TUM files compared: the detector's state
and the graph are restored exactly, and logged odometry replays deterministically.

A second log has LiDAR (14 m blocks, 150 frames, 75 keyframes): kiss-icp odometry and loop ICP,
both on one thread, loops registered 3 keyframes apart
(`loop_spacing_keyframes`) and the odometry gate at its defaults. The uninterrupted run refuses
the first lap's aliases as implausible (keyframes 46, 48-56), registers the second lap's loops from
keyframe 63 and spaces out those between (ICP at keyframes 63-66, the first three refused for
poor alignment, then 69, 72; spaced 67, 68, 70, 71, 73, 74).
Checkpoints come every 4 keyframes from the warm-up's 15th, so the kill after the first one of at
least 70 keyframes cuts the run at 71, and the log ends 4 keyframes later (one more ICP, and
spaced loops carried from before the cut and not): the resumed run must replay kiss-icp to the
same odometry and read the restored loop records and travelled distances to the same decisions,
among them spaced loops carried from a loop registered before the cut. All three LiDAR runs are
processes of their own, as a user's are: kiss-icp caps its threads once per process, at its
first registration (frontend/odometry/kiss_threads.py), and earlier tests in this process may
have built registrations on every core. Run in-process, the resumed and uninterrupted runs' loop
ICP then ran on 2 threads against the killed run's 1, and an inlier ratio came out 0.313 against
0.312 (the optimised poses 1.9 mm apart).
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: E402, F401

from frontend.config import McapWriterConfig
from frontend.simulation import SimulationConfig, TraverseSimulator
from frontend.sources import write_frames
from ssmvpr_common.trajectory_io import read_tum
from ssmvpr_slam.checkpoint.loading import load_checkpoint
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.prior_map import PriorMap

pytestmark = pytest.mark.slow

FRAMES = 120
KILL_AT_KEYFRAMES = 40
LIDAR_FRAMES = 150
LIDAR_KILL_AT_KEYFRAMES = 70
TOLERANCE = 1e-6

SMALL = """\
vpr:
  backbone: {input_size: 112, device: cpu}
  filtering: {pca: {dim: 8}}
  spatial: {pca: {dim: 8}}
detector: {pca_warmup_keyframes: 15, calibrated: {min_history: 10, prior_runner_ups: 0}}
evaluation: {loops: {min_frame_gap: 25}}
"""
# a short log with early revisits, decided by its own young model (no prior): it accepts look-alikes
# early that the odometry gate must refuse, the decisions that read restored state
SMALL_DETECTOR = "detector: {pca_warmup_keyframes: 15, calibrated: {min_history: 10, prior_runner_ups: 0}}\n"
FRONTEND = "frontend:\n  keyframes: {min_distance_m: null, min_angle_deg: null, max_interval_s: 0.35}\n"

# the camera-only log is too short and its 112-px images too coarse for the calibrated decision, and
# for the checks on camera loops, to let a loop into the graph before the kill; a resume must rebuild
# the same graph whatever the rules, so this log takes the loosest (absolute thresholds, camera loops
# unchecked). The LiDAR log below resumes with the default rules.
ABSOLUTE = (
    "detector: {pca_warmup_keyframes: 15, decision: absolute, rear: {direction: both},\n"
    "           sequence: {length: 3, direction: both, sequence_candidates: 10}}\n"
    "backend: {registration: {two_view: {on_geometry_failure: yaw_prior}, odometry_gate: {max_heading_deg: null}}}\n"
)

CONFIG = (
    SMALL.replace(SMALL_DETECTOR, ABSOLUTE)
    + FRONTEND
    + """\
  odometry:
    kind: logged
    logged: {pose_source: logged, drift: {enabled: true, yaw_bias_per_m: 0.002, translation_scale_error: 0.02}}
pipeline: {use_lidar_for_loops: false, overlap: OVERLAP, encode_ahead: OVERLAP}
results: {plots: false, checkpoint_every_keyframes: 5, checkpoint_every_s: null}
"""
)

LIDAR_CONFIG = (
    SMALL
    + FRONTEND
    + """\
  odometry: {kind: kiss_icp, kiss_icp: {max_num_threads: 1}}
backend: {registration: {lidar: {max_num_threads: 1, loop_spacing_keyframes: 3}}}
pipeline: {overlap: OVERLAP, encode_ahead: OVERLAP}
results: {plots: false, checkpoint_every_keyframes: 4, checkpoint_every_s: null}
"""
)


def _write_inputs(base: Path, sim: SimulationConfig, frames: int, config: str) -> SimpleNamespace:
    """The log (lossless PNG images: the same pixels on every read), its first 8 frames, and the
    config twice: stages overlapped and sequential."""
    rendered = list(TraverseSimulator(sim).frames())
    writer = McapWriterConfig(image_format="png", chunk_size=256 * 1024)
    log = base / "log.mcap"
    assert write_frames(iter(rendered), log, writer) == frames
    short = base / "short.mcap"
    assert write_frames(iter(rendered[:8]), short, writer) == 8
    overlapped = base / "small.yaml"
    overlapped.write_text(config.replace("OVERLAP", "true"))
    sequential = base / "small_sequential.yaml"
    sequential.write_text(config.replace("OVERLAP", "false"))
    return SimpleNamespace(base=base, log=log, short=short, config=overlapped, sequential=sequential)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    sim = SimulationConfig(frame_rate_hz=5.0, city={"block_size_m": 10.0}, route={"preset": "block_grid", "laps": 2},
                           max_frames=FRAMES, lidar={"enabled": False})  # fmt: skip
    return _write_inputs(tmp_path_factory.mktemp("resume"), sim, FRAMES, CONFIG)


@pytest.fixture(scope="module")
def lidar_inputs(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    sim = SimulationConfig(frame_rate_hz=5.0, city={"block_size_m": 14.0}, route={"preset": "block_grid", "laps": 2},
                           max_frames=LIDAR_FRAMES, lidar={"enabled": True, "beams": 16, "azimuths": 512})  # fmt: skip
    return _write_inputs(tmp_path_factory.mktemp("resume_lidar"), sim, LIDAR_FRAMES, LIDAR_CONFIG)


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.upper().startswith("SSMVPR_")}


def _kill(
    inputs: SimpleNamespace, weights_path: Path, at_keyframes: int, sig: signal.Signals = signal.SIGKILL
) -> SimpleNamespace:
    """`run` in a subprocess, sent `sig` once a checkpoint holds `at_keyframes` (SIGKILL: it dies
    there; SIGTERM: it stops at the frame it is on, as a preempted job does, and writes its partial
    results with the checkpoint it writes as it stops)."""
    out = inputs.base / ("killed" if sig == signal.SIGKILL else f"stopped_{sig.name}")
    command = [sys.executable, "-c", "from ssmvpr_slam.cli import app; app()", "run", str(inputs.log),
               "-c", str(inputs.config), "--weights", str(weights_path), "--out", str(out)]  # fmt: skip
    log_file = open(inputs.base / "killed.log", "wb")  # noqa: SIM115 (one at a time: each call rewrites it)
    process = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT, env=_env())
    checkpointed = 0
    deadline = time.monotonic() + 600
    try:
        while checkpointed < at_keyframes:
            assert process.poll() is None, f"the run ended before the kill:\n{(inputs.base / 'killed.log').read_text()}"
            assert time.monotonic() < deadline, "no checkpoint came"
            for record in out.glob("run_*/checkpoint/checkpoint.json"):
                try:
                    checkpointed = json.loads(record.read_text())["keyframes"]
                except (OSError, ValueError):
                    pass  # replaced under our feet: the next poll reads the new one
            time.sleep(0.1)
        process.send_signal(sig)
        code = process.wait(120)
        assert code == (-signal.SIGKILL if sig == signal.SIGKILL else 0), (inputs.base / "killed.log").read_text()
    finally:
        if process.poll() is None:
            process.kill()
        log_file.close()
    [run_folder] = out.glob("run_*")
    return SimpleNamespace(out=out, run_folder=run_folder, checkpoint=load_checkpoint(run_folder))


def _cli_in_own_process(inputs: SimpleNamespace, name: str, *args: object) -> None:
    """`ssmvpr-slam *args` in a fresh interpreter, as a user runs it (see the docstring: kiss-icp's
    thread cap is per process)."""
    command = [sys.executable, "-c", "from ssmvpr_slam.cli import app; app()", *map(str, args)]
    done = subprocess.run(command, capture_output=True, env=_env(), timeout=600)
    (inputs.base / f"{name}.log").write_bytes(done.stdout + done.stderr)
    assert done.returncode == 0, (done.stdout + done.stderr).decode(errors="replace")[-3000:]


def _uninterrupted(inputs: SimpleNamespace, weights_path: Path, own_process: bool = False) -> Path:
    out = inputs.base / "uninterrupted"
    args = ("run", inputs.log, "-c", inputs.sequential, "--weights", weights_path, "--out", out)
    if own_process:
        _cli_in_own_process(inputs, "uninterrupted", *args)
    else:
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    return (out / "latest").resolve()


def _resume(killed: SimpleNamespace, inputs: SimpleNamespace, weights_path: Path, own_process: bool = False) -> Path:
    args = ("run", inputs.log, "--resume", killed.run_folder, "--weights", weights_path)
    if own_process:
        _cli_in_own_process(inputs, "resumed", *args)
    else:
        result = invoke(*args)
        assert result.exit_code == 0, result.output
    return killed.run_folder


@pytest.fixture(scope="module")
def killed(inputs: SimpleNamespace, weights_path: Path) -> SimpleNamespace:
    return _kill(inputs, weights_path, KILL_AT_KEYFRAMES)


@pytest.fixture(scope="module")
def uninterrupted(inputs: SimpleNamespace, weights_path: Path) -> Path:
    return _uninterrupted(inputs, weights_path)


@pytest.fixture(scope="module")
def resumed(killed: SimpleNamespace, inputs: SimpleNamespace, weights_path: Path) -> Path:
    """The run's folder, finished by a resume."""
    return _resume(killed, inputs, weights_path)


def _assert_finished_as_if_never_killed(
    folder: Path, uninterrupted: Path, killed: SimpleNamespace, frames: int
) -> None:
    assert (killed.out / "latest").resolve() == folder  # published under the run's own name
    assert not list(folder.glob("checkpoint*"))  # the final results replaced the checkpoints
    metrics = json.loads((folder / "metrics.json").read_text())
    expected = json.loads((uninterrupted / "metrics.json").read_text())
    assert metrics["resumed_from"]["frames"] == killed.checkpoint.result.frames_seen
    assert metrics["frames"] == expected["frames"] == frames and metrics["keyframes"] == expected["keyframes"]
    assert metrics["loops"] == expected["loops"]
    for name in ("odometry.tum", "optimised.tum"):
        stamps, poses = read_tum(folder / name)
        stamps_ref, poses_ref = read_tum(uninterrupted / name)
        np.testing.assert_array_equal(stamps, stamps_ref)
        assert np.abs(poses - poses_ref).max() <= TOLERANCE, name
    assert (folder / "loop_closures.csv").read_text() == (uninterrupted / "loop_closures.csv").read_text()
    assert (folder / "trajectory.mcap").stat().st_size > 0 and (folder / "database" / "manifest.json").is_file()


def test_the_kill_leaves_a_checkpoint_and_no_finished_results(killed: SimpleNamespace) -> None:
    assert not (killed.out / "latest").exists()  # nothing was published
    assert not (killed.run_folder / "metrics.json").exists()
    assert (killed.run_folder / "checkpoint").is_symlink()
    partial = killed.checkpoint.result
    assert len(partial.keyframes) >= KILL_AT_KEYFRAMES and partial.ending.interrupted
    assert any(r.in_graph for r in partial.loops)  # the restored graph has loop factors to rebuild


def test_the_checkpoint_reads_as_a_partial_result(killed: SimpleNamespace) -> None:
    checkpoint = killed.checkpoint
    partial = checkpoint.result
    stamps, odom = read_tum(checkpoint.folder / "odometry.tum")
    _, optimised = read_tum(checkpoint.folder / "optimised.tum")
    np.testing.assert_allclose(stamps, partial.stamps, atol=TOLERANCE)
    np.testing.assert_allclose(odom, partial.odometry, atol=TOLERANCE)
    np.testing.assert_allclose(optimised, partial.optimised, atol=TOLERANCE)
    with open(checkpoint.folder / "loop_closures.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(partial.loops) and sum(r["in_graph"] == "1" for r in rows) == sum(
        r.in_graph for r in partial.loops
    )
    # what the keyframes keep, read back: grey copies within the pixel budget (here the camera's
    # 320 x 240, the rear one too as there is no scan) and JPEG thumbnails, no full image
    assert all(k.image is not None and k.image.gray.shape == (240, 320) and k.image.nbytes < 320 * 240
               and k.rear_image is not None and k.rear_image.gray.shape == (240, 320)
               and k.thumbnail is not None and len(k.thumbnail) < 12_000 for k in partial.keyframes)  # fmt: skip


def test_the_checkpoint_opens_as_a_prior_map(killed: SimpleNamespace, inputs: SimpleNamespace, weights_path: Path,
                                              tmp_path: Path) -> None:  # fmt: skip
    database = killed.run_folder / "checkpoint" / "database"
    n = len(killed.checkpoint.result.keyframes)
    prior = PriorMap.load(database, load_config(inputs.config).vpr)
    assert len(prior) == n and len(prior.poses) == n and len(prior.gt_poses) == n
    np.testing.assert_allclose(prior.poses[n - 1], killed.checkpoint.result.optimised[n - 1], atol=1e-9)
    # and the command line takes it: a short session closes loops against it
    result = invoke("run", inputs.short, "-c", inputs.config, "--map", database, "--weights", weights_path,
                    "--out", tmp_path / "out")  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["prior_map_loops"]["places"] == n and metrics["prior_map_loops"]["loops_proposed"] >= 1


def test_resume_refuses_other_settings_and_another_log(killed: SimpleNamespace, inputs: SimpleNamespace) -> None:
    result = invoke("run", inputs.log, "--resume", killed.run_folder, "-c", inputs.config)
    assert_user_error(result, "--resume", "--config cannot be combined")
    result = invoke("run", inputs.short, "--resume", killed.checkpoint.folder)
    assert_user_error(result, str(inputs.short), "not the log")
    missing = inputs.base / "no_such_run"
    assert_user_error(invoke("run", inputs.log, "--resume", missing), str(missing), "no such results folder")


def test_resume_finishes_the_run_as_if_never_killed(resumed: Path, uninterrupted: Path,
                                                     killed: SimpleNamespace) -> None:  # fmt: skip
    _assert_finished_as_if_never_killed(resumed, uninterrupted, killed, FRAMES)


def test_a_finished_run_is_not_resumed_again(resumed: Path, inputs: SimpleNamespace) -> None:
    result = invoke("run", inputs.log, "--resume", resumed)
    assert_user_error(result, str(resumed), "this run finished")


def test_a_run_stopped_by_sigterm_resumes_as_if_never_stopped(
    inputs: SimpleNamespace, uninterrupted: Path, weights_path: Path
) -> None:
    """A scheduler's SIGTERM (preemption): the run publishes its partial results with the
    checkpoint it wrote as it stopped, and `--resume` finishes it as if it had never stopped
    (before: the partial results replaced the checkpoint, and the resume said "finished")."""
    stopped = _kill(inputs, weights_path, 30, signal.SIGTERM)
    metrics = json.loads((stopped.run_folder / "metrics.json").read_text())
    assert metrics["interrupted"] is True and (stopped.out / "latest").resolve() == stopped.run_folder
    assert stopped.checkpoint.result.frames_seen == metrics["frames"] < FRAMES  # checkpointed where it stopped
    assert "resume it with: ssmvpr-slam run" in " ".join((inputs.base / "killed.log").read_text().split())
    resumed = _resume(stopped, inputs, weights_path)
    _assert_finished_as_if_never_killed(resumed, uninterrupted, stopped, FRAMES)


def test_a_lidar_run_with_spaced_and_gated_loops_resumes_as_if_never_killed(
    lidar_inputs: SimpleNamespace, weights_path: Path
) -> None:
    killed = _kill(lidar_inputs, weights_path, LIDAR_KILL_AT_KEYFRAMES)
    cut = len(killed.checkpoint.result.keyframes)
    # loops registered in the worker and not in the graph yet (pipeline.registration_lag_keyframes):
    # the checkpoint keeps them, and the resume applies them when they fall due
    assert killed.checkpoint.result.unapplied_registrations, "no loop was waiting to be applied at the cut"
    uninterrupted = _uninterrupted(lidar_inputs, weights_path, own_process=True)
    with open(uninterrupted / "loop_closures.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    method = {(int(r["query_kf"]), int(r["match_kf"])): r["registration"] for r in rows}
    before = [m for (q, _), m in method.items() if q < cut]
    after = [m for (q, _), m in method.items() if q >= cut]
    # the decisions that read restored state: the gate's refusals (travelled distances) before the
    # cut, loops registered by ICP and loops spaced out by an earlier one on both sides of it
    assert {"implausible", "icp", "spaced"} <= set(before), before
    assert {"icp", "spaced"} <= set(after), after
    carried_over = [r for r in rows if r["registration"] == "spaced" and int(r["query_kf"]) >= cut
                    and int(r["registration_reason"].split(" -> ")[0].split()[-1]) < cut]  # fmt: skip
    assert carried_over, "no spaced loop after the resume is carried from a loop registered before it"
    resumed = _resume(killed, lidar_inputs, weights_path, own_process=True)
    _assert_finished_as_if_never_killed(resumed, uninterrupted, killed, LIDAR_FRAMES)
