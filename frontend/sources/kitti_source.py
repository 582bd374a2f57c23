"""A KITTI odometry sequence folder (``dataset/sequences/XX``) as Frames.

Layout: ``times.txt`` (required), ``image_2/*.png`` (colour) or ``image_0/*.png`` (grey),
``velodyne/*.bin`` (float32 x, y, z, intensity), optional ``calib.txt`` and ground truth
from ``poses_file`` or ``poses/XX.txt`` (searched beside and two levels above the folder).

KITTI ground truth is the pose of camera 0 in the frame of camera 0 at the first scan.
With ``gt_frame="lidar"`` (the default when scans are read) it is moved to the LiDAR frame,
``T_lidar = Tr^-1 @ T_cam @ Tr``, where ``Tr`` (from ``calib.txt``) maps LiDAR points into
camera 0: exactly what kiss-icp's poses are comparable to. Without ``calib.txt``, ``Tr``
is taken as the identity (the gt is then the camera trajectory, labelled as LiDAR).
The camera's K is the left 3x3 of its projection matrix in ``calib.txt`` (``P2`` for image_2,
``P0`` for image_0), for images of the first image's size.
KITTI logs carry no odometry, so ``logged_pose`` is None; use ``pose_source="gt"`` for
logged-pose odometry. Scans carry no per-point times (KITTI scans are already deskewed).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from frontend.config import KittiSourceConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources.base import Source
from frontend.sources.clock import StreamClock, read_times
from frontend.sources.image_file import read_rgb
from frontend.sources.intrinsics import CameraIntrinsics
from ssmvpr_common.image_folders import image_files, pair_by_number
from ssmvpr_common.poses import KITTI_COLUMNS, pose_from_kitti_row, pose_problem
from ssmvpr_common.text_files import read_text
from ssmvpr_common.trajectory_io import read_kitti

log = logging.getLogger("frontend.sources.kitti")

KITTI_POINT_COLUMNS = 4  # x, y, z, intensity
CAMERA_FOLDERS = ("image_2", "image_0")
CALIB_TOLERANCE = 1e-3
"""max |R^T R - I| of calib.txt's Tr (a reflection is refused whatever the tolerance): KITTI prints it to 12 digits (its rotations are
orthonormal to ~1e-7); a Tr typed in by hand with 4 decimals still passes."""


def read_velodyne(path: Path) -> np.ndarray:
    """Nx3 float64 points of a KITTI ``.bin`` scan (intensity dropped)."""
    record = KITTI_POINT_COLUMNS * np.dtype(np.float32).itemsize
    size = path.stat().st_size
    if size % record:
        raise FrontendInputError(f"{path}: {size} bytes is not a whole number of 16-byte points")
    raw = np.fromfile(path, dtype=np.float32)
    return raw.reshape(-1, KITTI_POINT_COLUMNS)[:, :3].astype(np.float64)


def read_calib_tr(path: Path) -> np.ndarray | None:
    """4x4 LiDAR->camera-0 transform from the ``Tr:`` line of ``calib.txt`` (None if absent).

    Tr must be rigid: its rotation orthonormal within `CALIB_TOLERANCE`, with no reflection
    (a scaled or singular Tr would scale or break the ground truth moved by it)."""
    if not path.is_file():
        return None
    text = read_text(path, FrontendInputError)
    for lineno, line in enumerate(text.splitlines(), start=1):
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            try:
                numbers = [float(v) for v in values.split()]
            except ValueError:
                raise FrontendInputError(f"{path}:{lineno}: non-numeric value in Tr") from None
            if len(numbers) != KITTI_COLUMNS or not np.all(np.isfinite(numbers)):
                raise FrontendInputError(f"{path}:{lineno}: Tr needs 12 finite values")
            tr = pose_from_kitti_row(np.array(numbers))
            problem = pose_problem(tr, CALIB_TOLERANCE)
            if problem is not None:
                raise FrontendInputError(f"{path}:{lineno}: Tr is not a rigid LiDAR->camera transform ({problem})")
            return tr
    return None


def read_calib_values(path: Path, key: str) -> list[str] | None:
    """The values after ``key:`` in ``calib.txt``, unparsed (None when the file or line is absent)."""
    if not path.is_file():
        return None
    for line in read_text(path, FrontendInputError).splitlines():
        name, _, values = line.partition(":")
        if name.strip() == key:
            return values.split()
    return None


class KittiSource(Source):
    """Frames of one KITTI odometry sequence, read lazily file by file."""

    def __init__(
        self,
        path: str | Path,
        config: KittiSourceConfig | None = None,
        pose_config: PoseFileConfig | None = None,
    ) -> None:
        super().__init__()
        self.path = Path(path)
        self.config = config or KittiSourceConfig()
        if not self.path.is_dir():
            raise FrontendInputError(f"{self.path}: KITTI sequence folder not found")
        if not (self.path / "times.txt").is_file():
            raise FrontendInputError(
                f"{self.path}: a KITTI sequence folder needs times.txt (one timestamp per frame); it has none"
            )
        self.times = read_times(self.path / "times.txt")
        self.camera_folder = self._camera_folder()
        self.images = image_files(self.path / self.camera_folder) if self.camera_folder else []
        velodyne = self.path / "velodyne"
        self.scans = sorted(velodyne.glob("*.bin")) if self.config.load_points and velodyne.is_dir() else []
        if not self.images and not self.scans:
            raise FrontendInputError(f"{self.path}: no images ({'/'.join(CAMERA_FOLDERS)}) and no velodyne/*.bin scans")
        self._image_at, self._extra_images = self._pair(self.images, self.camera_folder)
        self._scan_at, self._extra_scans = self._pair(self.scans, "velodyne")
        self.tr = read_calib_tr(self.path / "calib.txt")
        self.gt_frame = self._gt_frame()
        self.poses_path = self._poses_path()
        self.gt_poses = self._read_gt(pose_config)
        self._intrinsics: dict[str, CameraIntrinsics] | None = None  # read on first use

    def _camera_folder(self) -> str | None:
        choice = self.config.camera
        if choice == "none":
            return None
        if choice != "auto":
            if not (self.path / choice).is_dir():
                raise FrontendInputError(f"{self.path / choice}: camera folder not found")
            return choice
        return next((c for c in CAMERA_FOLDERS if (self.path / c).is_dir()), None)

    def _pair(self, files: list[Path], what: str | None) -> tuple[list[Path | None], list[Path]]:
        """Each frame's file by its number (``000030.png`` is frame 30: a missing file is a gap,
        never a shift); by position when the names are not frame numbers (counts must agree)."""
        if not files:
            return [], []
        paired = pair_by_number(files, len(self.times))
        if paired is not None:
            return paired
        if len(files) != len(self.times):
            raise FrontendInputError(
                f"{self.path / str(what)}: {len(files)} files but times.txt has {len(self.times)} lines"
            )
        return list(files), []

    def _gt_frame(self) -> str:
        if self.config.gt_frame != "auto":
            return self.config.gt_frame
        return "lidar" if self.scans else "camera"

    def _poses_path(self) -> Path | None:
        if self.config.poses_file is not None:
            path = Path(self.config.poses_file)
            if not path.is_file():
                raise FrontendInputError(f"{path}: poses file not found")
            return path
        name = f"{self.path.name}.txt"
        candidates = [
            self.path / "poses.txt",
            self.path / "poses" / name,
            self.path.parent.parent / "poses" / name,
        ]
        return next((p for p in candidates if p.is_file()), None)

    def _read_gt(self, pose_config: PoseFileConfig | None) -> np.ndarray | None:
        if self.poses_path is None:
            return None
        poses = read_kitti(self.poses_path, (pose_config or PoseFileConfig()).rotation_tolerance)
        if len(poses) != len(self.times):
            raise FrontendInputError(f"{self.poses_path}: {len(poses)} poses but times.txt has {len(self.times)} lines")
        if self.gt_frame == "lidar":
            tr = self.tr if self.tr is not None else np.eye(4)
            poses = np.linalg.inv(tr) @ poses @ tr
        return poses

    def _read(self, reader: Callable[[Path], np.ndarray], files: list[Path | None], index: int, what: str, reason: str):  # noqa: ANN202
        """One sensor file of a frame, or None (counted, first warned): the frame keeps the rest."""
        if not files:
            return None
        path = files[index]
        if path is None:
            self.stats.skip(
                f"missing_{what}",
                f"{self.path}: frame {index} (times.txt line {index + 1}) has no {what} file; "
                "the frame keeps its other sensors",
            )
            return None
        try:
            return reader(path)
        except (FrontendInputError, OSError, ValueError) as error:
            self.stats.skip(reason, f"{error}; file skipped")
            return None

    # ---------------------------------------------------------------- Source API

    @property
    def length(self) -> int:
        return len(self.times)

    @property
    def topics(self) -> dict[str, str]:
        topics = {}
        if self.images:
            topics["camera"] = str(self.path / str(self.camera_folder))
        if self.scans:
            topics["lidar"] = str(self.path / "velodyne")
        if self.poses_path is not None:
            topics["gt_pose"] = str(self.poses_path)
        return topics

    @property
    def intrinsics(self) -> dict[str, CameraIntrinsics]:
        """The camera's K from ``calib.txt`` (``P2`` for image_2, ``P0`` for image_0), read on
        first use; none without calib.txt or that line, a counted warning when it is unusable."""
        if self._intrinsics is None:
            self._intrinsics = {}
            found = self._read_intrinsics()
            if found is not None:
                self._intrinsics["camera"] = found
        return dict(self._intrinsics)

    def _read_intrinsics(self) -> CameraIntrinsics | None:
        if not self.images or self.camera_folder is None:
            return None
        calib, key = self.path / "calib.txt", f"P{self.camera_folder[-1]}"
        values = read_calib_values(calib, key)
        if values is None:
            return None
        try:
            projection = np.array([float(v) for v in values]).reshape(3, 4)
        except ValueError:
            self.calibration_warning("invalid_calibration", f"{calib}: {key} is not 12 numbers; calibration ignored")
            return None
        first = cv2.imread(str(self.images[0]), cv2.IMREAD_UNCHANGED)  # the size K is for
        height, width = first.shape[:2] if first is not None else (None, None)
        return self.calibration(projection[:, :3], width, height, f"{calib}: {key}")

    @property
    def description(self) -> str:
        calib = "calib Tr" if self.tr is not None else "no calib.txt (Tr = identity)"
        return (
            f"KITTI {self.path.name}: {len(self)} frames, {', '.join(self.topics)}; "
            f"gt in {self.gt_frame} frame, {calib}"
        )

    def __iter__(self) -> Iterator[Frame]:
        self.reset_stats()
        clock = StreamClock(self.stats, self.config.max_time_gap_s)
        for extra, what in ((self._extra_images, "image"), (self._extra_scans, "scan")):
            if extra:
                self.stats.warn(
                    f"unpaired_{what}",
                    f"{self.path}: {len(extra)} {what} file(s) numbered past times.txt's {len(self.times)} lines "
                    f"(first {extra[0].name}); ignored",
                )
        for index, timestamp in enumerate(self.times):
            if not clock.accept("frame", float(timestamp), f"{self.path}/times.txt line {index + 1}"):
                continue
            image = self._read(read_rgb, self._image_at, index, "image", "undecodable_image")
            points = self._read(read_velodyne, self._scan_at, index, "scan", "bad_lidar")
            if (self.images or self.scans) and image is None and points is None:
                continue  # nothing of this frame could be read
            gt_pose = None
            if self.gt_poses is not None:
                where = f"{self.poses_path} line {index + 1}"
                gt_pose = self.plausible_pose("gt_pose", self.gt_poses[index].copy(), float(timestamp), where)
            frame = Frame(
                index=self.stats.frames_yielded,
                timestamp=float(timestamp),
                image=image,
                points=points,
                gt_pose=gt_pose,
            )
            self.stats.frames_yielded += 1
            yield frame
