"""The work `map` spreads over Ray: a worker (a Ray actor) loads the backbone once, then fits
the shared codebooks or runs sessions one after another; a session is a plain `run` of its log
with the shared codebooks, keeping its rear-image codes for the cross-session matching.

Ray is the engine (local by default, a cluster with `--ray-address`): the same code spreads
over the cores of a laptop or the machines of a cluster, and restarts a worker that died
(killed, out of memory) and runs its session again (`map.task_retries`). On a cluster the
output folder must be one every worker can write (a shared file system).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from ssmvpr_common.errors import SsmvprError
from ssmvpr_slam.config.slam import SlamConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SessionOutcome:
    """What became of one session: its results folder, or why it failed."""

    index: int
    name: str
    log: str
    folder: str | None = None
    error: str | None = None
    keyframes: int = 0
    seconds: float = 0.0


def session_config(config: SlamConfig, codebooks: Path, out_dir: Path) -> SlamConfig:
    """A session's settings: the map's, with the shared codebooks and rear codes kept."""
    cfg = config.model_copy(deep=True)
    cfg.detector.codebooks = str(codebooks)
    cfg.detector.rear.keep_codes = True
    cfg.results.out_dir = str(out_dir)
    cfg.results.save_database = True
    # a session is run again whole when its worker dies (`map.task_retries`): no checkpoints
    cfg.results.checkpoint_every_keyframes = None
    cfg.results.checkpoint_every_s = None
    return cfg


def sample_images(log_path: str, config: SlamConfig, count: int, stride: int) -> list[np.ndarray]:
    """`count` forward images of a log, `stride` frames apart from its start."""
    from frontend.sources import open_source

    source = open_source(Path(log_path), config.frontend.source, config.frontend.pose_files)
    images = []
    for frame in islice(source, 0, count * stride, stride):
        if frame.image is not None:
            images.append(frame.image)
    return images


class SessionWorker:
    """A Ray actor's body: the backbone, loaded once, for every task the worker runs."""

    def __init__(self, config: SlamConfig) -> None:
        from loopclosure.backbone import load_backbone

        logging.basicConfig(level=logging.WARNING)
        self.config = config
        self.backbone = load_backbone(config.vpr.backbone)

    def fit_codebooks(self, logs: list[str], out: str) -> str:
        """Fit the shared PCA codebooks on images of every log; returns the file written."""
        from loopclosure.encoder import Encoder

        cfg = self.config.map
        images = []
        for path in logs:
            try:
                images.extend(
                    sample_images(path, self.config, cfg.codebook_images_per_session, cfg.codebook_frame_stride)
                )
            except SsmvprError as exc:  # that session will fail on its own, named; the others still fit
                log.warning("codebooks: skipping %s: %s", path, exc)
        if len(images) < 2:
            raise SsmvprError(f"too few images in the logs to fit PCA codebooks on ({len(images)})")
        encoder = Encoder(self.config.vpr, self.backbone)
        prepared = (encoder.prepare(image, f"codebook image {k}") for k, image in enumerate(images))
        encoder.fit_codebooks(prepared).save(out)
        return out

    def run_session(self, index: int, name: str, log_path: str, codebooks: str, out_dir: str) -> SessionOutcome:
        """`run` the log as one session; a failure of its input is the outcome, not a crash."""
        import time

        from ssmvpr_slam.app.runner import run_log

        start = time.perf_counter()
        cfg = session_config(self.config, Path(codebooks), Path(out_dir))
        console = Console(quiet=True)  # a worker's progress bars would interleave; the driver reports each session
        try:
            folder, metrics = run_log(Path(log_path), cfg, None, console, name=name, backbone=self.backbone)
        except SsmvprError as exc:
            return SessionOutcome(index, name, log_path, error=str(exc), seconds=time.perf_counter() - start)
        return SessionOutcome(index, name, log_path, str(folder), keyframes=int(metrics["keyframes"]),
                              seconds=time.perf_counter() - start)  # fmt: skip


def worker_gpus(config: SlamConfig, cluster_gpus: float) -> float:
    """GPUs per worker: as configured, else the cluster's shared among the workers (at most one each)."""
    if config.map.worker_gpus is not None:
        return config.map.worker_gpus
    return min(1.0, cluster_gpus / config.map.workers) if cluster_gpus > 0 else 0.0


def worker_cpus(config: SlamConfig, cluster_cpus: float) -> float:
    """CPUs per worker: as configured, else the cluster's shared among the workers (at least
    one): one worker on two cores runs its backbone on both."""
    if config.map.worker_cpus is not None:
        return config.map.worker_cpus
    return max(1.0, float(int(cluster_cpus // config.map.workers)))


def remote_worker(config: SlamConfig) -> Any:
    """A `SessionWorker` as a Ray actor with the map's resources and retries."""
    import ray

    actor = ray.remote(SessionWorker).options(
        num_cpus=worker_cpus(config, float(ray.cluster_resources().get("CPU", 1.0))),
        num_gpus=worker_gpus(config, float(ray.cluster_resources().get("GPU", 0.0))),
        max_restarts=config.map.task_retries,
        max_task_retries=config.map.task_retries,
    )
    return actor.remote(config)
