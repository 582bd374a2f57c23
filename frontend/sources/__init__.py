"""Data sources: logged traverses in (MCAP, KITTI, image folders), and the MCAP writer."""

from frontend.sources.base import Source, SourceStats
from frontend.sources.factory import detect_kind, open_source
from frontend.sources.folder_source import FolderSource
from frontend.sources.kitti_source import KittiSource
from frontend.sources.mcap_source import McapSource
from frontend.sources.mcap_writer import McapFrameWriter, write_frames

__all__ = [
    "FolderSource",
    "KittiSource",
    "McapFrameWriter",
    "McapSource",
    "Source",
    "SourceStats",
    "detect_kind",
    "open_source",
    "write_frames",
]
