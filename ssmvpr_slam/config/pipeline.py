"""`pipeline`: how a run streams its frames: which stages run side by side, when a registered
loop enters the graph, the real-time playback, the heap's release."""

from __future__ import annotations

import os
from typing import Literal

from pydantic import Field

from ssmvpr_common.settings_model import SettingsModel


class PipelineConfig(SettingsModel):
    use_lidar_for_loops: bool = Field(default=True, description="Register loops by ICP when scans exist.")
    max_frames: int | None = Field(
        default=None, ge=1, description="Stop after this many frames of the log (`run --frames`); None: all of it."
    )
    keyframe_image_pixels: int | None = Field(
        default=76800, ge=1024,
        description="A keyframe without a scan keeps grey copies of its camera images for two-view loop "
        "registration, area-averaged to at most this many pixels (aspect kept; 76800 = 320 x 240) and held as PNG "
        "bytes; None keeps them at full size. Keyframes with a scan register by ICP and keep no image; full colour "
        "images are never kept.",
    )  # fmt: skip
    overlap: Literal["auto"] | bool = Field(
        default="auto",
        description="Run the source, odometry and keyframe selection in a thread of their own (run and demo put "
        "kiss-icp in a process of its own: it keeps the GIL), alongside recognition, registration and iSAM2 (same "
        "keyframes, loops and trajectory as false). auto: where the process may use 4 cores or more; on 2 cores "
        "every stage already uses both, and running them side by side was slower (docs/streaming.md).",
    )
    overlap_queue_keyframes: int = Field(
        default=2, ge=1, description="With overlap: keyframes the front end may run ahead of the back end."
    )
    read_ahead_frames: int = Field(
        default=2, ge=0, description="With overlap: frames the source reads and decodes ahead (queued, plus one in "
        "the reader's hand), in a thread of its own, while kiss-icp registers the frame before "
        "(ssmvpr_slam/app/read_ahead.py); 0: the front end's thread reads each frame after the last one's odometry."
    )  # fmt: skip
    odometry_ahead_frames: int = Field(
        default=1, ge=0, le=8, description="With overlap and kiss-icp in its own process: frames handed to that "
        "process before the front end takes their pose, so it registers the next scan while the front end keeps "
        "this keyframe (the same poses in the same order; frontend/odometry/own_process.py). Not in real time, "
        "where a frame is not handed over before it is due. 0: one frame at a time."
    )  # fmt: skip
    encode_ahead: Literal["auto"] | bool = Field(
        default="auto", description="With overlap: the backbone encodes the next keyframe in a thread of its own "
        "while this one is recognised (the same codes, so the same results as false; during the PCA warm-up, and "
        "while int8 calibrates on the stream, the back end encodes its keyframes itself, in order). auto: where "
        "the process may use 4 cores or more."
    )  # fmt: skip
    registration_lag_keyframes: int = Field(
        default=3, ge=0, description="A loop accepted at keyframe k enters the graph at keyframe k + this, "
        "registered meanwhile (ssmvpr_slam/loop_registrations.py): fixed in keyframes, so the result does not "
        "depend on the machine's timing. 0: at its own keyframe, inline."
    )  # fmt: skip
    realtime: bool = Field(
        default=False, description="Play the log at its recorded rate (`run --realtime`): a keyframe that reaches "
        "recognition more than realtime_max_lag_s after its frame was due is handled by odometry alone, counted."
    )  # fmt: skip
    realtime_rate: float = Field(default=1.0, gt=0.0, allow_inf_nan=False,
                                 description="Real time: play the log at this many times its recorded rate.")  # fmt: skip
    realtime_max_lag_s: float = Field(
        default=3.0, ge=0.0, allow_inf_nan=False,
        description="Real time: a keyframe later than this (from its frame being due) skips recognition: the sensor "
        "data that may queue up; it must absorb the one PCA fit that ends the warm-up (docs/streaming.md).",
    )  # fmt: skip
    registration_worker: Literal["auto"] | bool = Field(
        default="auto", description="Register accepted loops in a worker thread while later keyframes are "
        "recognised (the same results as false, which registers them inline when accepted); auto: where the "
        "process may use 4 cores or more."
    )  # fmt: skip

    @property
    def overlapped(self) -> bool:
        """`overlap`, with auto resolved on this machine."""
        return _resolved(self.overlap)

    @property
    def encodes_ahead(self) -> bool:
        """`encode_ahead`, with auto resolved on this machine; only with overlap (it needs the
        front end's keyframes queued ahead of the back end)."""
        return self.overlapped and _resolved(self.encode_ahead)

    @property
    def registers_in_worker(self) -> bool:
        """`registration_worker`, with auto resolved on this machine."""
        return _resolved(self.registration_worker)

    release_heap_every_keyframes: int = Field(
        default=25,
        ge=0,
        description="Hand the allocator's free pages back to the OS (glibc malloc_trim) every this many keyframes; "
        "0 never. Without it a long run's memory grew about 1.2 MB per keyframe of memory it no longer used "
        "(ssmvpr_slam/app/heap.py).",
    )


_CORES_FOR_STAGES_IN_FLIGHT = 4


def _resolved(setting: Literal["auto"] | bool) -> bool:
    """A stage-in-flight setting with auto resolved: on where the process may use 4 cores or more."""
    return setting if isinstance(setting, bool) else _cores() >= _CORES_FOR_STAGES_IN_FLIGHT


def _cores() -> int:
    """The cores this process may run on (a container's CPU set, not the machine's)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
