"""Checkpoints: a run killed (SIGKILL, power loss) keeps its work up to the last one.

Every `results.checkpoint_every_keyframes` keyframes or `results.checkpoint_every_s` seconds
the runner writes the run so far into its results folder::

    run_<stamp>/checkpoint -> checkpoint-000003     a link, switched atomically (os.replace)
    run_<stamp>/checkpoint-000003/
        odometry.tum, optimised.tum, ground_truth.tum   keyframe trajectories (iSAM2's estimate)
        loop_closures.csv                               the loop log so far
        database/                                       the place database: opens as `--map`
        config.yaml, keyframes.npz, detector.npz, images/, checkpoint.json (written last)
        images/kf000012.png, kf000012_rear.png, kf000012_thumb.jpg   what the keyframes keep

A version folder is complete before the link points at it, so a kill at any moment leaves the
previous checkpoint or the new one, never a mixture. `ssmvpr-slam run LOG --resume RUN_DIR`
continues from it, and `load_checkpoint(...).result` reads it as a partial `RunResult`.

What is saved and what is re-derived (the choice, and why):
- saved exactly: keyframes (poses, ground truth, scans, and the images they keep: the grey
  copies' PNG bytes and the JPEG thumbnails, written as they are held), loop records
  with their registrations and factor handles, the place database, and the detector's state
  (travelled distances, the sequence matchers' recent stage-II grids and score caches, the gate);
- re-derived: the pose graph, by repeating the run's calls in order (cheap: no backbone, no
  ICP); and the odometry, by replaying the frames already seen through it alone. kiss-icp's
  voxel map and adaptive threshold live in its C++ core with no serialisation API, so replay
  is the one way that works for every odometry; it costs an odometry pass, not a backbone pass.
- checkpoints start once the place database exists (after the PCA warm-up): the warm-up's raw
  feature cubes are megabytes per keyframe, and a kill before then loses only the warm-up.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import os
import shutil
import time
import zipfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NoReturn

import cv2
import numpy as np
import yaml

from loopclosure.database import PlaceDatabase
from loopclosure.detector import LoopProposal
from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.atomic import atomic_write_bytes, atomic_write_text
from ssmvpr_common.text_files import read_text
from ssmvpr_slam.backend.kept_scan import KeptScan
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.backend.noise import check_sigmas
from ssmvpr_slam.backend.se3 import DEFAULT_ROTATION_TOLERANCE, as_pose
from ssmvpr_slam.backend.two_view import ReducedImage
from ssmvpr_slam.config import ResultsConfig, SlamConfig
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.run_folder import RunFolder, switch_link
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult, StreamEnd, frozen_array
from ssmvpr_slam.writers import prior_gt, write_config, write_database, write_loop_csv, write_trajectories

log = logging.getLogger(__name__)

FORMAT = "ssmvpr-slam-checkpoint"
FORMAT_VERSION = 3  # 2: keyframes keep grey PNG copies and JPEG thumbnails, float32 scans; 3: int16 cm scans
LINK = "checkpoint"
META = "checkpoint.json"
_PREFIX = "checkpoint-"


class CheckpointError(SlamError, ValueError):
    """A checkpoint that cannot be read or resumed (the message names the file or the log)."""


# --------------------------------------------------------------------------- fingerprints


def log_fingerprint(path: str | Path) -> dict[str, Any]:
    """What identifies a log cheaply: its size and the hash of its first and last MiB (a file),
    or its files' names and sizes (a folder, e.g. KITTI). A resume refuses another log."""
    path = Path(path)
    digest = hashlib.sha256()
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        for p in files:
            digest.update(f"{p.relative_to(path)}\0{p.stat().st_size}\n".encode())
        return {"kind": "folder", "files": len(files), "sha256": digest.hexdigest()}
    size = path.stat().st_size
    with open(path, "rb") as handle:
        digest.update(handle.read(1 << 20))
        handle.seek(max(0, size - (1 << 20)))
        digest.update(handle.read(1 << 20))
    return {"kind": "file", "size": size, "sha256": digest.hexdigest()}


# --------------------------------------------------------------------------- writing


@dataclass(frozen=True)
class CheckpointMeta:
    """What a resume needs besides the run's state: the log, the prior map, the odometry."""

    log: str
    log_fingerprint: dict[str, Any]
    prior_map: str | None
    name: str


def write_checkpoint(
    run_folder: Path,
    partial: RunResult,
    detector_state: dict[str, np.ndarray],
    config: SlamConfig,
    meta: CheckpointMeta,
) -> Path:
    """Write the run so far as a new checkpoint version, then point `checkpoint` at it."""
    previous = _current(run_folder)
    number = 1 + max([_number(p) for p in run_folder.glob(f"{_PREFIX}*")] or [0])
    folder = run_folder / f"{_PREFIX}{number:06d}"
    folder.mkdir()
    try:
        _write_version(folder, previous, partial, detector_state, config, meta)
    except BaseException:  # a full disk: the half-written version goes, so the space it took is free
        shutil.rmtree(folder, ignore_errors=True)  # for the next checkpoint; the last good one stays linked
        raise
    switch_link(run_folder / LINK, folder.name)
    for old in run_folder.glob(f"{_PREFIX}*"):  # earlier versions, and any a kill left half written
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    return folder


def _write_version(
    folder: Path,
    previous: Path | None,
    partial: RunResult,
    detector_state: dict[str, np.ndarray],
    config: SlamConfig,
    meta: CheckpointMeta,
) -> None:
    write_trajectories(folder, partial)
    write_loop_csv(folder / "loop_closures.csv", partial.keyframes, partial.loops, prior_gt(partial))
    write_config(folder, config)
    write_database(folder / "database", partial, config, poses=partial.in_map_frame)
    _write_images(folder / "images", partial.keyframes, previous)
    atomic_write_bytes(folder / "keyframes.npz", _npz(_keyframe_arrays(partial)))
    atomic_write_bytes(folder / "detector.npz", _npz(detector_state))
    record = {
        "format": FORMAT, "version": FORMAT_VERSION, "written": time.strftime("%Y-%m-%dT%H:%M:%S"),
        **asdict(meta), "frames_seen": partial.frames_seen, "frames_skipped": dict(partial.frames_skipped),
        "rear_keyframes": partial.rear_keyframes, "seconds": partial.ending.seconds,
        "keyframes": len(partial.keyframes), "timings": [dict(r) for r in partial.timings],
        "loops": [_loop_dict(r) for r in partial.loops],
        "config_sha256": hashlib.sha256((folder / "config.yaml").read_bytes()).hexdigest(),
    }  # fmt: skip
    atomic_write_text(folder / META, json.dumps(record, indent=1, allow_nan=True) + "\n")
    _fsync_dir(folder)


def _current(run_folder: Path) -> Path | None:
    link = run_folder / LINK
    return link.resolve() if link.is_symlink() and (link / META).is_file() else None


def _number(path: Path) -> int:
    try:
        return int(path.name.removeprefix(_PREFIX))
    except ValueError:
        return 0


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _npz(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub reads the first keyword as allow_pickle
    return buffer.getvalue()


def _image_files(kf: Keyframe) -> list[tuple[str, bytes]]:
    """(file name, bytes) of what the keyframe keeps: its encoded images, as they are held."""
    out = []
    if kf.image is not None:
        out.append((f"kf{kf.id:06d}.png", kf.image.png))
    if kf.rear_image is not None:
        out.append((f"kf{kf.id:06d}_rear.png", kf.rear_image.png))
    if kf.thumbnail is not None:
        out.append((f"kf{kf.id:06d}_thumb.jpg", kf.thumbnail))
    return out


def _write_images(folder: Path, keyframes: tuple[Keyframe, ...], previous: Path | None) -> None:
    """The keyframes' images, byte for byte as held (PNG, JPEG: nothing is re-encoded, so a
    resume is exact); a file the previous version holds is hard-linked, so each keyframe's
    images are written once over the whole run."""
    folder.mkdir()
    for kf in keyframes:
        for name, data in _image_files(kf):
            earlier = previous / "images" / name if previous is not None else None
            if earlier is not None and earlier.is_file():
                try:
                    os.link(earlier, folder / name)
                    continue
                except OSError:  # a file system without hard links: write it again
                    pass
            atomic_write_bytes(folder / name, data)


def _keyframe_arrays(result: RunResult) -> dict[str, np.ndarray]:
    kfs = result.keyframes
    n = len(kfs)
    gt = np.full((n, 4, 4), np.nan)
    for i, k in enumerate(kfs):
        if k.gt_pose is not None:
            gt[i] = k.gt_pose
    scans = [k.scan for k in kfs]
    lengths = np.array([-1 if s is None else len(s) for s in scans], np.int64)
    held = [s.centimetres for s in scans if s is not None]
    stacked = np.concatenate(held) if held else np.zeros((0, 3), np.int16)

    def full_size(image: ReducedImage | None) -> tuple[int, int]:
        return (-1, -1) if image is None else (image.full_width, image.full_height)

    in_map = result.in_map_frame
    return {
        "ids": np.array([k.id for k in kfs], np.int64),
        "frame_index": np.array([k.frame_index for k in kfs], np.int64),
        "timestamps": np.array([k.timestamp for k in kfs], np.float64),
        "odometry": np.array(result.odometry, np.float64).reshape(n, 4, 4),
        "optimised": np.array(result.optimised, np.float64).reshape(n, 4, 4),
        "in_map_frame": np.full((n, 4, 4), np.nan) if in_map is None else np.array(in_map, np.float64),
        "gt_present": np.array([k.gt_pose is not None for k in kfs], bool),
        "gt": gt,
        "scan_lengths": lengths,
        "scans": stacked,  # int16 centimetres, unpacked (packing them again on resume is exact)
        "image_full_size": np.array([full_size(k.image) for k in kfs], np.int64).reshape(n, 2),
        "rear_image_full_size": np.array([full_size(k.rear_image) for k in kfs], np.int64).reshape(n, 2),
        "has_thumbnail": np.array([k.thumbnail is not None for k in kfs], bool),
    }


def _loop_dict(record: LoopRecord) -> dict[str, Any]:
    reg = record.registration
    registration = None
    if reg is not None:
        registration = {**asdict(reg), "T_mq": np.asarray(reg.T_mq).tolist(), "sigmas": np.asarray(reg.sigmas).tolist()}
    return {"proposal": asdict(record.proposal), "registration": registration, "factor_handle": record.factor_handle}


# --------------------------------------------------------------------------- the runner's side


class Checkpointer:
    """Decides when a checkpoint of `system` (a SlamSystem) is due and writes it; the runner
    calls `maybe` after every frame. seconds: the run's time before this session (a resume)."""

    def __init__(
        self, run: RunFolder, config: SlamConfig, meta: CheckpointMeta, system: Any, seconds: float = 0.0
    ) -> None:
        self.run = run
        self.config = config
        self.meta = meta
        self.system = system
        self.settings: ResultsConfig = config.results
        self._keyframes_at_last = len(system.state.keyframes)
        self._started = self._time_of_last = time.monotonic()
        self._seconds_before = seconds
        self.written = 0

    def due(self) -> bool:
        new = len(self.system.state.keyframes) - self._keyframes_at_last
        if new <= 0:
            return False
        every_kf, every_s = self.settings.checkpoint_every_keyframes, self.settings.checkpoint_every_s
        by_count = every_kf is not None and new >= every_kf
        by_time = every_s is not None and time.monotonic() - self._time_of_last >= every_s
        return by_count or by_time

    def maybe(self) -> Path | None:
        """Write a checkpoint if one is due and the system can be resumed from it."""
        if not self.due():
            return None
        return self.write()

    def write(self) -> Path | None:
        """Write a checkpoint now (a stop request: the run is resumable from where it stopped),
        if the system can be resumed from one; None when it cannot (the PCA warm-up) or failed."""
        state = self.system.detector_state()
        if state is None:  # still in the PCA warm-up: nothing a resume could start from
            return None
        seconds = self._seconds_before + time.monotonic() - self._started
        partial = self.system.partial_result(StreamEnd(interrupted=True, seconds=seconds))
        self._keyframes_at_last = len(partial.keyframes)
        self._time_of_last = time.monotonic()
        try:
            folder = write_checkpoint(self.run.ensure(), partial, state, self.config, self.meta)
        except OSError as exc:  # a safety net that fails (disk full) must not end the run itself
            log.error("checkpoint not written (%s); the run goes on, the previous checkpoint stays", exc)
            return None
        self.written += 1
        log.info("checkpoint %s: %d keyframes, %d frames", folder, len(partial.keyframes), partial.frames_seen)
        return folder


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Checkpoint:
    """A checkpoint as read back: the partial result, the detector's state, what resuming needs."""

    folder: Path  # the version folder
    run_folder: Path  # the run's results folder that holds it
    meta: CheckpointMeta
    result: RunResult  # the run so far (interrupted; iSAM2's estimate, no final pass)
    detector_state: dict[str, np.ndarray]
    config_text: str

    @property
    def config_path(self) -> Path:
        return self.folder / "config.yaml"


def find_checkpoint(path: str | Path) -> Path:
    """The checkpoint version folder for a run's results folder or a checkpoint folder. A run
    stopped by SIGTERM/SIGINT published its partial results beside the checkpoint it wrote as it
    stopped: it resumes from that checkpoint like a killed run."""
    path = Path(path)
    if (path / META).is_file():
        return path.resolve()  # the `checkpoint` link itself: its version folder
    if (path / LINK / META).is_file():
        return (path / LINK).resolve()
    if not path.exists():
        raise CheckpointError(f"{path}: no such results folder")
    if (path / "metrics.json").is_file():
        if _interrupted(path / "metrics.json"):
            raise CheckpointError(f"{path}: this run was stopped before its first checkpoint (during the PCA "
                                  "warm-up); nothing to resume: run the log again")  # fmt: skip
        raise CheckpointError(f"{path}: this run finished (metrics.json is there); nothing to resume")
    raise CheckpointError(f"{path}: no checkpoint here (no {LINK}/{META}); a run writes one after its PCA warm-up")


def _interrupted(metrics: Path) -> bool:
    try:
        return bool(json.loads(metrics.read_text(encoding="utf-8")).get("interrupted"))
    except (OSError, ValueError, AttributeError):
        return False


def carry_checkpoint(run_folder: Path | None, into: Path) -> bool:
    """Put the run's current checkpoint into `into` (the partial results of a stopped run, about
    to replace the run's folder) by hard links, so a resume still finds it; False when there is none."""
    current = None if run_folder is None else _current(run_folder)
    if current is None:
        return False
    shutil.copytree(current, into / current.name, copy_function=_link_or_copy)
    switch_link(into / LINK, current.name)
    return True


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system, or links refused: a copy
        shutil.copy2(source, target)


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint (`path`: the run's results folder or the checkpoint folder).

    Everything is checked before it is used: a damaged file (cut short, a field of the wrong
    type, NaN in a pose, ids out of order) is one CheckpointError naming the file and what is
    wrong, never a traceback from deep inside the restore or a silently wrong resumed run."""
    folder = find_checkpoint(path)
    record = _read_meta(folder / META)
    _check_record(folder / META, record)
    run_folder = folder.parent
    try:
        meta = CheckpointMeta(record["log"], record["log_fingerprint"], record["prior_map"], record["name"])
        config_text = read_text(folder / "config.yaml", CheckpointError)
        arrays = _load_npz(folder / "keyframes.npz")
        tolerance = _rotation_tolerance(config_text)
        n = _check_keyframe_arrays(folder / "keyframes.npz", arrays, record, tolerance)
        keyframes = _keyframes(arrays, folder / "images")
        loops = tuple(_loop_record(d) for d in record["loops"])
        detector_state = _load_npz(folder / "detector.npz")
        database = PlaceDatabase.load(folder / "database")
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, (CheckpointError, LoopClosureInputError)):
            raise
        raise CheckpointError(f"{folder / META}: not a usable checkpoint ({type(exc).__name__}: {exc})") from None
    except OSError as exc:
        raise CheckpointError(f"{folder}: cannot read the checkpoint ({exc})") from None
    _check_config(folder, record, config_text, database)
    prior_places = _prior_places(folder / "detector.npz", detector_state, len(database))
    _check_loops(folder / META, loops, n, prior_places, tolerance)
    for info in database.places[prior_places:]:  # the session's places: the poses are the checkpoint's, not the run's
        info.extra.pop("map_pose", None)
        info.extra.pop("gt_pose", None)
    in_map = arrays["in_map_frame"]
    result = RunResult(
        keyframes=keyframes,
        loops=loops,
        stamps=frozen_array(arrays["timestamps"]),
        odometry=frozen_array(arrays["odometry"]),
        optimised=frozen_array(arrays["optimised"]),
        in_map_frame=frozen_array(in_map) if np.isfinite(in_map).all() else None,
        frames_seen=record["frames_seen"],
        frames_skipped=dict(record["frames_skipped"]),
        rear_keyframes=record["rear_keyframes"],
        timings=tuple(record["timings"]),
        ending=StreamEnd(interrupted=True, seconds=float(record["seconds"])),
        database=database,
        session_places={database.places[i].frame_id: i for i in range(prior_places, len(database))},
    )
    return Checkpoint(folder, run_folder, meta, result, detector_state, config_text)


def _read_meta(path: Path) -> dict[str, Any]:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{path}: cannot read the checkpoint record ({exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a {FORMAT} record")
    if record.get("version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {record.get('version')}, this build reads {FORMAT_VERSION}"
        )
    return record


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # a file cut short is no zip archive
        raise CheckpointError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):  # a lone .npy array, or a pickle refused above
        raise CheckpointError(f"{path}: not an .npz archive of arrays")
    try:
        with data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:  # a damaged member
        raise CheckpointError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from None


# --------------------------------------------------------------------------- checks on reading


def _whole(value: object) -> bool:
    """A JSON whole number >= 0 (not a bool, not 3.0)."""
    return type(value) is int and value >= 0


def _finite(value: object) -> bool:
    """A JSON finite number (not a bool)."""
    return type(value) in (int, float) and math.isfinite(value)  # type: ignore[arg-type]


def _check_record(path: Path, record: dict[str, Any]) -> None:
    """The fields of checkpoint.json have the types the writer gives them."""

    def refuse(key: str, what: str) -> NoReturn:
        shown = repr(record[key]) if key in record else "nothing"
        raise CheckpointError(f"{path}: {key} must be {what}, got {shown[:60]}")

    for key in ("log", "name"):
        if not isinstance(record.get(key), str):
            refuse(key, "a string")
    if not isinstance(record.get("log_fingerprint"), dict):
        refuse("log_fingerprint", "an object")
    if "prior_map" not in record or not isinstance(record["prior_map"], (str, type(None))):
        refuse("prior_map", "a path or null")
    for key in ("frames_seen", "keyframes", "rear_keyframes"):
        if not _whole(record.get(key)):
            refuse(key, "a whole number >= 0")
    if record["rear_keyframes"] > record["keyframes"]:
        refuse("rear_keyframes", f"at most keyframes ({record['keyframes']})")
    if not (_finite(record.get("seconds")) and record["seconds"] >= 0):
        refuse("seconds", "a number >= 0")
    skipped = record.get("frames_skipped")
    if not (isinstance(skipped, dict) and all(_whole(v) for v in skipped.values())):
        refuse("frames_skipped", "an object of whole numbers >= 0")
    timings = record.get("timings")
    if not isinstance(timings, list):
        refuse("timings", "a list of objects (seconds per stage)")
    for i, row in enumerate(timings):
        if not (isinstance(row, dict) and row and all(_finite(v) for v in row.values())):
            raise CheckpointError(f"{path}: timings[{i}] must be an object of numbers (seconds per stage)")
        if row.keys() != timings[0].keys():
            raise CheckpointError(f"{path}: timings[{i}] has other stages than timings[0]")
    if not (isinstance(record.get("loops"), list) and all(isinstance(d, dict) for d in record["loops"])):
        refuse("loops", "a list of objects")


# name: (dtype kinds, shape per keyframe) of keyframes.npz, as `_keyframe_arrays` writes it
_KEYFRAME_ARRAYS: dict[str, tuple[str, tuple[int, ...]]] = {
    "ids": ("iu", ()),
    "frame_index": ("iu", ()),
    "timestamps": ("f", ()),
    "odometry": ("f", (4, 4)),
    "optimised": ("f", (4, 4)),
    "in_map_frame": ("f", (4, 4)),
    "gt_present": ("b", ()),
    "gt": ("f", (4, 4)),
    "scan_lengths": ("iu", ()),
    "image_full_size": ("iu", (2,)),
    "rear_image_full_size": ("iu", (2,)),
    "has_thumbnail": ("b", ()),
}


_KINDS = {"iu": "integer", "f": "float", "b": "bool"}


def _check_keyframe_arrays(path: Path, arrays: dict[str, np.ndarray], record: dict[str, Any], tolerance: float) -> int:
    """keyframes.npz holds every array, shaped for the keyframes checkpoint.json lists, with
    values a restore can use; returns the number of keyframes."""
    missing = [name for name in (*_KEYFRAME_ARRAYS, "scans") if name not in arrays]
    if missing:
        raise CheckpointError(f"{path}: lacks {', '.join(missing)}")
    if arrays["ids"].ndim != 1:
        raise CheckpointError(f"{path}: ids has shape {arrays['ids'].shape}, expected one id per keyframe")
    n = len(arrays["ids"])
    if record["keyframes"] != n:
        raise CheckpointError(f"{path.parent}: {META} lists {record['keyframes']} keyframes, {path.name} holds {n}")
    for name, (kinds, shape) in _KEYFRAME_ARRAYS.items():
        array = arrays[name]
        if array.dtype.kind not in kinds or array.shape != (n, *shape):
            raise CheckpointError(f"{path}: {name} is {array.dtype} {array.shape}, expected {_KINDS[kinds]} "
                                  f"{(n, *shape)}")  # fmt: skip
    frames_seen = record["frames_seen"]
    if not np.array_equal(arrays["ids"], np.arange(n)):
        raise CheckpointError(f"{path}: keyframe ids must be 0..{n - 1} in order, got {arrays['ids'][:8].tolist()}")
    frame_index = arrays["frame_index"]
    if n and (frame_index[0] < 0 or np.any(np.diff(frame_index) <= 0)):
        raise CheckpointError(f"{path}: frame_index must increase from 0 or more, keyframe by keyframe")
    if n and frame_index[-1] >= frames_seen:
        raise CheckpointError(f"{path}: keyframe {n - 1} is frame {frame_index[-1]}, but {META} says "
                              f"{frames_seen} frames were seen")  # fmt: skip
    if not np.isfinite(arrays["timestamps"]).all():
        raise CheckpointError(f"{path}: timestamps contain NaN or inf")
    for i in range(n):
        try:
            as_pose(f"odometry of keyframe {i}", arrays["odometry"][i], tolerance)
        except ValueError as exc:
            raise CheckpointError(f"{path}: {exc}") from None
    for name, rows in (("optimised", slice(None)), ("gt", arrays["gt_present"])):
        if not np.isfinite(arrays[name][rows]).all():
            raise CheckpointError(f"{path}: {name} poses contain NaN or inf")
    in_map = arrays["in_map_frame"]
    if not (np.isfinite(in_map).all() or np.isnan(in_map).all()):
        raise CheckpointError(f"{path}: in_map_frame must be all finite (anchored) or all NaN (not anchored)")
    lengths, scans = arrays["scan_lengths"], arrays["scans"]
    if np.any(lengths < -1):
        raise CheckpointError(f"{path}: scan_lengths must be -1 (no scan) or a point count")
    if scans.dtype != np.int16 or scans.ndim != 2 or scans.shape[1] != 3 or len(scans) != lengths[lengths > 0].sum():
        raise CheckpointError(f"{path}: scans is {scans.dtype} {scans.shape}, expected int16 "
                              f"({int(lengths[lengths > 0].sum())}, 3) as scan_lengths add up")  # fmt: skip
    for name in ("image_full_size", "rear_image_full_size"):
        sizes = arrays[name]
        none = (sizes == -1).all(axis=1)
        if not np.all(none | (sizes > 0).all(axis=1)):
            raise CheckpointError(f"{path}: {name} must be -1 -1 (no image) or a width and height > 0")
    return n


def _check_config(folder: Path, record: dict[str, Any], config_text: str, database: PlaceDatabase) -> None:
    """config.yaml must be the settings the database and the state were made with: a resume
    runs with it, and writes it into the results as the run's settings. Edited (its digest is not
    the one checkpoint.json recorded), or naming code sizes the database's codebooks do not have,
    it is refused (one line), never a resume whose config.yaml says what the run did not do."""
    path = folder / "config.yaml"
    digest = record.get("config_sha256")
    if digest is not None and hashlib.sha256(config_text.encode("utf-8")).hexdigest() != digest:
        raise CheckpointError(f"{path}: changed after the checkpoint was written (not the digest {META} "
                              "recorded); a resume runs with the settings its state was made with: restore the file")  # fmt: skip
    try:
        vpr = yaml.safe_load(config_text)["vpr"]
        dims = (int(vpr["filtering"]["pca"]["dim"]), int(vpr["spatial"]["pca"]["dim"]))
    except (yaml.YAMLError, KeyError, TypeError, ValueError):
        return  # a config.yaml without them is refused when it is loaded
    held = (database.codebooks.stage1.dim, database.codebooks.stage2.dim)
    if dims != held:
        raise CheckpointError(f"{path}: PCA dims {dims[0]}/{dims[1]} (vpr.filtering/spatial.pca.dim), but the "
                              f"checkpoint's database holds {held[0]}/{held[1]}-dim codes; restore the file")  # fmt: skip


def _rotation_tolerance(config_text: str) -> float:
    """The run's `backend.pose_graph.rotation_tolerance`: the poses a checkpoint holds passed it
    when the run added them, and the restore adds them again with it."""
    try:
        value = yaml.safe_load(config_text)["backend"]["pose_graph"]["rotation_tolerance"]
    except (yaml.YAMLError, KeyError, TypeError):  # a broken config.yaml is refused when it is loaded
        return DEFAULT_ROTATION_TOLERANCE
    return float(value) if _finite(value) and value > 0 else DEFAULT_ROTATION_TOLERANCE


def _prior_places(path: Path, state: dict[str, np.ndarray], places: int) -> int:
    """The detector state's count of prior-map places (the database's first ones)."""
    value = state.get("prior_places", np.array(0))
    if value.shape != () or value.dtype.kind not in "iu" or not 0 <= int(value) <= places:
        raise CheckpointError(f"{path}: prior_places must be a whole number from 0 to {places} (the database's "
                              f"places), got {value.tolist()!r}")  # fmt: skip
    return int(value)


def _check_loops(path: Path, loops: tuple[LoopRecord, ...], n: int, prior_places: int, tolerance: float) -> None:
    """Loop records a restore can replay: in query order, on the checkpoint's keyframes, and the
    factors (handles 0, 1, 2, ...) on accepted registrations that the graph takes again."""
    last_query, handles = 0, 0
    for i, record in enumerate(loops):
        p, reg = record.proposal, record.registration
        where = f"{path}: loops[{i}]"
        for name in ("query_id", "match_id", "match_place"):
            if not _whole(getattr(p, name)):
                raise CheckpointError(f"{where}: {name} must be a whole number >= 0, got {getattr(p, name)!r}")
        if type(p.accepted) is not bool or type(p.prior_map) is not bool:
            raise CheckpointError(f"{where}: accepted and prior_map must be true or false")
        if not last_query <= p.query_id < n:
            raise CheckpointError(f"{where}: query keyframe {p.query_id} is not one of the {n} keyframes "
                                  "in query order")  # fmt: skip
        last_query = p.query_id
        if record.factor_handle is None:
            continue
        if record.factor_handle != handles:
            raise CheckpointError(f"{where}: factor_handle is {record.factor_handle}, the graph would give {handles}")
        handles += 1
        if reg is None or reg.accepted is not True:
            raise CheckpointError(f"{where}: a loop factor without an accepted registration")
        if p.prior_map and p.match_place >= prior_places:
            raise CheckpointError(f"{where}: match_place {p.match_place} is not one of the {prior_places} "
                                  "prior-map places")  # fmt: skip
        if not p.prior_map and p.match_id >= p.query_id:
            raise CheckpointError(f"{where}: match keyframe {p.match_id} is not before query keyframe {p.query_id}")
        try:
            as_pose("T_mq", reg.T_mq, tolerance)
            check_sigmas("sigmas", reg.sigmas)
        except ValueError as exc:
            raise CheckpointError(f"{where}: {exc}") from None


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise CheckpointError(f"{path}: missing or unreadable ({exc.strerror})") from None


def _read_kept(path: Path, full_size: np.ndarray) -> ReducedImage | None:
    """A keyframe's grey copy as written (None where the keyframe kept none: size -1)."""
    width, height = (int(v) for v in full_size)
    if width < 0:
        return None
    try:
        return ReducedImage.from_png(_read_bytes(path), width, height)
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from None


def _read_thumbnail(path: Path) -> bytes:
    data = _read_bytes(path)
    if not data or cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) is None:
        raise CheckpointError(f"{path}: not a JPEG image")
    return data


def _keyframes(arrays: dict[str, np.ndarray], images: Path) -> tuple[Keyframe, ...]:
    out = []
    offset = 0
    scans = arrays["scans"]
    for i, kf_id in enumerate(arrays["ids"].tolist()):
        length = int(arrays["scan_lengths"][i])
        scan = None
        if length >= 0:
            scan = KeptScan.from_centimetres(np.array(scans[offset : offset + length], np.int16))
            offset += length
        out.append(Keyframe(
            id=kf_id,
            frame_index=int(arrays["frame_index"][i]),
            timestamp=float(arrays["timestamps"][i]),
            odom_pose=np.array(arrays["odometry"][i], np.float64),
            gt_pose=np.array(arrays["gt"][i], np.float64) if arrays["gt_present"][i] else None,
            scan=scan,
            image=_read_kept(images / f"kf{kf_id:06d}.png", arrays["image_full_size"][i]),
            rear_image=_read_kept(images / f"kf{kf_id:06d}_rear.png", arrays["rear_image_full_size"][i]),
            thumbnail=_read_thumbnail(images / f"kf{kf_id:06d}_thumb.jpg") if arrays["has_thumbnail"][i] else None,
        ))  # fmt: skip
    return tuple(out)


def _loop_record(data: dict[str, Any]) -> LoopRecord:
    proposal = LoopProposal(**data["proposal"])
    reg = data["registration"]
    registration = None
    if reg is not None:
        registration = LoopRegistration(
            **{**reg, "T_mq": np.array(reg["T_mq"], np.float64), "sigmas": np.array(reg["sigmas"], np.float64)}
        )
    handle = data["factor_handle"]
    return LoopRecord(proposal, registration, None if handle is None else int(handle))


def check_log(checkpoint: Checkpoint, log: str | Path) -> None:
    """Refuse to resume a checkpoint with another log than the one it was made from."""
    now = log_fingerprint(log)
    if now != checkpoint.meta.log_fingerprint:
        raise CheckpointError(
            f"{log}: not the log checkpoint {checkpoint.folder} was made from ({checkpoint.meta.log}); "
            "a resume must replay the same frames"
        )
