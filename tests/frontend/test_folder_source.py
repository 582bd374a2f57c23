"""Image folders with TUM / KITTI poses, the source factory, and the folder converter."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from tool_module import load_tool

from frontend.config import FolderSourceConfig, SourceConfig
from frontend.errors import FrontendInputError
from frontend.sources import FolderSource, McapSource, detect_kind, open_source
from ssmvpr_common.trajectory_io import write_kitti, write_tum

ROOT = Path(__file__).resolve().parents[2]


def _poses(n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n)
    return poses


def _images(folder: Path, names: list[str]) -> list[np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(len(names))
    images = []
    for name in names:
        rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        images.append(rgb)
    return images


def test_tum_poses_matched_by_time_from_file_names(tmp_path: Path) -> None:
    stamps = [1000.00, 1000.10, 1000.20, 1000.30]
    images = _images(tmp_path / "rgb", [f"{t:.6f}.png" for t in stamps])
    pose_times = np.array([999.995, 1000.105, 1000.25, 1000.298])  # 3rd is 50 ms off
    write_tum(tmp_path / "groundtruth.txt", pose_times, _poses(4))
    assert detect_kind(tmp_path) == "folder"
    source = open_source(tmp_path)
    assert isinstance(source, FolderSource) and len(source) == 4
    frames = list(source)
    assert [f.timestamp for f in frames] == pytest.approx(stamps)
    assert [f.gt_pose is not None for f in frames] == [True, True, False, True]
    assert frames[3].gt_pose[0, 3] == 3 and frames[1].logged_pose is None
    assert source.stats.notes["unmatched_pose"] == 1
    assert np.array_equal(frames[2].image, images[2])


def test_kitti_poses_by_index_with_times_file(tmp_path: Path) -> None:
    _images(tmp_path / "images", [f"{i:04d}.jpg" for i in range(3)])
    write_kitti(tmp_path / "poses.txt", _poses(3))
    (tmp_path / "times.txt").write_text("5.0\n5.5\n6.0\n")
    source = FolderSource(tmp_path, FolderSourceConfig(pose_role="both"))
    frames = list(source)
    assert [f.timestamp for f in frames] == [5.0, 5.5, 6.0]
    assert all(np.array_equal(f.gt_pose, f.logged_pose) for f in frames)
    assert set(source.topics) == {"camera", "gt_pose", "logged_pose"}


def test_plain_folder_uses_frame_period_and_tum_times(tmp_path: Path) -> None:
    _images(tmp_path, ["a.png", "b.png", "c.png"])
    frames = list(FolderSource(tmp_path, FolderSourceConfig(frame_period_s=0.5)))
    assert [f.timestamp for f in frames] == [0.0, 0.5, 1.0]
    assert all(f.gt_pose is None for f in frames)
    write_tum(tmp_path / "poses.txt", np.array([7.0, 8.0, 9.0]), _poses(3))
    frames = list(FolderSource(tmp_path, FolderSourceConfig(pose_role="logged")))
    assert [f.timestamp for f in frames] == [7.0, 8.0, 9.0]
    assert frames[2].logged_pose[0, 3] == 2


def test_folder_errors(tmp_path: Path) -> None:
    _images(tmp_path / "images", ["0.png", "1.png"])
    write_kitti(tmp_path / "poses.txt", _poses(3))
    with pytest.raises(FrontendInputError, match=r"poses\.txt: 3 poses for 2 images"):
        FolderSource(tmp_path)
    (tmp_path / "poses.txt").unlink()
    (tmp_path / "times.txt").write_text("1.0\n")
    with pytest.raises(FrontendInputError, match=r"times\.txt: need 2 finite times"):
        FolderSource(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FrontendInputError, match="empty: no image files"):
        FolderSource(empty)
    with pytest.raises(FrontendInputError, match="not recognised"):
        open_source(empty)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(FrontendInputError, match=r"notes\.txt: not a \.mcap or \.bag file"):
        open_source(tmp_path / "notes.txt")
    (tmp_path / "images" / "1.png").write_bytes(b"not a png")
    (tmp_path / "times.txt").unlink()
    source = FolderSource(tmp_path)  # streaming: a corrupt image is a counted skip
    frames = list(source)
    assert len(frames) == len(source.images) - 1 and source.stats.skipped["undecodable_image"] == 1


def test_folder_to_mcap_converter(tmp_path: Path) -> None:
    data = tmp_path / "trav"
    images = _images(data / "images", [f"{i}.png" for i in range(1, 4)])
    write_tum(data / "poses.txt", np.array([1.0, 2.0, 3.0]), _poses(3))
    tool = load_tool("folder_to_mcap")
    out = tmp_path / "bag" / "trav.mcap"
    assert tool.main([str(data), str(out), "--pose-role", "both", "--image-format", "png"]) == 0
    assert detect_kind(out.parent) == "mcap"  # a bag folder holding one .mcap
    source = open_source(out.parent, SourceConfig(kind="auto"))
    assert isinstance(source, McapSource)
    frames = list(source)
    assert [f.timestamp for f in frames] == [1.0, 2.0, 3.0]
    assert all(np.array_equal(f.image, im) for f, im in zip(frames, images))
    assert frames[2].logged_pose[0, 3] == pytest.approx(2) and frames[2].gt_pose[0, 3] == pytest.approx(2)


def test_a_pose_file_glitch_is_skipped_like_a_logged_one(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The jump check of MCAP odometry covers pose files too: a TUM line 1e5 m off for one
    frame is a counted skip of that pose (both roles), the frame keeps its image."""
    stamps = [10.0, 10.1, 10.2, 10.3, 10.4]
    _images(tmp_path / "rgb", [f"{t:.6f}.png" for t in stamps])
    poses = _poses(5)
    poses[2, 0, 3] = 1e5
    write_tum(tmp_path / "poses.txt", np.array(stamps), poses)
    source = FolderSource(tmp_path, FolderSourceConfig(pose_role="both"))
    with caplog.at_level("WARNING"):
        frames = list(source)
    assert [f.logged_pose is None for f in frames] == [False, False, True, False, False]
    assert [f.gt_pose is None for f in frames] == [False, False, True, False, False]
    assert all(f.image is not None for f in frames)
    assert source.stats.skipped == {"implausible_logged_pose": 1, "implausible_gt_pose": 1}
    assert "poses.txt at t=10.200000: pose jumped 1e+05 m in 0.1 s" in caplog.text


def test_images_pair_with_times_and_poses_by_frame_number(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """000002.png missing and 000005.png extra (counts equal): frame 3 keeps line 3's time and
    pose instead of taking line 2's; the gap is a counted skip and the extra image is ignored."""
    folder = tmp_path / "seq"
    (folder / "images").mkdir(parents=True)
    for number in (0, 1, 3, 4, 5):
        cv2.imwrite(str(folder / "images" / f"{number:06d}.png"), np.full((8, 8, 3), number * 10, np.uint8))
    (folder / "times.txt").write_text("".join(f"{0.5 * i}\n" for i in range(5)))
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, 0, 3] = np.arange(5)
    write_kitti(folder / "poses.txt", poses)
    source = FolderSource(folder)
    with caplog.at_level(logging.WARNING):
        frames = list(source)
    assert [f.timestamp for f in frames] == [0.0, 0.5, 1.5, 2.0]
    assert [f.gt_pose[0, 3] for f in frames] == [0.0, 1.0, 3.0, 4.0]
    assert [int(f.image[0, 0, 0]) for f in frames] == [0, 10, 30, 40]
    assert source.stats.skipped["missing_image"] == 1 and source.stats.notes["unpaired_image"] == 1
    assert "first 000005.png" in caplog.text and "frame 2 has no image file" in caplog.text


def test_unpadded_image_names_sort_as_numbers(tmp_path: Path) -> None:
    for number in (0, 1, 2, 10, 9):
        cv2.imwrite(str(tmp_path / f"{number}.jpg"), np.zeros((4, 4, 3), np.uint8))
    assert [p.stem for p in FolderSource(tmp_path).images] == ["0", "1", "2", "9", "10"]
