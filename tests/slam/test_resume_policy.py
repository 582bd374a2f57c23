"""What `run --resume` keeps and what it may change (`ssmvpr_slam.checkpoint.resume`): the options and
SSMVPR_ settings that would change the checkpoint's settings are refused before anything is
read; the resumed run takes the checkpoint's config.yaml, only the weights and the device as
given, and writes beside its run's folder. The command line end to end: test_checkpoint_resume.py
and bad_inputs/test_damaged_files.py."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_helpers import clean_ssmvpr_environment  # noqa: F401
from pydantic import ValidationError

from ssmvpr_slam.checkpoint.record import CheckpointError
from ssmvpr_slam.checkpoint.resume import check_resume_options, prepare_resume, resumed_config
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.results.writers import write_config

NOTHING_GIVEN = {"--config": None, "--no-lidar-loops": False, "--frames": None, "--realtime": False}


def test_options_not_given_pass_and_given_ones_are_named_in_order(tmp_path: Path) -> None:
    check_resume_options(tmp_path, NOTHING_GIVEN, environ={})
    given = {**NOTHING_GIVEN, "--no-lidar-loops": True, "--frames": 0, "--config": "fast"}  # 0 is a value given
    with pytest.raises(CheckpointError) as refused:
        check_resume_options(tmp_path, given, environ={})
    assert str(refused.value) == (f"--resume {tmp_path}: --config, --no-lidar-loops, --frames cannot be combined "
                                  "with it (a resumed run keeps the settings of its checkpoint)")  # fmt: skip


def test_settings_from_the_environment_are_refused_but_weights_device_and_files_are_not(tmp_path: Path) -> None:
    allowed = {"SSMVPR_WEIGHTS": "/w.pth", "SSMVPR_CACHE": "/c", "SSMVPR_VPR__BACKBONE__DEVICE": "cpu",
               "SSMVPR_VPR__BACKBONE__WEIGHTS": "/w.pth", "HOME": "/root"}  # fmt: skip
    check_resume_options(tmp_path, NOTHING_GIVEN, environ=allowed)
    environ = {**allowed, "SSMVPR_DETECTOR__CALIBRATED__ACCEPT": "5", "ssmvpr_pipeline__max_frames": "3"}
    with pytest.raises(CheckpointError) as refused:
        check_resume_options(tmp_path, NOTHING_GIVEN, environ=environ)
    message = str(refused.value)
    assert "SSMVPR_DETECTOR__CALIBRATED__ACCEPT, ssmvpr_pipeline__max_frames would change" in message
    assert "DEVICE" not in message and "SSMVPR_WEIGHTS" not in message and "unset them" in message


def test_options_are_refused_before_the_checkpoint_is_read(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_run"
    with pytest.raises(CheckpointError, match="--map cannot be combined"):
        prepare_resume(missing, {"--map": tmp_path / "database"})
    with pytest.raises(CheckpointError, match="no such results folder"):  # and then the folder is read
        prepare_resume(missing, NOTHING_GIVEN)


def test_the_resumed_config_is_the_checkpoints_with_only_weights_and_device_changed(tmp_path: Path) -> None:
    saved = load_config("fast")
    saved.detector.calibrated.accept = 4.5
    saved.vpr.backbone.weights = "/where/it/was.pth"
    run_folder = tmp_path / "results" / "run_x"
    (run_folder / "checkpoint-000001").mkdir(parents=True)
    write_config(run_folder / "checkpoint-000001", saved)
    config_path = run_folder / "checkpoint-000001" / "config.yaml"

    kept = resumed_config(config_path, run_folder, None, None)
    assert kept.vpr.backbone.weights == "/where/it/was.pth" and kept.vpr.backbone.device == saved.vpr.backbone.device
    assert kept.results.out_dir == str(tmp_path / "results")  # the resumed run publishes beside its folder
    expected = saved.model_dump()
    expected["results"]["out_dir"] = str(tmp_path / "results")
    assert kept.model_dump() == expected

    moved = resumed_config(config_path, run_folder, Path("/now/here.pth"), "cpu")
    assert moved.vpr.backbone.weights == "/now/here.pth" and moved.vpr.backbone.device == "cpu"
    assert moved.detector.calibrated.accept == 4.5 and moved.vpr.filtering == saved.vpr.filtering
    with pytest.raises(ValidationError):  # a device the model refuses (the command line names --device)
        resumed_config(config_path, run_folder, None, "gpu")
