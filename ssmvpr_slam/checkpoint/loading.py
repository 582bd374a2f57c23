"""Reading a checkpoint back (`load_checkpoint`), everything checked before it is used.

A damaged file (cut short, a field of the wrong kind, NaN in a pose, ids out of order, a
config.yaml edited since) is one CheckpointError naming the file and what is wrong, never a
traceback from deep inside the restore or a silently wrong resumed run. checkpoint.json is
validated by its model (`checkpoint_record`); what spans files (keyframes.npz against the
record, loops against the keyframes and the graph's handles) is checked here. The layout is in
`ssmvpr_slam.checkpoint.saving`, which writes it."""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
import zlib
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from loopclosure.database import PlaceDatabase
from loopclosure.detector import LoopProposal
from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.text_files import read_text
from ssmvpr_slam.backend.kept_scan import KeptScan
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.backend.noise import check_sigmas
from ssmvpr_slam.backend.se3 import DEFAULT_ROTATION_TOLERANCE, as_pose
from ssmvpr_slam.backend.two_view import ReducedImage
from ssmvpr_slam.checkpoint.record import FORMAT, FORMAT_VERSION, CheckpointError, CheckpointRecord, read_record
from ssmvpr_slam.checkpoint.saving import META, Checkpoint, CheckpointMeta, find_checkpoint
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult, StreamEnd, frozen_array


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint (`path`: the run's results folder or the checkpoint folder).

    Everything is checked before it is used: a damaged file (cut short, a field of the wrong
    type, NaN in a pose, ids out of order) is one CheckpointError naming the file and what is
    wrong, never a traceback from deep inside the restore or a silently wrong resumed run."""
    folder = find_checkpoint(path)
    record = read_record(folder / META, _read_meta(folder / META))
    run_folder = folder.parent
    try:
        meta = CheckpointMeta(record.log, record.log_fingerprint, record.prior_map, record.name)
        config_text = read_text(folder / "config.yaml", CheckpointError)
        arrays = _load_npz(folder / "keyframes.npz")
        tolerance = _rotation_tolerance(config_text)
        n = _check_keyframe_arrays(folder / "keyframes.npz", arrays, record, tolerance)
        keyframes = _keyframes(arrays, folder / "images")
        loops = tuple(_loop_record(d) for d in record.loops)
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
    loops, unapplied = _split_unapplied(folder / META, loops, record.unapplied_loops)
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
        frames_seen=record.frames_seen,
        frames_skipped=dict(record.frames_skipped),
        rear_keyframes=record.rear_keyframes,
        timings=tuple(record.timings),
        ending=StreamEnd(interrupted=True, seconds=record.seconds),
        database=database,
        session_places={database.places[i].frame_id: i for i in range(prior_places, len(database))},
        unapplied_registrations=unapplied,
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


def _check_keyframe_arrays(
    path: Path, arrays: dict[str, np.ndarray], record: CheckpointRecord, tolerance: float
) -> int:
    """keyframes.npz holds every array, shaped for the keyframes checkpoint.json lists, with
    values a restore can use; returns the number of keyframes."""
    missing = [name for name in (*_KEYFRAME_ARRAYS, "scans") if name not in arrays]
    if missing:
        raise CheckpointError(f"{path}: lacks {', '.join(missing)}")
    if arrays["ids"].ndim != 1:
        raise CheckpointError(f"{path}: ids has shape {arrays['ids'].shape}, expected one id per keyframe")
    n = len(arrays["ids"])
    if record.keyframes != n:
        raise CheckpointError(f"{path.parent}: {META} lists {record.keyframes} keyframes, {path.name} holds {n}")
    for name, (kinds, shape) in _KEYFRAME_ARRAYS.items():
        array = arrays[name]
        if array.dtype.kind not in kinds or array.shape != (n, *shape):
            raise CheckpointError(f"{path}: {name} is {array.dtype} {array.shape}, expected {_KINDS[kinds]} "
                                  f"{(n, *shape)}")  # fmt: skip
    frames_seen = record.frames_seen
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


def _check_config(folder: Path, record: CheckpointRecord, config_text: str, database: PlaceDatabase) -> None:
    """config.yaml must be the settings the database and the state were made with: a resume
    runs with it, and writes it into the results as the run's settings. Edited (its digest is not
    the one checkpoint.json recorded), or naming code sizes the database's codebooks do not have,
    it is refused (one line), never a resume whose config.yaml says what the run did not do."""
    path = folder / "config.yaml"
    digest = record.config_sha256
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


def _split_unapplied(
    path: Path, loops: tuple[LoopRecord, ...], indices: list[int]
) -> tuple[tuple[LoopRecord, ...], tuple[tuple[int, LoopRegistration], ...]]:
    """The records as the running system held them (an unapplied loop without its registration)
    and the unapplied registrations: accepted proposals, no factor yet, in order."""
    if indices != sorted(set(indices)):
        raise CheckpointError(f"{path}: unapplied_loops must be increasing loop indices, got {indices}")
    unapplied = []
    for i in indices:
        if i >= len(loops):
            raise CheckpointError(f"{path}: unapplied_loops names loops[{i}], there are {len(loops)}")
        record = loops[i]
        if not record.proposal.accepted or record.registration is None or record.factor_handle is not None:
            raise CheckpointError(f"{path}: loops[{i}] is not a registered loop waiting to be applied")
        unapplied.append((i, record.registration))
    held = tuple(replace(r, registration=None) if i in set(indices) else r for i, r in enumerate(loops))
    return held, tuple(unapplied)


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
