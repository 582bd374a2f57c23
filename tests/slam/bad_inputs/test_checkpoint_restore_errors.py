"""A checkpoint whose detector state this build or these settings cannot take (a calibration
count that differs, a key it lacks) is refused as one CheckpointError naming the state's file,
before any frame is replayed."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
from rich.console import Console

from loopclosure.errors import LoopClosureInputError
from ssmvpr_slam.app import checkpoint_replay
from ssmvpr_slam.app.checkpoint_replay import restore_from_checkpoint
from ssmvpr_slam.checkpoint.saving import CheckpointError


@pytest.mark.parametrize(
    "problem, expected",
    [
        (LoopClosureInputError("int8 stream calibration calibrated on 4 images, but int8_calibration_images is 3"),
         "detector.npz: int8 stream calibration calibrated on 4 images"),
        (KeyError("int8_stream_calibrated"), "detector.npz: lacks 'int8_stream_calibrated'"),
    ],
)  # fmt: skip
def test_a_state_the_detector_refuses_names_the_checkpoints_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, problem, expected
) -> None:
    def restore(system, result, state) -> None:  # noqa: ANN001
        raise problem

    monkeypatch.setattr(checkpoint_replay, "restore_system", restore)
    replayed: list[object] = []
    pipeline = SimpleNamespace(system=SimpleNamespace(odometry=SimpleNamespace(update=replayed.append)))
    checkpoint = SimpleNamespace(folder=tmp_path / "checkpoint-000002", result=SimpleNamespace(frames_seen=3),
                                 detector_state={})  # fmt: skip
    with pytest.raises(CheckpointError) as caught:
        restore_from_checkpoint(pipeline, checkpoint, tmp_path / "log.mcap", iter([1, 2, 3]), Console())  # type: ignore[arg-type]
    message = str(caught.value)
    assert message.startswith(str(tmp_path / "checkpoint-000002" / "detector.npz")) and expected in message
    assert "\n" not in message and replayed == []
