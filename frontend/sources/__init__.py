"""Data sources: logged traverses in (MCAP, ROS 1 and ROS 2 bags, KITTI, image folders), and the MCAP writer."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ssmvpr_common.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from frontend.sources.base import Source, SourceStats
    from frontend.sources.factory import detect_kind, open_source
    from frontend.sources.folder_source import FolderSource
    from frontend.sources.kitti_source import KittiSource
    from frontend.sources.mcap_source import McapSource
    from frontend.sources.mcap_writer import McapFrameWriter, write_frames
    from frontend.sources.rosbag_source import RosbagSource

# names load their modules on first use: opening one kind of log loads only its reader,
# not every reader and the ROS libraries
_EXPORTS = {
    "Source": "frontend.sources.base",
    "SourceStats": "frontend.sources.base",
    "detect_kind": "frontend.sources.factory",
    "open_source": "frontend.sources.factory",
    "FolderSource": "frontend.sources.folder_source",
    "KittiSource": "frontend.sources.kitti_source",
    "McapSource": "frontend.sources.mcap_source",
    "McapFrameWriter": "frontend.sources.mcap_writer",
    "write_frames": "frontend.sources.mcap_writer",
    "RosbagSource": "frontend.sources.rosbag_source",
}
__all__ = [
    "FolderSource",
    "KittiSource",
    "McapFrameWriter",
    "McapSource",
    "RosbagSource",
    "Source",
    "SourceStats",
    "detect_kind",
    "open_source",
    "write_frames",
]

__getattr__ = lazy_exports("frontend.sources", _EXPORTS)
