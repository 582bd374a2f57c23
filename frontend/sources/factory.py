"""Pick the data source for a path, by suffix and folder contents (kiss-icp's factory style)."""

from __future__ import annotations

from pathlib import Path

from frontend.config import PoseFileConfig, SourceConfig
from frontend.errors import FrontendInputError
from frontend.sources.base import Source
from frontend.sources.folder_source import IMAGE_DIR_NAMES, FolderSource
from frontend.sources.kitti_source import CAMERA_FOLDERS, KittiSource
from frontend.sources.mcap_source import McapSource
from frontend.sources.rosbag_source import RosbagSource, is_rosbag
from ssmvpr_common.image_folders import image_files

MCAP_SUFFIX = ".mcap"


def detect_kind(path: Path) -> str:
    """``mcap``, ``rosbag``, ``kitti`` or ``folder`` for ``path``; FrontendInputError when none fits."""
    if path.is_file():
        if path.suffix.lower() == MCAP_SUFFIX:
            return "mcap"
        if is_rosbag(path):
            return "rosbag"
        raise FrontendInputError(f"{path}: not a .mcap or .bag file (or a ROS 2 bag, KITTI or image folder)")
    if not path.is_dir():
        raise FrontendInputError(f"{path}: no such file or folder")
    if is_rosbag(path):  # a ROS 2 bag folder (metadata.yaml; .db3 or .mcap storage)
        return "rosbag"
    if len(list(path.glob(f"*{MCAP_SUFFIX}"))) == 1:  # a folder holding one MCAP log
        return "mcap"
    has_camera = any((path / c).is_dir() for c in CAMERA_FOLDERS)
    if (path / "velodyne").is_dir() or ((path / "times.txt").is_file() and has_camera):
        return "kitti"
    if image_files(path) or any((path / name).is_dir() and image_files(path / name) for name in IMAGE_DIR_NAMES):
        return "folder"
    raise FrontendInputError(
        f"{path}: not recognised: expected a .mcap file, a ROS 1 .bag, a ROS 2 bag folder, a KITTI sequence folder "
        "(velodyne/, image_0/ or image_2/, times.txt) or a folder of images"
    )


def open_source(
    path: str | Path, config: SourceConfig | None = None, pose_config: PoseFileConfig | None = None
) -> Source:
    """The Source that reads ``path`` (``config.kind`` forces a kind; ``auto`` detects it)."""
    path = Path(path)
    config = config or SourceConfig()
    kind = detect_kind(path) if config.kind == "auto" else config.kind
    if kind == "mcap":
        if path.is_dir():
            bags = sorted(path.glob(f"*{MCAP_SUFFIX}"))
            if len(bags) != 1:
                raise FrontendInputError(f"{path}: expected one .mcap file, found {len(bags)}")
            path = bags[0]
        return McapSource(path, config.mcap, pose_config)
    if kind == "rosbag":
        return RosbagSource(path, config.mcap, pose_config)
    if kind == "kitti":
        return KittiSource(path, config.kitti, pose_config)
    return FolderSource(path, config.folder, pose_config)
