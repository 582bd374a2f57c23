"""A saved session as a prior map: its place database plus each place's pose and scan (or images).

A run writes its place database into the results folder; with the places' optimised poses
(in that session's map frame) and their down-sampled scans beside it, a later run given
``--map DIR`` can turn a recognised prior place into a loop factor against the fixed map.
A place without a scan (a camera-only run) keeps its grey keyframe images instead
(`KeptImages`), so a loop to it can still be verified by two views: by `map` between
sessions, by `run --map` against the map.
The manifest records the encoder settings, because codes from another backbone layer, input
size or cube layout are not comparable and would match nonsense.
"""

from __future__ import annotations

import copy
import io
import logging
import math
import zipfile
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from loopclosure.config import VPRConfig
from loopclosure.database import MANIFEST, PlaceDatabase
from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.atomic import atomic_write_bytes
from ssmvpr_common.poses import pose_problem
from ssmvpr_slam.backend.config import TwoViewConfig
from ssmvpr_slam.backend.two_view import ReducedImage

SCANS_FILE = "scans.npz"
IMAGES_FILE = "images.npz"
"""The kept grey images of the places without a scan (`KeptImages`), beside the scans."""
CAMERA_FIELDS = ("fx", "fy", "cx", "cy", "hfov_deg")
"""The two-view intrinsics settings a run registered its kept images with, saved per place."""
MAP_MANIFEST = "map.json"
"""A merged map's manifest (`ssmvpr-slam map`); its places are in its database/ folder."""
REAR_FOLDER = "rear"
"""Subfolder of a saved map holding its keyframes' rear-image codes (`detector.rear.keep_codes`)."""
POSE_TOLERANCE = {"map_pose": 1e-4, "gt_pose": 1e-3}
"""max |R^T R - I| of a place's saved poses (a reflection is refused whatever the tolerance): a map pose must pass the pose graph's default
`rotation_tolerance` to anchor a loop (a run saves it orthonormal to ~1e-12); ground truth is held to what the
sources accept (`PoseFileConfig.rotation_tolerance`)."""

log = logging.getLogger(__name__)
_V = TypeVar("_V")


def encoder_signature(vpr: VPRConfig) -> dict[str, Any]:
    """The settings that make two databases' codes comparable."""
    backbone = vpr.backbone
    return {
        "input_size": backbone.input_size,
        "preprocessing": backbone.preprocessing,
        "pre_relu": backbone.pre_relu,
        "stage1_layer": backbone.stage1_layer,
        "stage2_layer": backbone.stage2_layer,
        "stage1_cubes": vpr.filtering.cubes.model_dump(),
        "stage2_cubes": vpr.spatial.cubes.model_dump(),
    }


@dataclass
class KeptImages:
    """The grey keyframe images (`ReducedImage`) a session kept where it had no scan, forward and
    rear, by place, with the two-view intrinsics its run used for them (`CAMERA_FIELDS`, NaN where
    unset): two views of a place verify a loop to it only in the calibration they were taken in."""

    front: dict[int, ReducedImage] = field(default_factory=dict)
    rear: dict[int, ReducedImage] = field(default_factory=dict)
    cameras: dict[int, tuple[float, ...]] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.front or self.rear)

    @staticmethod
    def camera_of(config: TwoViewConfig) -> tuple[float, ...]:
        """A run's intrinsics settings as saved (NaN for those it left to the image size)."""
        return tuple(math.nan if (v := getattr(config, name)) is None else float(v) for name in CAMERA_FIELDS)

    def two_view(self, place: int, config: TwoViewConfig) -> TwoViewConfig:
        """`config` with the intrinsics the place's images were kept with (as it is where unknown)."""
        camera = self.cameras.get(place)
        if camera is None:
            return config
        update = {name: None if math.isnan(v) else v for name, v in zip(CAMERA_FIELDS, camera)}
        return config.model_copy(update=update)  # checked when loaded (`_cameras_of`)

    def moved(self, offset: int) -> KeptImages:
        """The same images with every place `offset` further on (a session's places in a merged map)."""
        return KeptImages(_shifted(self.front, offset), _shifted(self.rear, offset), _shifted(self.cameras, offset))

    def update(self, other: KeptImages) -> None:
        """Add `other`'s places (a prior map's, carried into the map a run grew from it)."""
        self.front.update(other.front)
        self.rear.update(other.rear)
        self.cameras.update(other.cameras)


def _shifted(by_place: dict[int, _V], offset: int) -> dict[int, _V]:
    return {place + offset: value for place, value in by_place.items()}


@dataclass
class PriorMap:
    """Places of an earlier session: codes (in `database`), map-frame poses and scans, and the
    kept images of the places without a scan."""

    database: PlaceDatabase
    poses: dict[int, np.ndarray] = field(default_factory=dict)
    scans: dict[int, np.ndarray] = field(default_factory=dict)
    gt_poses: dict[int, np.ndarray] = field(default_factory=dict)
    folder: Path | None = None
    rear: PlaceDatabase | None = None  # rear-image codes by keyframe id, where the session kept them
    images: KeptImages = field(default_factory=KeptImages)

    def session_starts(self) -> list[int]:
        """Places where another session of a merged map (`ssmvpr-slam map`) begins: no path runs
        from the place before to it."""
        places = self.database.places
        return [
            k for k in range(1, len(places)) if places[k].extra.get("session") != places[k - 1].extra.get("session")
        ]

    def rear_codes_by_keyframe(self) -> dict[int, int]:
        """Keyframe id -> row of `rear`, for the keyframes whose rear codes were kept."""
        return {} if self.rear is None else {info.frame_id: i for i, info in enumerate(self.rear.places)}

    def __len__(self) -> int:
        return len(self.database)

    def pose(self, place: int) -> np.ndarray | None:
        return self.poses.get(place)

    def neighbourhood(self, place: int, half_window: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """(scan, map pose) of the places around `place` that have both: a local map's parts."""
        out = []
        for p in range(place - half_window, place + half_window + 1):
            if p in self.scans and p in self.poses:
                out.append((self.scans[p], self.poses[p]))
        return out

    @classmethod
    def load(cls, folder: str | Path, vpr: VPRConfig) -> PriorMap:
        """Read a saved database folder (or a merged map's folder, whose database/ it reads);
        refuses one written with other encoder settings."""
        folder = Path(folder)
        if (folder / MAP_MANIFEST).is_file():
            folder = folder / "database"
        database = PlaceDatabase.load(folder)
        saved = database.extra.get("encoder")
        wanted = encoder_signature(vpr)
        if saved is None:  # written before databases were signed: cannot be checked
            log.warning("prior map %s records no encoder settings; assuming they match this configuration", folder)
        elif not isinstance(saved, dict):
            raise LoopClosureInputError(f"{folder / MANIFEST}: extra.encoder must be an object, got {saved!r}")
        elif saved != wanted:
            diff = sorted(k for k in wanted if saved.get(k) != wanted[k])
            raise LoopClosureInputError(
                f"prior map {folder}: encoded with other settings ({', '.join(diff)}); "
                "its places cannot be matched with this configuration"
            )
        poses: dict[int, np.ndarray] = {}
        gt: dict[int, np.ndarray] = {}
        for index, info in enumerate(database.places):
            for key, target in (("map_pose", poses), ("gt_pose", gt)):
                value = info.extra.get(key)
                if value is not None:
                    pose = _pose_of(value, folder / "places.json", index, key)
                    if not np.isnan(pose).all():  # all NaN marks a place without one
                        target[index] = pose
        if len(database) and not poses:  # nothing to anchor to; its codebooks would replace the run's
            raise LoopClosureInputError(
                f"prior map {folder}: none of its {len(database)} places has a map pose, so no loop to it "
                "can correct anything (a vpr-eval database?); pass a SLAM run's results/run_<stamp>/database"
            )
        rear = PlaceDatabase.load(folder / REAR_FOLDER) if (folder / REAR_FOLDER / MANIFEST).is_file() else None
        if rear is not None and not rear.codebooks.same_as(database.codebooks):
            raise LoopClosureInputError(f"{folder / REAR_FOLDER}: rear codes made with other codebooks than the map's")
        scans = _load_scans(folder / SCANS_FILE, len(database))
        return cls(database, poses, scans, gt, folder, rear, _load_images(folder / IMAGES_FILE, len(database)))


def save_map(
    folder: Path,
    database: PlaceDatabase,
    vpr: VPRConfig,
    poses: dict[int, np.ndarray],
    scans: dict[int, np.ndarray],
    gt_poses: dict[int, np.ndarray],
    images: KeptImages | None = None,
) -> None:
    """Write the database with each place's map pose (and ground truth), the scans and the
    kept images (none: no images file).

    Scans and images go first and the database's manifest last, so an interrupted save leaves
    either the previous map or the new one readable. The poses go into the saved place records
    only: the caller's database (a live run's, which keeps growing) is not changed.
    """
    folder.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    arrays = {f"p{place}": np.asarray(scan, np.float32) for place, scan in scans.items()}
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub reads the first keyword as allow_pickle
    atomic_write_bytes(folder / SCANS_FILE, buffer.getvalue())
    if images:
        atomic_write_bytes(folder / IMAGES_FILE, _images_npz(images))
    places = []
    for index, info in enumerate(database.places):
        extra = dict(info.extra)
        for key, source in (("map_pose", poses), ("gt_pose", gt_poses)):
            if index in source:  # a place without one keeps what its own session saved
                extra[key] = np.asarray(source[index], dtype=np.float64).ravel().tolist()
        places.append(replace(info, extra=extra))
    view = copy.copy(database)  # shares the code arrays (saving only reads them), not the place list
    view.places = places
    view.save(folder, extra={"encoder": encoder_signature(vpr)})


def _pose_of(value: Any, path: Path, index: int, key: str) -> np.ndarray:
    """A place's saved 4x4 pose (16 numbers, row-major); anything else names the place."""
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        pose = None
    if pose is None or pose.size != 16:
        shown = f"{pose.size} values" if pose is not None else repr(value)[:60]
        raise LoopClosureInputError(f"{path}: place {index}: {key} must be 16 numbers (a 4x4 pose), got {shown}")
    pose = pose.reshape(4, 4)
    if np.isnan(pose).all():  # a place without one
        return pose
    tolerance = POSE_TOLERANCE[key]
    problem = pose_problem(pose, tolerance)
    if problem is not None:
        raise LoopClosureInputError(f"{path}: place {index}: {key} is not a rigid pose ({problem})")
    return pose


def _load_scans(path: Path, num_places: int) -> dict[int, np.ndarray]:
    if not path.is_file():
        return {}
    try:
        with np.load(path, allow_pickle=False) as data:
            scans = {int(name[1:]): np.asarray(data[name], dtype=np.float64) for name in data.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        # a truncated .npz raises any of these, depending on where it was cut
        raise LoopClosureInputError(f"cannot read the prior map's scans {path}: {type(exc).__name__}: {exc}") from None
    bad = [p for p, s in scans.items() if not 0 <= p < num_places or s.ndim != 2 or s.shape[1] != 3]
    if bad:
        raise LoopClosureInputError(f"{path}: scans for unknown places or not Nx3: {bad[:5]}")
    bad = [p for p, s in scans.items() if not np.isfinite(s).all()]
    if bad:
        raise LoopClosureInputError(f"{path}: scans of places {bad[:5]} contain NaN or inf")
    return scans


def _images_npz(images: KeptImages) -> bytes:
    """`images.npz`: per camera (front, rear) the places, their full image sizes and each PNG as
    bytes; the places' intrinsics settings. Stored, not compressed: PNG bytes are already."""
    arrays: dict[str, np.ndarray] = {}
    for camera, kept in (("front", images.front), ("rear", images.rear)):
        places = sorted(kept)
        arrays[f"{camera}_places"] = np.array(places, dtype=np.int64)
        arrays[f"{camera}_sizes"] = np.array(
            [[kept[p].full_width, kept[p].full_height] for p in places], dtype=np.int64
        ).reshape(-1, 2)
        arrays.update({f"{camera}{p}": np.frombuffer(kept[p].png, np.uint8) for p in places})
    calibrated = sorted(images.cameras)
    arrays["camera_places"] = np.array(calibrated, dtype=np.int64)
    arrays["cameras"] = np.array([images.cameras[p] for p in calibrated], np.float64).reshape(-1, len(CAMERA_FIELDS))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub reads the first keyword as allow_pickle
    return buffer.getvalue()


def _load_images(path: Path, num_places: int) -> KeptImages:
    """The kept images of `images.npz` (none when there is no such file); a damaged or
    inconsistent file is refused in one line naming it."""
    if not path.is_file():
        return KeptImages()
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: np.asarray(data[name]) for name in data.files}
        kept = KeptImages(_images_of(arrays, "front"), _images_of(arrays, "rear"), _cameras_of(arrays))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        # a truncated .npz raises any of these, depending on where it was cut
        raise LoopClosureInputError(f"cannot read the prior map's images {path}: {type(exc).__name__}: {exc}") from None
    bad = sorted(p for d in (kept.front, kept.rear, kept.cameras) for p in d if not 0 <= p < num_places)
    if bad:
        raise LoopClosureInputError(f"{path}: images of unknown places: {bad[:5]}")
    return kept


def _images_of(arrays: dict[str, np.ndarray], camera: str) -> dict[int, ReducedImage]:
    """One camera's images; ValueError or KeyError naming what does not fit."""
    places, sizes = arrays[f"{camera}_places"], arrays[f"{camera}_sizes"]
    if places.ndim != 1 or sizes.shape != (len(places), 2) or not (sizes > 0).all():
        raise ValueError(f"{camera}: {len(places)} places with sizes of shape {sizes.shape} (need positive (n, 2))")
    out = {}
    for place, (width, height) in zip(places.tolist(), sizes.tolist()):
        png = arrays[f"{camera}{place}"]
        try:
            out[int(place)] = ReducedImage.from_png(png.astype(np.uint8, copy=False).tobytes(), width, height)
        except ValueError as exc:
            raise ValueError(f"{camera} image of place {place}: {exc}") from None
    return out


def _cameras_of(arrays: dict[str, np.ndarray]) -> dict[int, tuple[float, ...]]:
    places, cameras = arrays["camera_places"], arrays["cameras"]
    if places.ndim != 1 or cameras.shape != (len(places), len(CAMERA_FIELDS)):
        raise ValueError(f"intrinsics of shape {cameras.shape} for {len(places)} places")
    fx, fy, hfov = cameras[:, 0], cameras[:, 1], cameras[:, 4]
    if np.isinf(cameras).any() or (fx <= 0).any() or (fy <= 0).any() or not ((hfov > 0) & (hfov < 180)).all():
        raise ValueError("intrinsics: fx, fy positive or NaN (unset), cx, cy finite or NaN, hfov_deg in (0, 180)")
    return {int(p): tuple(float(v) for v in row) for p, row in zip(places.tolist(), cameras)}
