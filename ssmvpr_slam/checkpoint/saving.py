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
continues from it, and `checkpoint_loading.load_checkpoint(...).result` reads it as a partial
`RunResult`.

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
import os
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ssmvpr_common.atomic import atomic_write_bytes, atomic_write_text
from ssmvpr_slam.backend.two_view import ReducedImage
from ssmvpr_slam.checkpoint.record import CheckpointError, CheckpointRecord
from ssmvpr_slam.config.slam import ResultsConfig, SlamConfig
from ssmvpr_slam.results.run_folder import RunFolder, switch_link
from ssmvpr_slam.results.writers import prior_gt, write_config, write_database, write_loop_csv, write_trajectories
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult, StreamEnd

log = logging.getLogger(__name__)

LINK = "checkpoint"
META = "checkpoint.json"
_PREFIX = "checkpoint-"


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
    write_database(folder / "database", partial, config, poses=partial.in_map_frame, images=False)  # in images/
    _write_images(folder / "images", partial.keyframes, previous)
    atomic_write_bytes(folder / "keyframes.npz", _npz(_keyframe_arrays(partial)))
    atomic_write_bytes(folder / "detector.npz", _npz(detector_state))
    record = CheckpointRecord(
        written=time.strftime("%Y-%m-%dT%H:%M:%S"), **asdict(meta), frames_seen=partial.frames_seen,
        frames_skipped=dict(partial.frames_skipped), rear_keyframes=partial.rear_keyframes,
        seconds=partial.ending.seconds, keyframes=len(partial.keyframes),
        timings=[dict(r) for r in partial.timings], loops=_loop_dicts(partial),
        unapplied_loops=[index for index, _ in partial.unapplied_registrations],
        config_sha256=hashlib.sha256((folder / "config.yaml").read_bytes()).hexdigest(),
    )  # fmt: skip
    # allow_nan: a loop record's scores may be NaN (a proposal with no sequence score)
    atomic_write_text(folder / META, json.dumps(record.model_dump(), indent=1, allow_nan=True) + "\n")
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


def _loop_dicts(partial: RunResult) -> list[dict[str, Any]]:
    """The loop records; a loop registered but not applied yet (`unapplied_loops`) with its
    registration, which a resume applies when it falls due."""
    unapplied = dict(partial.unapplied_registrations)
    return [_loop_dict(replace(r, registration=unapplied[i]) if i in unapplied else r)
            for i, r in enumerate(partial.loops)]  # fmt: skip


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
        if not self.system.detector.ready:  # still in the PCA warm-up: nothing a resume could start from
            return None
        state = self.system.detector.state_arrays()  # `checkpoint_replay` puts a system back from it
        seconds = self._seconds_before + time.monotonic() - self._started
        partial = partial_result(self.system, StreamEnd(interrupted=True, seconds=seconds))
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


def check_log(checkpoint: Checkpoint, log: str | Path) -> None:
    """Refuse to resume a checkpoint with another log than the one it was made from."""
    now = log_fingerprint(log)
    if now != checkpoint.meta.log_fingerprint:
        raise CheckpointError(
            f"{log}: not the log checkpoint {checkpoint.folder} was made from ({checkpoint.meta.log}); "
            "a resume must replay the same frames"
        )


def partial_result(system: Any, ending: StreamEnd) -> RunResult:
    """The run so far of `system` (a SlamSystem) with iSAM2's current estimate, without the final pass (a checkpoint's view:
    the system goes on afterwards, unchanged), and the registrations not applied yet. Its
    `database` is the live one, which the next keyframe extends: write it out before processing on."""
    optimised = system.graph.optimized_poses() if system.state.keyframes else {}
    partial = system.result_with(optimised, set(system.graph.loop_handles), ending, odometry_stats=False)
    return replace(partial, unapplied_registrations=tuple(system.registrations.unapplied()))
