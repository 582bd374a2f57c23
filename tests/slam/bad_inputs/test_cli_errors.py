"""The command line on bad input: one "error: ..." line naming the culprit, exit status 2,
never a traceback (typer.testing.CliRunner on ssmvpr_slam.cli.app)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: E402, F401

from frontend.config import McapWriterConfig
from frontend.simulation import SimulationConfig, TraverseSimulator
from frontend.sources import write_frames
from ssmvpr_common.trajectory_io import read_tum


def _write_images(folder: Path, n: int, seed: int) -> list[Path]:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n):
        path = folder / f"img{i}.png"
        assert cv2.imwrite(str(path), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
        paths.append(path)
    return paths


@pytest.fixture
def folders(tmp_path: Path) -> dict[str, Path]:
    _write_images(tmp_path / "ref", 3, 0)
    _write_images(tmp_path / "query", 3, 1)
    (tmp_path / "empty").mkdir()
    return {"ref": tmp_path / "ref", "query": tmp_path / "query", "empty": tmp_path / "empty", "out": tmp_path / "out"}


# ---------------------------------------------------------------------------------- vpr-eval


def test_vpr_eval_missing_folder(folders: dict[str, Path], weights_path: Path) -> None:
    missing = folders["ref"].parent / "no_such_folder"
    result = invoke("vpr-eval", missing, folders["query"], "--weights", weights_path, "--out", folders["out"])
    assert_user_error(result, str(missing), "not found")
    result = invoke("vpr-eval", folders["ref"], missing, "--weights", weights_path, "--out", folders["out"])
    assert_user_error(result, str(missing))
    assert not folders["out"].exists()  # nothing written on a refused run


def test_vpr_eval_empty_folder(folders: dict[str, Path], weights_path: Path) -> None:
    result = invoke("vpr-eval", folders["empty"], folders["query"], "--weights", weights_path, "--out", folders["out"])
    assert_user_error(result, str(folders["empty"]), "no images")


def test_vpr_eval_corrupt_reference_image(folders: dict[str, Path], weights_path: Path) -> None:
    corrupt = folders["ref"] / "img1.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\nthis is not a png")
    result = invoke("vpr-eval", folders["ref"], folders["query"], "--weights", weights_path,
                    "--device", "cpu", "--out", folders["out"])  # fmt: skip
    assert_user_error(result, str(corrupt), "cannot decode")


def test_vpr_eval_ground_truth_naming_an_unknown_file(folders: dict[str, Path], weights_path: Path) -> None:
    gt = folders["ref"].parent / "gt.csv"
    gt.write_text("Reference,Live\nimg0.png,img0.png\nnot_there.png,img1.png\n")
    result = invoke("vpr-eval", folders["ref"], folders["query"], "--gt", gt, "--weights", weights_path,
                    "--out", folders["out"])  # fmt: skip
    assert_user_error(result, str(gt), "not_there.png")


def test_vpr_eval_missing_ground_truth_and_weights(folders: dict[str, Path], weights_path: Path) -> None:
    gt = folders["ref"].parent / "missing.csv"
    result = invoke("vpr-eval", folders["ref"], folders["query"], "--gt", gt, "--weights", weights_path)
    assert_user_error(result, str(gt), "does not exist")
    weights = folders["ref"].parent / "missing.pth"
    result = invoke("vpr-eval", folders["ref"], folders["query"], "--weights", weights, "--out", folders["out"])
    assert_user_error(result, str(weights))


@pytest.mark.parametrize(
    ("option", "value", "field"),
    [("--device", "gpu", "device"), ("-n", "0", "num_candidates"), ("--sequence", "0", "sequence_lengths"),
     ("--direction", "sideways", "direction")],
)  # fmt: skip
def test_vpr_eval_invalid_option_values(folders: dict[str, Path], option: str, value: str, field: str) -> None:
    result = invoke("vpr-eval", folders["ref"], folders["query"], option, value, "--out", folders["out"])
    line = assert_user_error(
        result, field, repr(value) if option in ("--device", "--direction") else "greater than or equal to 1"
    )
    assert f"invalid value for {option}" in line or f"/{option} (" in line  # the option typed, not the model


def test_run_option_errors_name_the_option_in_its_cli_spelling(tmp_path: Path) -> None:
    line = assert_user_error(invoke("run", tmp_path / "x.mcap", "--odometry", "foo"), "--odometry")
    assert "'kiss-icp'" in line and "OdometryConfig" not in line


@pytest.mark.parametrize(
    ("args", "option"),
    [
        (["map", "x.mcap", "--workers", "0"], "--workers"),  # before: 'MapConfig.workers'
        (["run", "x.mcap", "--realtime", "--rate", "0"], "--rate"),  # before: 'PipelineConfig.realtime_rate'
        (["run", "x.mcap", "--frames", "0"], "--frames"),
        (["run", "x.mcap", "--pose-role", "camera"], "--pose-role"),
        (["run", "x.mcap", "--device", "gpu"], "--device"),
        (["demo", "--frames", "0"], "--frames"),
        (["demo", "--odometry", "wheels"], "--odometry"),
        (["simulate", "--frames", "0"], "--frames"),
        (["simulate", "--seed", "-1"], "--seed"),
        (["vpr-eval", "a", "b", "--tolerance", "-1"], "--tolerance"),
    ],
)
def test_every_option_a_config_model_checks_is_named_as_typed(tmp_path: Path, args: list[str], option: str) -> None:
    """An option's value the config models refuse names the option (and the key it sets), never
    the model class a user never sees."""
    out = ["--out", tmp_path / ("o.mcap" if args[0] == "simulate" else "o")]
    line = assert_user_error(invoke(*args, *out), f"invalid value for {option}")
    assert "Config" not in line, line


def test_error_text_with_brackets_is_printed_verbatim(tmp_path: Path) -> None:
    # rich markup must not eat "[x]" from a path, nor crash on the closing tag "[/x]"
    folder = tmp_path / "scans[x]"
    folder.mkdir()
    assert_user_error(invoke("vpr-eval", folder, folder), str(folder), "no images")
    missing = tmp_path / "odd[" / "x]"  # its text holds "[/x]"
    assert_user_error(invoke("vpr-eval", missing, missing), str(missing), "not found")


# --------------------------------------------------------------------------------------- run


@pytest.fixture(scope="module")
def truncated_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """A small simulated log (camera + poses, 8 frames) cut short part-way through."""
    folder = tmp_path_factory.mktemp("logs")
    full = folder / "full.mcap"
    sim = TraverseSimulator(SimulationConfig(max_frames=8, lidar={"enabled": False}))
    assert write_frames(sim.frames(), full, McapWriterConfig(chunk_size=64 * 1024)) == 8
    data = full.read_bytes()
    cut = folder / "cut.mcap"
    cut.write_bytes(data[: int(0.3 * len(data))])
    return cut, 8


@pytest.fixture(scope="module")
def camera_only_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Camera and logged poses, no LiDAR (a car with wheel odometry)."""
    log = tmp_path_factory.mktemp("logs") / "camera_only.mcap"
    write_frames(TraverseSimulator(SimulationConfig(max_frames=6, lidar={"enabled": False})).frames(), log)
    return log


@pytest.fixture(scope="module")
def lidar_only_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("logs") / "lidar_only.mcap"
    write_frames(TraverseSimulator(SimulationConfig(max_frames=3, camera={"enabled": False})).frames(), log)
    return log


def test_run_picks_logged_odometry_for_a_log_without_scans(
    camera_only_log: Path, weights_path: Path, tmp_path: Path
) -> None:
    result = invoke("run", camera_only_log, "--weights", weights_path, "--device", "cpu", "--out", tmp_path / "out")
    assert result.exit_code == 0, result.output
    metrics = json.loads((_run_folders(tmp_path / "out")[0] / "metrics.json").read_text())
    assert metrics["odometry_kind"] == "logged", metrics["odometry_kind"]
    # the logged poses move (kiss-icp without scans would predict a standstill: one keyframe)
    assert metrics["keyframes"] >= 2, (metrics["frames"], metrics["keyframes"])
    # 6 frames end inside the PCA warm-up: the run says so rather than looking like one without loops
    assert metrics["recognition_started"] is False
    assert "recognition never started" in result.output and "detector.pca_warmup_keyframes" in result.output
    assert not (_run_folders(tmp_path / "out")[0] / "database").exists()


def test_opening_a_log_resolves_auto_odometry_without_touching_the_callers_config(camera_only_log: Path) -> None:
    from ssmvpr_slam.app.runner import open_camera_source
    from ssmvpr_slam.config.slam import load_config

    config = load_config(None)
    assert config.frontend.odometry.kind == "auto"
    source, odometry = open_camera_source(camera_only_log, config)
    assert odometry.kind == "logged"  # no scans in the log: the logged poses drive
    assert config.frontend.odometry.kind == "auto"  # the caller's config is as it was given
    assert "camera" in source.topics


def test_run_refuses_an_odometry_the_log_cannot_feed(camera_only_log: Path, weights_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = invoke("run", camera_only_log, "--odometry", "kiss-icp", "--weights", weights_path, "--out", out)
    assert_user_error(result, str(camera_only_log), "kiss-icp odometry needs LiDAR scans", "--odometry logged")
    assert _run_folders(out) == []  # refused before any work: no results folder


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Images and a KITTI-format poses.txt, as a user would lay out a folder."""
    folder = tmp_path_factory.mktemp("logs") / "images_and_poses"
    folder.mkdir()
    frames = list(TraverseSimulator(SimulationConfig(max_frames=6, lidar={"enabled": False})).frames())
    for frame in frames:
        cv2.imwrite(str(folder / f"{frame.index:06d}.png"), cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))
    np.savetxt(folder / "poses.txt", np.array([f.gt_pose[:3].reshape(-1) for f in frames]))
    return folder


def test_an_image_folders_poses_drive_the_run_once_named_odometry(
    image_folder: Path, weights_path: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    result = invoke("run", image_folder, "--weights", weights_path, "--out", out)
    assert_user_error(result, str(image_folder), "no LiDAR scans and no logged poses",
                      "read as ground truth", "run --pose-role logged")  # fmt: skip
    assert _run_folders(out) == []
    assert_user_error(invoke("run", image_folder, "--pose-role", "odometry"), "--pose-role", "'odometry'")
    result = invoke("run", image_folder, "--pose-role", "both", "--weights", weights_path, "--device", "cpu",
                    "--out", out)  # fmt: skip  # as the error says
    assert result.exit_code == 0, result.output
    metrics = json.loads((_run_folders(out)[0] / "metrics.json").read_text())
    assert metrics["odometry_kind"] == "logged" and metrics["frames"] == 6 and metrics["keyframes"] >= 2
    assert metrics["ground_truth"] and metrics["ground_truth_coverage"] == 1.0  # both: the poses are the truth too


def test_an_image_folder_without_poses_points_to_the_recognition_benchmarks(
    image_folder: Path, weights_path: Path, tmp_path: Path
) -> None:
    bare = tmp_path / "images_only"
    bare.mkdir()
    for image in sorted(image_folder.glob("*.png")):
        (bare / image.name).write_bytes(image.read_bytes())
    result = invoke("run", bare, "--pose-role", "logged", "--weights", weights_path, "--out", tmp_path / "out")
    assert_user_error(result, str(bare), "images only", "--pose-role logged", "loop-eval", "vpr-eval")
    assert not (tmp_path / "out").exists()


def test_run_refuses_configured_codebooks_it_cannot_read_before_any_work(
    camera_only_log: Path, weights_path: Path, tmp_path: Path
) -> None:
    out, missing = tmp_path / "out", tmp_path / "no_codebooks.npz"
    env = {"SSMVPR_DETECTOR__CODEBOOKS": str(missing)}
    result = invoke("run", camera_only_log, "--weights", weights_path, "--out", out, env=env)
    assert_user_error(result, "detector.codebooks", str(missing))
    assert _run_folders(out) == []


def test_run_refuses_a_log_without_camera_images(lidar_only_log: Path, weights_path: Path, tmp_path: Path) -> None:
    result = invoke("run", lidar_only_log, "--weights", weights_path, "--out", tmp_path / "out")
    assert_user_error(result, str(lidar_only_log), "no camera images", "lidar")


def _run_folders(out: Path) -> list[Path]:
    return sorted(p for p in out.glob("run_*") if p.is_dir()) if out.exists() else []


def test_run_truncated_log_strict_exits_with_one_line(truncated_log, weights_path: Path, tmp_path: Path) -> None:  # noqa: ANN001
    cut, _ = truncated_log
    out = tmp_path / "out"
    result = invoke("run", cut, "--odometry", "logged", "--weights", weights_path, "--device", "cpu", "--out", out)
    line = assert_user_error(result, str(cut), "truncated")
    assert "after 2 frames" in line
    # the frames before the cut are not lost: a complete results folder records the fault
    folders = _run_folders(out)
    assert len(folders) == 1
    metrics = json.loads((folders[0] / "metrics.json").read_text())
    assert "truncated" in metrics["source_error"]
    assert metrics["frames"] == 2
    assert (folders[0] / "loop_closures.csv").is_file()


def test_run_truncated_log_lenient_keeps_the_frames_before_the_cut(
    truncated_log,
    weights_path: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,  # noqa: ANN001
) -> None:
    cut, total = truncated_log
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        result = invoke("run", cut, "--odometry", "logged", "--weights", weights_path, "--device", "cpu", "--out", out,
                        env={"SSMVPR_FRONTEND__SOURCE__MCAP__STRICT": "false"})  # fmt: skip
    assert result.exit_code == 0, (result.output, result.exception)
    assert f"{cut}: log is truncated or corrupt after 2 frames" in caplog.text  # the clear message, once
    (folder,) = _run_folders(out)
    metrics = json.loads((folder / "metrics.json").read_text())
    assert 0 < metrics["frames"] < total
    assert metrics["source_stats"]["skipped"].get("truncated") == 1
    stamps, poses = read_tum(folder / "odometry.tum")
    assert len(stamps) == len(poses) == metrics["keyframes"] >= 1


def test_run_missing_path(tmp_path: Path) -> None:
    missing = tmp_path / "nothing.mcap"
    assert_user_error(invoke("run", missing), str(missing), "no such file")


def test_run_unrecognised_inputs(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("not a log")
    assert_user_error(invoke("run", text), str(text), "not a .mcap")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_user_error(invoke("run", empty), str(empty), "not recognised")
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"definitely not an mcap file" * 10)
    assert_user_error(invoke("run", garbage), str(garbage))


def test_run_invalid_odometry_kind(truncated_log) -> None:  # noqa: ANN001
    cut, _ = truncated_log
    assert_user_error(invoke("run", cut, "--odometry", "wheels"), "kind", "'wheels'")


# ------------------------------------------------------------------------ config, simulate


def test_config_unknown_preset() -> None:
    assert_user_error(invoke("config", "-c", "nonexistent"), "'nonexistent'", "default", "ras2020")


def test_config_missing_file_path(tmp_path: Path) -> None:
    missing = tmp_path / "missing.yaml"
    assert_user_error(invoke("config", "-c", missing), str(missing))


def test_config_typo_in_file(tmp_path: Path) -> None:
    path = tmp_path / "typo.yaml"
    path.write_text("preset: default\ndetector: {min_scor: 0.3}\n")
    assert_user_error(invoke("config", "-c", path), str(path), "detector.min_scor")


def test_config_bad_environment_variable() -> None:
    result = invoke("config", env={"SSMVPR_DETECTOR__MIN_SCORE": "high"})
    assert_user_error(result, "SSMVPR_DETECTOR__MIN_SCORE", "detector.min_score")


def test_config_prints_effective_yaml() -> None:
    result = invoke("config", "-c", "ras2020", env={"SSMVPR_DETECTOR__GATE__LENGTH": "4"})
    assert result.exit_code == 0, result.output
    assert "cube_size: 9" in result.output and "length: 4" in result.output
    assert "# presets:" in result.output


@pytest.mark.parametrize(
    ("text", "fragment"),
    [("route: {speed_mps: -1}\n", "route.speed_mps"), ("rout: {laps: 1}\n", "rout"), ("- 1\n", "mapping")],
)
def test_simulate_bad_sim_config(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "sim.yaml"
    path.write_text(text)
    out = tmp_path / "sim.mcap"
    assert_user_error(invoke("simulate", "--sim-config", path, "--out", out), str(path), fragment)
    assert not out.exists()


def test_a_full_disk_is_one_line_naming_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """What the file system refuses (ENOSPC here, as a full disk gave from every command) is an
    error line with its errno and file, not a traceback; an OSError that is a fault (a broken
    pipe to a child process) is not dressed up as bad input."""
    import errno

    from ssmvpr_slam.app import runner

    out = tmp_path / "sim.mcap"
    raised: list[OSError] = [OSError(errno.ENOSPC, "No space left on device", str(out))]

    def failing(config, path, console):  # noqa: ANN001, ANN202, ARG001
        raise raised[0]

    monkeypatch.setattr(runner, "simulate_to_mcap", failing)
    assert_user_error(invoke("simulate", "--frames", 2, "--out", out), "No space left on device", str(out))
    raised[0] = BrokenPipeError(errno.EPIPE, "Broken pipe")
    result = invoke("simulate", "--frames", 2, "--out", out)
    assert result.exit_code == 1  # a fault, not the one-line exit 2 of bad input


def test_a_log_that_fills_the_disk_while_it_streams_out_names_the_log(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The MCAP writer streams into its own file: a full disk there (ENOSPC from a file object,
    which names no file) is the same one line naming the log, and no partial log is left."""
    import errno

    import frontend.sources.mcap_writer as mcap_writer

    class FullDisk:
        """The log's file, on a disk with 20 kB left."""

        def __init__(self, file: Any) -> None:
            self.file = file

        def write(self, data: bytes) -> int:
            if self.file.tell() + len(data) > 20_000:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.file.write(data)

        def __getattr__(self, name: str) -> Any:
            return getattr(self.file, name)

    real_writer = mcap_writer.Writer
    monkeypatch.setattr(mcap_writer, "Writer", lambda stream, **kw: real_writer(FullDisk(stream), **kw))
    out = tmp_path / "sim.mcap"
    line = assert_user_error(invoke("simulate", "--frames", 3, "--out", out),
                             f"{out}: disk full while writing it (No space left on device; ")  # fmt: skip
    assert "free on" in line and "--out" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # neither the log nor its temp file
