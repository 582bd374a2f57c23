"""Data sources: logged traverses in (MCAP, ROS 1 and ROS 2 bags, KITTI, image folders), and the MCAP writer."""

from frontend.sources.base import Source, SourceStats
from frontend.sources.factory import detect_kind, open_source
from frontend.sources.folder_source import FolderSource
from frontend.sources.kitti_source import KittiSource
from frontend.sources.mcap_source import McapSource
from frontend.sources.mcap_writer import McapFrameWriter, write_frames
from frontend.sources.rosbag_source import RosbagSource

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
