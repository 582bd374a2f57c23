"""The stages overlapped (`pipeline.overlap`): a producer thread runs the source, odometry and
keyframe selection while this thread runs the backbone, recognition, registration and iSAM2.
It must not change the result: the same keyframes, loops and trajectory as the sequential
path, also with the backbone encoding the next keyframe in a thread of its own
(`pipeline.encode_ahead`). Nor must the stage-I search a GPU runs (torch from a float16 copy). And keyframes keep
bounded images, never the camera's full ones.

Traverse: the block_grid route in a city of 10 m blocks, 5 Hz, 100 frames, camera only
(forward and rear), drifting logged odometry; a keyframe every second frame (50), the first
revisit from keyframe ~33. Small settings keep each run to seconds: input 112 px, 8 PCA
dimensions, PCA fitted on 15 keyframes.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry import make_odometry
from frontend.simulation import SimulationConfig, TraverseSimulator
from loopclosure.backbone import load_backbone
from ssmvpr_slam.app.pipeline import SlamPipeline
from ssmvpr_slam.backend.two_view import ReducedImage
from ssmvpr_slam.config.slam import SlamConfig, load_config
from ssmvpr_slam.run_result import RunResult
from ssmvpr_slam.run_state import FRONT_PARTS

pytestmark = pytest.mark.slow

FRAMES = 100
CONFIG = {
    "vpr": {"backbone": {"input_size": 112, "device": "cpu"}, "filtering": {"pca": {"dim": 8}},
            "spatial": {"pca": {"dim": 8}}},
    # the log is too short and its 112-px images too coarse for the calibrated decision, and for the
    # checks on camera loops, to let a loop into the graph: overlapping the stages must give the same
    # graph whatever the rules, so this test takes the loosest (absolute thresholds, camera loops unchecked)
    "detector": {"pca_warmup_keyframes": 15, "decision": "absolute", "rear": {"direction": "both"},
                 "sequence": {"length": 3, "direction": "both", "sequence_candidates": 10}},
    "backend": {"registration": {"two_view": {"on_geometry_failure": "yaw_prior"},
                                 "odometry_gate": {"max_heading_deg": None}}},
    "frontend": {"keyframes": {"min_distance_m": None, "min_angle_deg": None, "max_interval_s": 0.35},
                 "odometry": {"kind": "logged", "logged": {"pose_source": "logged",
                              "drift": {"enabled": True, "yaw_bias_per_m": 0.002, "translation_scale_error": 0.02}}}},
    "pipeline": {"use_lidar_for_loops": False},
    "results": {"plots": False},
}  # fmt: skip


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    sim = SimulationConfig(frame_rate_hz=5.0, city={"block_size_m": 10.0}, route={"preset": "block_grid", "laps": 2},
                           max_frames=FRAMES, lidar={"enabled": False})  # fmt: skip
    return list(TraverseSimulator(sim).frames())


def _config(weights_path: Path, overlap: bool, **pipeline: object) -> SlamConfig:
    cfg = load_config(overrides=CONFIG)
    cfg.vpr.backbone.weights = str(weights_path)
    cfg.pipeline.overlap = overlap
    for key, value in pipeline.items():
        setattr(cfg.pipeline, key, value)
    return cfg


@dataclass
class Run:
    pipeline: SlamPipeline
    result: RunResult


def _run(cfg: SlamConfig, frames: list[Frame], backbone: object) -> Run:
    pipeline = SlamPipeline.build(cfg, make_odometry(cfg.frontend.odometry), backbone)  # type: ignore[arg-type]
    pipeline.run(iter(frames))
    return Run(pipeline, pipeline.finish())


@pytest.fixture(scope="module")
def backbone(weights_path: Path):
    return load_backbone(_config(weights_path, False).vpr.backbone)


@pytest.fixture(scope="module")
def sequential(weights_path: Path, frames: list[Frame], backbone: object) -> Run:
    return _run(_config(weights_path, overlap=False), frames, backbone)


@pytest.fixture(scope="module")
def overlapped(weights_path: Path, frames: list[Frame], backbone: object) -> Run:
    return _run(_config(weights_path, overlap=True, overlap_queue_keyframes=2), frames, backbone)


def test_overlap_gives_the_sequential_keyframes_loops_and_trajectory(sequential: Run, overlapped: Run) -> None:
    a, b = sequential.result, overlapped.result
    assert a.frames_seen == b.frames_seen == FRAMES and len(a.keyframes) == len(b.keyframes) == FRAMES // 2
    assert dict(a.frames_skipped) == dict(b.frames_skipped) and a.rear_keyframes == b.rear_keyframes
    for ka, kb in zip(a.keyframes, b.keyframes):
        assert (ka.id, ka.frame_index, ka.timestamp) == (kb.id, kb.frame_index, kb.timestamp)
        assert ka.image == kb.image and ka.rear_image == kb.rear_image and ka.thumbnail == kb.thumbnail
    np.testing.assert_array_equal(a.odometry, b.odometry)
    assert any(r.in_graph for r in a.loops)  # the run got to its revisits: there is something to compare
    assert [(r.proposal, r.factor_handle, r.dropped) for r in a.loops] == [(r.proposal, r.factor_handle, r.dropped)
                                                                            for r in b.loops]  # fmt: skip
    for ra, rb in zip(a.loops, b.loops):
        assert (ra.registration is None) == (rb.registration is None)
        if ra.registration is not None:
            np.testing.assert_array_equal(ra.registration.T_mq, rb.registration.T_mq)
    np.testing.assert_array_equal(a.optimised, b.optimised)
    # the front end's own time is recorded per keyframe beside the back end's stages
    assert all(row["front_end"] > 0 for row in b.timings) and len(b.timings) == len(b.keyframes)
    for row in b.timings:  # and where it went: the odometry (here in this thread) and keeping the keyframe
        assert min(row[name] for name in FRONT_PARTS) >= 0.0 and row["odometry"] == row["odometry_wait"] > 0.0
        assert row["odometry_wait"] + row["keyframe_keeping"] <= row["front_end"]


@pytest.fixture(scope="module")
def encoded_ahead(weights_path: Path, frames: list[Frame], backbone: object) -> Run:
    return _run(_config(weights_path, overlap=True, encode_ahead=True), frames, backbone)


def test_keyframes_encoded_ahead_give_the_sequential_loops_and_trajectory(sequential: Run, encoded_ahead: Run) -> None:
    """The encoder thread computes the codes the back end would: the same proposals, registrations
    and graph. It takes over once the PCA warm-up has ended (before, there are no codebooks to
    encode with) and the back end then runs no backbone of its own."""
    a, b = sequential.result, encoded_ahead.result
    assert encoded_ahead.pipeline.config.pipeline.encodes_ahead
    assert len(a.keyframes) == len(b.keyframes) == FRAMES // 2 and a.rear_keyframes == b.rear_keyframes
    np.testing.assert_array_equal(a.odometry, b.odometry)
    assert any(r.in_graph for r in a.loops)
    assert [(r.proposal, r.factor_handle) for r in a.loops] == [(r.proposal, r.factor_handle) for r in b.loops]
    np.testing.assert_array_equal(a.optimised, b.optimised)
    warmup = encoded_ahead.pipeline.config.detector.pca_warmup_keyframes
    ahead = [row["backbone_ahead"] > 0.0 for row in b.timings]
    # the encoder passed at most the two keyframes in its hands on before the warm-up ended
    assert not any(ahead[:warmup]) and all(ahead[warmup + 2 :])
    assert not any(row["backbone_ahead"] for row in a.timings)  # sequential: the back end's own pass
    inline = np.median([row["backbone"] for row in a.timings[warmup:]])
    waited = np.median([row["backbone"] for row in b.timings[warmup:]])
    assert waited < 0.5 * inline  # the back end only takes the codes (or waits for the rest of them)


@pytest.fixture(scope="module")
def gpu_search(weights_path: Path, frames: list[Frame], backbone: object) -> Run:
    """Stage I as `exact_backend: auto` searches on a GPU: torch products from a float16 copy
    (on the CPU device here, the float16 values widened for the product)."""
    cfg = _config(weights_path, overlap=False)
    cfg.vpr.filtering.exact_backend, cfg.vpr.filtering.torch_device = "torch", "cpu"
    cfg.vpr.filtering.torch_storage = "float16"
    return _run(cfg, frames, backbone)


def test_the_gpus_stage_one_search_streams_the_same_loops(sequential: Run, gpu_search: Run) -> None:
    """Keyframes appended one at a time, exclusion windows, rear camera: the torch search from a
    float16 copy proposes, the exact re-scoring decides, so the loops and trajectory are faiss's."""
    index = gpu_search.pipeline.system.detector.database.search_index()
    assert (index.search_device, index.search_storage) == ("cpu", "float16")
    assert sequential.pipeline.system.detector.database.search_index().search_device is None  # faiss
    a, b = sequential.result, gpu_search.result
    assert any(r.in_graph for r in a.loops)
    assert [(r.proposal, r.factor_handle, r.dropped) for r in a.loops] == [(r.proposal, r.factor_handle, r.dropped)
                                                                            for r in b.loops]  # fmt: skip
    np.testing.assert_array_equal(a.optimised, b.optimised)


def test_keyframes_keep_bounded_grey_copies_and_thumbnails_not_the_images(sequential: Run, frames: list[Frame]) -> None:
    """The simulator's 320 x 240 RGB images (230 kB each) are kept as a grey PNG copy within the
    pixel budget, the rear one too (no scan here), and a JPEG thumbnail of 160 px."""
    for kf in sequential.result.keyframes:
        frame = frames[kf.frame_index]
        for kept, full in ((kf.image, frame.image), (kf.rear_image, frame.rear_image)):
            assert isinstance(kept, ReducedImage) and kept.gray.shape == (240, 320)  # 76800 px: the budget
            assert (kept.full_width, kept.full_height) == (320, 240) and kept.nbytes < 320 * 240
            assert kept.nbytes < full.nbytes / 3
        assert kf.thumbnail is not None and len(kf.thumbnail) < 12_000
        assert kf.nbytes < 150_000
    assert all(not isinstance(v, np.ndarray) or v.size <= 16 for kf in sequential.result.keyframes
               for v in vars(kf).values())  # no image array at all, only the poses  # fmt: skip


def test_a_smaller_budget_keeps_smaller_copies_and_no_thumbnail_without_mcap(
    weights_path: Path, frames: list[Frame], backbone: object
) -> None:
    cfg = _config(weights_path, overlap=True, keyframe_image_pixels=19200)
    cfg.results.mcap = False
    run = _run(cfg, frames[:20], backbone)
    for kf in run.result.keyframes:
        assert kf.image is not None and kf.image.gray.shape == (120, 160) and kf.image.scale == (0.5, 0.5)
        assert kf.thumbnail is None


class _FailingOdometry:
    """Logged odometry that raises on one frame: a front-end failure in the producer thread."""

    def __init__(self, inner: object, fail_at: int) -> None:
        self.inner, self.fail_at, self.calls = inner, fail_at, 0

    def update(self, frame: Frame):
        self.calls += 1
        if self.calls == self.fail_at:
            raise RuntimeError("odometry broke")
        return self.inner.update(frame)  # type: ignore[attr-defined]


@pytest.mark.parametrize(("overlap", "encode_ahead"), [(False, False), (True, False), (True, True)])
def test_a_front_end_failure_ends_the_run_with_the_frames_before_it(
    weights_path: Path, frames: list[Frame], backbone: object, overlap: bool, encode_ahead: bool
) -> None:
    cfg = _config(weights_path, overlap=overlap, encode_ahead=encode_ahead)
    odometry = _FailingOdometry(make_odometry(cfg.frontend.odometry), fail_at=41)  # after the PCA warm-up
    pipeline = SlamPipeline.build(cfg, odometry, backbone)  # type: ignore[arg-type]
    state = pipeline.run(iter(frames))
    assert isinstance(pipeline.step_error, RuntimeError) and "odometry broke" in str(pipeline.step_error)
    assert state.frames_seen == 41 and len(state.keyframes) == 20  # frames 0, 2, ..., 38
    assert pipeline.ending.error is not None and pipeline.finish().keyframes == tuple(state.keyframes)


class _BackboneFailingOn:
    """The backbone, failing on the batch that holds one image (a keyframe the backbone cannot
    take): whether it is encoded ahead or by the back end."""

    def __init__(self, backbone: object, image: np.ndarray) -> None:
        self.backbone, self.image, self.failed_in = backbone, image, set[str]()

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if any(np.array_equal(image, self.image) for image in images):
            self.failed_in.add(threading.current_thread().name)
            raise RuntimeError("backbone broke")
        return self.backbone(images)  # type: ignore[operator]

    def __getattr__(self, name: str):  # noqa: ANN204
        if name == "backbone":
            raise AttributeError(name)
        return getattr(self.backbone, name)


@pytest.mark.parametrize("encode_ahead", [False, True])
def test_a_keyframe_the_backbone_fails_on_ends_the_run_in_its_turn(
    weights_path: Path, frames: list[Frame], backbone: object, encode_ahead: bool
) -> None:
    """Encoded ahead, a keyframe the backbone fails on still fails in its turn, after the ones
    before it were recognised, and the run keeps them, as without the encoder's thread."""
    cfg = _config(weights_path, overlap=True, encode_ahead=encode_ahead)
    pipeline = SlamPipeline.build(cfg, make_odometry(cfg.frontend.odometry), backbone)  # type: ignore[arg-type]
    detector = pipeline.system.detector
    image = detector.encoder.prepare(frames[50].image)  # keyframe 25, after the PCA warm-up
    failing = detector.encoder.backbone = _BackboneFailingOn(backbone, image)
    state = pipeline.run(iter(frames))
    assert isinstance(pipeline.step_error, RuntimeError) and str(pipeline.step_error) == "backbone broke"
    assert len(state.keyframes) == 26 and len(pipeline.finish().keyframes) == 26  # 0..25, the last failed
    assert failing.failed_in == ({"slam-encoder", "MainThread"} if encode_ahead else {"MainThread"})


@pytest.mark.parametrize("encode_ahead", [False, True])
def test_a_back_end_failure_stops_the_producer(
    weights_path: Path, frames: list[Frame], backbone: object, encode_ahead: bool
) -> None:
    cfg = _config(weights_path, overlap=True, encode_ahead=encode_ahead)
    pipeline = SlamPipeline.build(cfg, make_odometry(cfg.frontend.odometry), backbone)  # type: ignore[arg-type]
    back = pipeline.system.back
    read: list[int] = []

    def failing_back(item):
        back(item)
        if item.keyframe.id == 20:  # e.g. the pose graph failing once the keyframe is in (after the warm-up)
            raise ValueError("back end broke")

    def source() -> Iterator[Frame]:
        for frame in frames:
            read.append(frame.index)
            yield frame

    pipeline.system.back = failing_back  # type: ignore[method-assign]
    state = pipeline.run(source())
    assert isinstance(pipeline.step_error, ValueError) and len(state.keyframes) == 21  # 0..20, the last failed
    assert state.frames_seen == 41  # the counts of the failed keyframe's frame, not the producer's
    # it stopped reading soon after: two frames a keyframe queued or in the producer's hand (and
    # in the encoder's: one queued, one in its hand), and the frames the source read ahead (those
    # queued and one in the reader's hand)
    ahead = cfg.pipeline.read_ahead_frames + 1
    keyframes_ahead = cfg.pipeline.overlap_queue_keyframes + 2 + (2 if encode_ahead else 0)
    assert len(read) <= 41 + 2 * keyframes_ahead + ahead
    assert not [t.name for t in threading.enumerate() if t.name.startswith("slam-")]  # every stage's thread ended


@pytest.mark.parametrize("read_ahead", [0, 2])
def test_a_source_failure_keeps_the_frames_before_it_read_ahead_or_not(
    weights_path: Path, frames: list[Frame], backbone: object, read_ahead: int
) -> None:
    """A log cut short ends an overlapped run after the frames before the cut, whether its frames
    were read ahead in a thread of their own or in the front end's."""
    cfg = _config(weights_path, overlap=True, read_ahead_frames=read_ahead)
    pipeline = SlamPipeline.build(cfg, make_odometry(cfg.frontend.odometry), backbone)  # type: ignore[arg-type]
    readers: set[str] = set()

    def source() -> Iterator[Frame]:
        for frame in frames[:21]:
            readers.add(threading.current_thread().name)
            yield frame
        raise FrontendInputError("cut.mcap: truncated after 21 frames")

    state = pipeline.run(source())
    assert readers == {"slam-read-ahead" if read_ahead else "slam-front-end"}
    assert pipeline.step_error is None and pipeline.ending.source_error == "cut.mcap: truncated after 21 frames"
    assert state.frames_seen == 21 and len(state.keyframes) == 11  # frames 0, 2, ..., 20
