"""kiss-icp handed frames ahead (`pipeline.odometry_ahead_frames`): with the stages overlapped its
process registers the next scans while the front end keeps this keyframe. The run must be the one
it is with frames handed over one at a time: the same keyframes at the same poses, the same
frames counted, and a log cut short keeps the frames before the cut."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry import OdometryProcess, make_odometry
from frontend.simulation import SimulationConfig, TraverseSimulator
from loopclosure.backbone import load_backbone
from ssmvpr_slam.app.pipeline import SlamPipeline
from ssmvpr_slam.config.slam import SlamConfig, load_config
from ssmvpr_slam.kept_keyframe import kept_voxel
from ssmvpr_slam.run_state import RunState

pytestmark = pytest.mark.slow

FRAMES = 24
CONFIG = {
    "vpr": {"backbone": {"input_size": 112, "device": "cpu"}, "filtering": {"pca": {"dim": 8}},
            "spatial": {"pca": {"dim": 8}}},
    "detector": {"pca_warmup_keyframes": 10},
    "frontend": {"keyframes": {"min_distance_m": None, "min_angle_deg": None, "max_interval_s": 0.35},
                 "odometry": {"kind": "kiss_icp", "kiss_icp": {"max_num_threads": 1}}},
    "pipeline": {"overlap": True},
    "results": {"plots": False},
}  # fmt: skip


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    sim = SimulationConfig(frame_rate_hz=5.0, city={"block_size_m": 10.0}, route={"preset": "block_grid"},
                           max_frames=FRAMES, lidar={"enabled": True, "beams": 16, "azimuths": 512})  # fmt: skip
    return list(TraverseSimulator(sim).frames())


@pytest.fixture(scope="module")
def backbone(weights_path: Path):
    return load_backbone(_config(weights_path, 0).vpr.backbone)


def _config(weights_path: Path, ahead: int) -> SlamConfig:
    cfg = load_config(overrides=CONFIG)
    cfg.vpr.backbone.weights = str(weights_path)
    cfg.pipeline.odometry_ahead_frames = ahead
    return cfg


def _run(cfg: SlamConfig, frames: Iterator[Frame], backbone: object) -> tuple[SlamPipeline, RunState]:
    odometry = make_odometry(cfg.frontend.odometry, own_process=True, kept_voxel=kept_voxel(cfg))
    pipeline = SlamPipeline.build(cfg, odometry, backbone)  # type: ignore[arg-type]
    handed: list[int] = []
    submit = odometry.submit

    def recorded(frame: Frame) -> None:  # when each frame went to the odometry's process
        handed.append(pipeline.system.front_counts.frames_seen)
        submit(frame)

    odometry.submit = recorded  # type: ignore[method-assign]
    state = pipeline.run(frames)
    pipeline.handed = handed  # type: ignore[attr-defined]
    return pipeline, state


def test_frames_handed_ahead_give_the_run_of_one_at_a_time(
    weights_path: Path, frames: list[Frame], backbone: object
) -> None:
    one, one_state = _run(_config(weights_path, 0), iter(frames), backbone)
    ahead, ahead_state = _run(_config(weights_path, 1), iter(frames), backbone)
    assert isinstance(ahead.odometry, OdometryProcess)
    # one at a time, frame k goes to kiss-icp as the front end takes it (k + 1 frames seen); ahead,
    # before the front end has taken frame k - 1 (k - 1 seen): while it keeps the keyframe before
    assert one.handed == list(range(1, FRAMES + 1))  # type: ignore[attr-defined]
    assert ahead.handed == [0, 0, *range(1, FRAMES - 1)]  # type: ignore[attr-defined]
    assert one_state.frames_seen == ahead_state.frames_seen == FRAMES
    a, b = one.finish(), ahead.finish()
    assert len(a.keyframes) == len(b.keyframes) >= FRAMES // 2
    assert [k.frame_index for k in a.keyframes] == [k.frame_index for k in b.keyframes]
    np.testing.assert_allclose(a.odometry, b.odometry, rtol=0, atol=1e-9)  # kiss-icp on one thread
    assert all(k.scan is not None for k in b.keyframes)
    assert [k.scan.count for k in a.keyframes] == [k.scan.count for k in b.keyframes]  # type: ignore[union-attr]
    assert b.odometry_stats["updates"] == FRAMES
    assert ahead.odometry._process.poll() == 0  # type: ignore[attr-defined]  # finish ended the child


def test_a_log_cut_short_keeps_the_frames_before_it_when_handed_ahead(
    weights_path: Path, frames: list[Frame], backbone: object
) -> None:
    def cut() -> Iterator[Frame]:
        yield from frames[:15]
        raise FrontendInputError("cut.mcap: truncated after 15 frames")

    pipeline, state = _run(_config(weights_path, 2), cut(), backbone)
    assert pipeline.step_error is None and pipeline.ending.source_error == "cut.mcap: truncated after 15 frames"
    assert state.frames_seen == 15 and pipeline.finish().odometry_stats["updates"] == 15  # type: ignore[index]


def test_a_stop_with_frames_in_flight_ends_the_child_and_counts_the_frames_taken(
    weights_path: Path, frames: list[Frame], backbone: object
) -> None:
    pipeline: SlamPipeline | None = None

    def interrupted() -> Iterator[Frame]:
        for frame in frames:
            if frame.index == 12:
                assert pipeline is not None
                pipeline.stop.requested = True  # as SIGINT's handler does, with frames 10 and 11 handed over
            yield frame

    cfg = _config(weights_path, 2)
    odometry = make_odometry(cfg.frontend.odometry, own_process=True, kept_voxel=kept_voxel(cfg))
    pipeline = SlamPipeline.build(cfg, odometry, backbone)  # type: ignore[arg-type]
    state = pipeline.run(interrupted())
    assert pipeline.ending.interrupted and pipeline.step_error is None
    taken = state.frames_seen
    assert 8 <= taken <= 12  # the front end stops after its current frame; those handed ahead are dropped
    result = pipeline.finish()
    assert result.odometry_stats["updates"] == taken  # the odometry's counts cover the frames taken
    assert isinstance(odometry, OdometryProcess) and odometry._process.poll() == 0
