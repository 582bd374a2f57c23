"""KITTI odometry folders (tiny ones written here) and the KITTI -> MCAP converter."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from tool_module import load_tool

from frontend.config import KittiSourceConfig, SourceConfig
from frontend.errors import FrontendInputError
from frontend.odometry.logged import so3_exp
from frontend.sources import KittiSource, McapSource, detect_kind, open_source
from ssmvpr_common.trajectory_io import write_kitti

ROOT = Path(__file__).resolve().parents[2]
N = 4


def _tr() -> np.ndarray:
    tr = np.eye(4)
    tr[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # velodyne x-forward -> camera z-forward
    tr[:3, 3] = [-0.004, -0.076, -0.27]
    return tr


def _make_sequence(root: Path, calib: bool = True, rng_seed: int = 0) -> tuple[Path, dict]:
    rng = np.random.default_rng(rng_seed)
    seq = root / "dataset" / "sequences" / "05"
    for name in ("image_0", "image_2", "velodyne"):
        (seq / name).mkdir(parents=True)
    truth: dict = {"rgb": [], "points": [], "poses": []}
    for i in range(N):
        rgb = rng.integers(0, 256, (10, 12, 3), dtype=np.uint8)
        cv2.imwrite(str(seq / "image_2" / f"{i:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(seq / "image_0" / f"{i:06d}.png"), rgb[:, :, 0])
        scan = rng.normal(size=(100, 4)).astype(np.float32)
        scan.tofile(seq / "velodyne" / f"{i:06d}.bin")
        pose = np.eye(4)
        pose[:3, :3] = so3_exp([0, 0.1 * i, 0])
        pose[:3, 3] = [0.1 * i, 0, 1.0 * i]
        truth["rgb"].append(rgb)
        truth["points"].append(scan[:, :3].astype(np.float64))
        truth["poses"].append(pose)
    (seq / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(N)))
    if calib:
        values = " ".join(f"{v:.12e}" for v in _tr()[:3, :4].ravel())
        (seq / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {values}\n")
    (root / "dataset" / "poses").mkdir(parents=True)
    write_kitti(root / "dataset" / "poses" / "05.txt", np.stack(truth["poses"]))
    return seq, truth


def test_kitti_sequence_frames(tmp_path: Path) -> None:
    seq, truth = _make_sequence(tmp_path)
    assert detect_kind(seq) == "kitti"
    source = open_source(seq)
    assert isinstance(source, KittiSource) and len(source) == N
    assert set(source.topics) == {"camera", "lidar", "gt_pose"}
    assert "calib Tr" in source.description
    frames = list(source)
    tr = _tr()
    for i, frame in enumerate(frames):
        assert frame.index == i and frame.timestamp == pytest.approx(0.1 * i)
        assert np.array_equal(frame.image, truth["rgb"][i])  # image_2 preferred, RGB order
        np.testing.assert_array_equal(frame.points, truth["points"][i])
        assert frame.point_times is None and frame.logged_pose is None
        np.testing.assert_allclose(frame.gt_pose, np.linalg.inv(tr) @ truth["poses"][i] @ tr, atol=1e-6)
    assert source.stats.frames_yielded == N


def test_a_corrupt_file_drops_only_its_own_sensor(tmp_path: Path) -> None:
    """Streaming policy: a bad image keeps the frame's scan (and the other way round)."""
    seq, truth = _make_sequence(tmp_path)
    images = sorted((seq / "image_2").iterdir())
    images[1].write_bytes(b"not a png")
    scans = sorted((seq / "velodyne").iterdir())
    scans[2].write_bytes(b"\x00" * 10)  # not a whole number of points
    source = open_source(seq)
    frames = list(source)
    assert len(frames) == N
    assert frames[1].image is None and np.array_equal(frames[1].points, truth["points"][1])
    assert frames[2].points is None and np.array_equal(frames[2].image, truth["rgb"][2])
    assert source.stats.skipped == {"undecodable_image": 1, "bad_lidar": 1}


def test_kitti_grey_camera_and_camera_frame_gt(tmp_path: Path) -> None:
    seq, truth = _make_sequence(tmp_path)
    config = KittiSourceConfig(camera="image_0", gt_frame="camera", load_points=False)
    frames = list(KittiSource(seq, config))
    grey = truth["rgb"][1][:, :, :1]
    assert np.array_equal(frames[1].image, np.repeat(grey, 3, axis=2))
    assert frames[1].points is None
    np.testing.assert_allclose(frames[1].gt_pose, truth["poses"][1], atol=1e-6)


def test_kitti_without_calib_uses_identity(tmp_path: Path) -> None:
    seq, truth = _make_sequence(tmp_path, calib=False)
    source = KittiSource(seq)
    assert source.tr is None and "Tr = identity" in source.description
    np.testing.assert_allclose(list(source)[2].gt_pose, truth["poses"][2], atol=1e-6)


def test_kitti_errors_name_the_input(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    seq, _ = _make_sequence(tmp_path)
    (seq / "velodyne" / "000001.bin").write_bytes(b"\0" * 6)
    with caplog.at_level(logging.WARNING):
        list(KittiSource(seq))  # streaming: a counted, named skip
    assert any(re.search(r"000001\.bin: 6 bytes is not a whole number", r.getMessage()) for r in caplog.records)
    (seq / "velodyne" / "scan_x.bin").write_bytes(b"\0" * 16)  # a name that is no frame number: by position
    with pytest.raises(FrontendInputError, match=r"velodyne: 5 files but times.txt has 4 lines"):
        KittiSource(seq)
    (seq / "velodyne" / "scan_x.bin").unlink()
    with pytest.raises(FrontendInputError, match="poses file not found"):
        KittiSource(seq, KittiSourceConfig(poses_file=str(tmp_path / "nope.txt")))
    (seq / "times.txt").unlink()
    with pytest.raises(FrontendInputError, match=rf"^{re.escape(str(seq))}: a KITTI sequence folder needs times\.txt"):
        KittiSource(seq)


def test_files_pair_with_frames_by_number_not_position(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A gap (000001.png missing) with an extra file (000009.png) keeps the counts equal; frame 1
    must lose its image, not take frame 2's, and the extra file is ignored, both told."""
    seq, truth = _make_sequence(tmp_path)
    gap = seq / "image_2" / "000001.png"
    gap.rename(seq / "image_2" / "000009.png")
    source = KittiSource(seq, KittiSourceConfig(camera="image_2"))
    with caplog.at_level(logging.WARNING):
        frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2, 3]  # the scan still makes frame 1
    assert frames[1].image is None and frames[1].points is not None
    assert np.array_equal(frames[2].image, truth["rgb"][2]) and np.array_equal(frames[3].image, truth["rgb"][3])
    assert source.stats.skipped["missing_image"] == 1 and source.stats.notes["unpaired_image"] == 1
    messages = " ".join(r.getMessage() for r in caplog.records)
    assert "frame 1 (times.txt line 2) has no image file" in messages and "first 000009.png" in messages


def test_kitti_to_mcap_converter(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    seq, truth = _make_sequence(tmp_path)
    out = tmp_path / "seq05.mcap"
    tool = load_tool("kitti_to_mcap")
    assert tool.main([str(seq), str(out), "--max-frames", "3"]) == 0
    assert "wrote 3 frames" in capsys.readouterr().out
    source = open_source(out, SourceConfig(kind="auto"))
    assert isinstance(source, McapSource)
    frames = list(source)
    kitti = list(KittiSource(seq))
    assert len(frames) == 3
    for got, want in zip(frames, kitti):
        assert got.timestamp == pytest.approx(want.timestamp, abs=1e-9)
        assert np.array_equal(got.image, want.image)
        np.testing.assert_allclose(got.points, want.points, atol=1e-6)
        np.testing.assert_allclose(got.gt_pose, want.gt_pose, atol=1e-6)
    assert tool.main([str(tmp_path / "missing"), str(tmp_path / "x.mcap")]) == 2
    assert "error:" in capsys.readouterr().err


def test_a_ground_truth_line_far_off_is_skipped(tmp_path: Path) -> None:
    """A poses file line 1e5 m from its neighbours (a glitch, or a corrupt line) is a counted skip
    of that frame's ground truth, as in an MCAP log."""
    seq, truth = _make_sequence(tmp_path)
    poses = np.stack(truth["poses"])
    poses[1, :3, 3] += 1e5
    write_kitti(tmp_path / "dataset" / "poses" / "05.txt", poses)
    source = KittiSource(seq)
    frames = list(source)
    assert [f.gt_pose is None for f in frames] == [False, True, False, False]
    assert source.stats.skipped["implausible_gt_pose"] == 1 and all(f.image is not None for f in frames)
