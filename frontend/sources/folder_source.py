"""A folder of images, optionally with a TUM or KITTI poses file and a times file.

Images: ``image_dir`` or the first of ``images/``, ``image/``, ``rgb/``, ``image_2/``,
``image_0/`` or the folder itself holding image files, sorted by name. Times: ``times_file``
or ``times.txt`` (one per image); else the file names when they all parse as numbers
(``1305031102.175304.png``); else the TUM poses' times when there is one pose per image;
else ``index * frame_period_s``. Poses: ``poses_file`` or the first of ``poses.txt``,
``groundtruth.txt``, ``poses_tum.txt``, ``poses_kitti.txt``, ``gt.txt``, format detected.
TUM poses with real image times are matched by nearest time; otherwise poses pair with
images by index and the counts must agree.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from frontend.config import FolderSourceConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.poses_io import PoseFile, read_poses
from frontend.sources.base import Source
from frontend.sources.clock import StreamClock, read_times
from frontend.sources.image_file import read_rgb
from ssmvpr_common.image_folders import frame_number, image_files, pair_by_number

IMAGE_DIR_NAMES = ("images", "image", "rgb", "image_2", "image_0")
POSES_NAMES = ("poses.txt", "groundtruth.txt", "poses_tum.txt", "poses_kitti.txt", "gt.txt")
TIMES_NAME = "times.txt"
POSE_ROLES = {"gt": ("gt_pose",), "logged": ("logged_pose",), "both": ("gt_pose", "logged_pose")}


class FolderSource(Source):
    """Frames from an image folder (+ poses); images are read lazily."""

    def __init__(
        self,
        path: str | Path,
        config: FolderSourceConfig | None = None,
        pose_config: PoseFileConfig | None = None,
    ) -> None:
        super().__init__()
        self.path = Path(path)
        self.config = config or FolderSourceConfig()
        if not self.path.is_dir():
            raise FrontendInputError(f"{self.path}: image folder not found")
        self.image_dir = self._image_dir()
        self.images = image_files(self.image_dir)
        if not self.images:
            raise FrontendInputError(f"{self.image_dir}: no image files")
        self.poses_path = self._find(self.config.poses_file, POSES_NAMES, "poses file")
        self.pose_file: PoseFile | None = read_poses(self.poses_path, config=pose_config) if self.poses_path else None
        self.times_path = self._find(self.config.times_file, (TIMES_NAME,), "times file")
        self._unpaired: list[Path] = []  # images numbered past the last times/poses line
        self._gaps: list[int] = []  # lines (frames) with no image
        self.times, real_times = self._times()
        self.poses = self._match_poses(real_times)

    # ---------------------------------------------------------------- layout

    def _image_dir(self) -> Path:
        if self.config.image_dir is not None:
            folder = self.path / self.config.image_dir
            if not folder.is_dir():
                raise FrontendInputError(f"{folder}: image folder not found")
            return folder
        for name in IMAGE_DIR_NAMES:
            if (self.path / name).is_dir() and image_files(self.path / name):
                return self.path / name
        return self.path

    def _find(self, explicit: str | None, names: tuple[str, ...], what: str) -> Path | None:
        if explicit is not None:
            path = Path(explicit)
            path = path if path.is_absolute() or path.exists() else self.path / path
            if not path.is_file():
                raise FrontendInputError(f"{path}: {what} not found")
            return path
        return next((self.path / n for n in names if (self.path / n).is_file()), None)

    def _times(self) -> tuple[np.ndarray, bool]:
        """Per-image times, and whether they are real (usable to match TUM poses)."""
        count = len(self.images)
        if self.times_path is not None:
            times = read_times(self.times_path)
            lines = self._lines(len(times))
            if lines is None:
                raise FrontendInputError(
                    f"{self.times_path}: need {count} finite times (one per image), got {times.size}"
                )
            return times[lines], True
        try:
            stems = np.array([float(p.stem) for p in self.images])
            if np.all(np.isfinite(stems)) and np.all(np.diff(stems) > 0):
                return stems, True
        except ValueError:
            pass
        pose_file = self.pose_file
        if pose_file is not None and pose_file.timestamps is not None and len(pose_file.poses) == count:
            return np.array(pose_file.timestamps, dtype=np.float64), False
        return np.arange(count) * self.config.frame_period_s, False

    def _match_poses(self, real_times: bool) -> list[np.ndarray | None] | None:
        if self.pose_file is None:
            return None
        poses, stamps = self.pose_file.poses, self.pose_file.timestamps
        if stamps is not None and real_times:
            return self._nearest(stamps, poses)
        lines = self._lines(len(poses))
        if lines is None:
            raise FrontendInputError(
                f"{self.poses_path}: {len(poses)} poses for {len(self.images)} images "
                "(without timestamps to match, poses pair with images by index)"
            )
        return list(poses[lines])

    def _lines(self, lines: int) -> np.ndarray | None:
        """The line of a per-frame file (times, poses) each image pairs with: its position when the
        counts agree and the names are in step; its frame number (``000030.png`` is line 30) when
        names are frame numbers with a gap, so one missing image shifts nothing (the images
        numbered past the last line are dropped, told once); None when neither pairs them."""
        paired = pair_by_number(self.images, lines)
        if paired is None:
            return np.arange(lines) if lines == len(self.images) else None
        at, extra = paired
        self._gaps = [line for line, path in enumerate(at) if path is None]
        if extra:
            self._unpaired = extra
            self.images = [p for p in self.images if p not in extra]
            if not self.images:
                return None
        return np.array([frame_number(p) for p in self.images])

    def _nearest(self, stamps: np.ndarray, poses: np.ndarray) -> list[np.ndarray | None]:
        if len(stamps) == 0:
            return [None] * len(self.times)
        order = np.argsort(stamps)
        stamps, poses = stamps[order], poses[order]
        right = np.searchsorted(stamps, self.times).clip(0, len(stamps) - 1)
        left = (right - 1).clip(0)
        closer_left = np.abs(stamps[left] - self.times) <= np.abs(stamps[right] - self.times)
        pick = np.where(closer_left, left, right)
        within = np.abs(stamps[pick] - self.times) <= self.config.association_tolerance_s
        return [poses[i] if ok else None for i, ok in zip(pick, within)]

    # ---------------------------------------------------------------- Source API

    @property
    def length(self) -> int:
        return len(self.images)

    @property
    def topics(self) -> dict[str, str]:
        topics = {"camera": str(self.image_dir)}
        if self.poses_path is not None:
            for role in POSE_ROLES[self.config.pose_role]:
                topics[role] = str(self.poses_path)
        return topics

    @property
    def description(self) -> str:
        poses = "no poses"
        if self.pose_file is not None:
            poses = f"{self.pose_file.format} poses as {self.config.pose_role}"
        return f"image folder {self.image_dir}: {len(self)} images, {poses}"

    def __iter__(self) -> Iterator[Frame]:
        self.reset_stats()
        roles = POSE_ROLES[self.config.pose_role]
        clock = StreamClock(self.stats, self.config.max_time_gap_s)
        if self._unpaired:
            self.stats.warn(
                "unpaired_image",
                f"{self.image_dir}: {len(self._unpaired)} image(s) numbered past the times/poses lines "
                f"(first {self._unpaired[0].name}); ignored",
            )
        for line in self._gaps:
            self.stats.skip(
                "missing_image", f"{self.image_dir}: frame {line} has no image file (a gap in the numbering)"
            )
        for index, (path, time) in enumerate(zip(self.images, self.times)):
            if not clock.accept("frame", float(time), str(path)):
                continue
            try:
                image = read_rgb(path)
            except FrontendInputError as error:  # the image is all a folder frame has
                self.stats.skip("undecodable_image", f"{error}; frame skipped")
                continue
            pose = self.poses[index] if self.poses is not None else None
            if self.poses is not None and pose is None:
                self.stats.notes["unmatched_pose"] += 1
            where = f"{self.poses_path} at t={float(time):.6f}"
            kept = {
                role: self.plausible_pose(role, pose.copy(), float(time), where) if pose is not None else None
                for role in ("logged_pose", "gt_pose")
                if role in roles
            }
            frame = Frame(
                index=self.stats.frames_yielded,
                timestamp=float(time),
                image=image,
                logged_pose=kept.get("logged_pose"),
                gt_pose=kept.get("gt_pose"),
            )
            self.stats.frames_yielded += 1
            yield frame
