"""checkpoint.json as one pydantic model: the writer builds it, the reader validates against it.

Strict, so a resume never runs on a field a hand edit or a damaged disk changed in kind (a
count that became text, 12.5 or true; NaN seconds). A field that fails is one line naming the
file, the field and what it must be; the checks that span files (keyframes against
keyframes.npz, loops against the graph) stay with the reader, `ssmvpr_slam.checkpoint.loading`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, NoReturn

from pydantic import BaseModel, ConfigDict, Field, NonNegativeInt, ValidationError

from ssmvpr_slam.errors import SlamError

FORMAT = "ssmvpr-slam-checkpoint"
FORMAT_VERSION = 3  # 2: keyframes keep grey PNG copies and JPEG thumbnails, float32 scans; 3: int16 cm scans

FiniteSeconds = Annotated[float, Field(allow_inf_nan=False)]
StageSeconds = Annotated[dict[str, FiniteSeconds], Field(min_length=1)]


class CheckpointError(SlamError, ValueError):
    """A checkpoint that cannot be resumed from (missing, damaged, another log, another build);
    the message names the file."""


class CheckpointRecord(BaseModel):
    """What checkpoint.json holds besides the arrays and files beside it."""

    model_config = ConfigDict(strict=True, extra="forbid")

    format: str = FORMAT
    version: int = FORMAT_VERSION
    written: str
    log: str
    log_fingerprint: dict[str, Any]
    prior_map: str | None  # required: null says "no prior map", a missing key says nothing
    name: str
    frames_seen: NonNegativeInt
    frames_skipped: dict[str, NonNegativeInt]
    rear_keyframes: NonNegativeInt
    seconds: Annotated[float, Field(ge=0, allow_inf_nan=False)]
    keyframes: NonNegativeInt
    # one row of seconds per stage a keyframe, each with the stages of the first at least (a run
    # resumed from an older build's checkpoint adds rows with the stages added since)
    timings: list[StageSeconds]
    loops: list[dict[str, Any]]  # LoopRecord fields, checked against the keyframes by the reader
    # loops[i] registered but not applied yet (pipeline.registration_lag_keyframes): a resume applies them
    unapplied_loops: list[NonNegativeInt] = []
    config_sha256: str | None = None  # of config.yaml beside it; absent in records of older builds


# What each field must be, for the one-line error (pydantic's own messages name types, not units).
_WHAT = {
    "written": "a string", "log": "a string", "name": "a string", "log_fingerprint": "an object",
    "prior_map": "a path or null", "frames_seen": "a whole number >= 0", "keyframes": "a whole number >= 0",
    "rear_keyframes": "a whole number >= 0", "seconds": "a number >= 0",
    "frames_skipped": "an object of whole numbers >= 0", "timings": "a list of objects (seconds per stage)",
    "loops": "a list of objects", "config_sha256": "a hex digest or null",
    "unapplied_loops": "a list of loop indices",
}  # fmt: skip


def read_record(path: Path, data: dict[str, Any]) -> CheckpointRecord:
    """checkpoint.json's parsed JSON as a record, or one CheckpointError naming `path` and the
    first field that is wrong."""
    try:
        record = CheckpointRecord.model_validate(data)
    except ValidationError as exc:
        _refuse(path, data, exc)
    if record.rear_keyframes > record.keyframes:
        raise CheckpointError(f"{path}: rear_keyframes must be at most keyframes ({record.keyframes}), "
                              f"got {record.rear_keyframes}")  # fmt: skip
    for i, row in enumerate(record.timings):
        if missing := sorted(record.timings[0].keys() - row.keys()):
            raise CheckpointError(f"{path}: timings[{i}] lacks stages timings[0] has ({', '.join(missing)})")
    return record


def _refuse(path: Path, data: dict[str, Any], exc: ValidationError) -> NoReturn:
    error = exc.errors()[0]
    loc = error["loc"]
    key = str(loc[0]) if loc else "record"
    if key == "timings" and len(loc) > 1 and isinstance(loc[1], int):
        raise CheckpointError(f"{path}: timings[{loc[1]}] must be an object of numbers (seconds per stage)") from None
    if error["type"] == "extra_forbidden":
        raise CheckpointError(f"{path}: {key} is no field of a checkpoint record") from None
    shown = repr(data[key]) if key in data else "nothing"
    raise CheckpointError(
        f"{path}: {key} must be {_WHAT.get(key, 'as the writer gives it')}, got {shown[:60]}"
    ) from None
