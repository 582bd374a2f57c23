"""The `map:` settings of `ssmvpr-slam map` (`ssmvpr_slam.multi_session`): the Ray workers, the
shared codebooks, and when two sessions are joined. `SlamConfig` nests them as `map:`."""

from __future__ import annotations

from pydantic import Field

from ssmvpr_common.settings_model import SettingsModel


class MapConfig(SettingsModel):
    """`map`: many sessions (logs) into one map through the loops between them."""

    workers: int = Field(default=1, ge=1, description="Ray workers, each holding the backbone once (--workers).")
    worker_cpus: float | None = Field(
        default=None,
        gt=0,
        description="CPUs Ray reserves for each worker (its torch threads); None: the CPUs Ray sees shared "
        "among the workers (at least one each).",
    )
    worker_gpus: float | None = Field(
        default=None,
        ge=0,
        description="GPUs Ray reserves for each worker; None: where Ray sees GPUs, they are shared among the "
        "workers (at most one each), else 0 (the backbone runs on the CPU).",
    )
    ray_connect_timeout_s: float = Field(
        default=30.0, gt=0, description="Seconds a cluster at --ray-address has to answer before `map` gives up on it."
    )
    task_retries: int = Field(
        default=1, ge=0, description="Times a session whose worker died (killed, out of memory) is run again."
    )
    codebook_images_per_session: int = Field(
        default=24, ge=1, description="Images of each log the shared PCA codebooks are fitted on (no codebooks given)."
    )
    codebook_frame_stride: int = Field(
        default=4, ge=1, description="Frames between those images, from each log's start."
    )
    min_agreeing_loops: int = Field(
        default=3, ge=1, description="Verified loops between two sessions that must agree on where one lies in "
        "the other's frame before the two are joined (fewer: kept apart, never forced together).",
    )  # fmt: skip
    agree_translation_m: float = Field(
        default=3.0, gt=0, description="Two loops agree when the session offsets they imply differ by less than this."
    )
    agree_yaw_deg: float = Field(default=5.0, gt=0, description="... and by less than this in heading.")
