"""The demo's simulated log and settings.

`demo` keeps the logs it simulates in the user cache, outside the results folders, one file per
simulation (its settings, the writer's and the simulator's own code), so a second `demo` with the
same settings streams the log it already has instead of rendering it again. With the log's own
(wheel) odometry the demo is the camera-only case, as `run --odometry logged --no-lidar-loops`."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from rich.console import Console
from rich.markup import escape

import frontend.simulation
import frontend.sources.mcap_writer
from loopclosure.weights import default_cache_dir
from ssmvpr_slam.app.runner import simulate_to_mcap
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.results.run_folder import output_file

FOLDER = "simulated"


def _code_digest() -> str:
    """The simulator's and the writer's source: a changed simulator makes a new log."""
    digest = hashlib.sha256()
    files = sorted(Path(frontend.simulation.__file__).parent.glob("*.py"))
    for path in [*files, Path(frontend.sources.mcap_writer.__file__)]:
        digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()


def simulated_log_path(config: SlamConfig, cache_dir: Path | None = None) -> Path:
    """`<cache>/simulated/demo-<digest>.mcap` for this simulation (the file may not exist yet)."""
    settings = {"simulation": config.simulation.model_dump(mode="json"),
                "writer": config.frontend.writer.model_dump(mode="json"), "code": _code_digest()}  # fmt: skip
    key = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    return (cache_dir or default_cache_dir()) / FOLDER / f"demo-{key}.mcap"


def demo_log(config: SlamConfig, console: Console, cache_dir: Path | None = None) -> Path:
    """The demo's log for `config`: the one an earlier demo with these settings left in the
    cache, else simulated into the cache now."""
    log = simulated_log_path(config, cache_dir)
    if log.is_file():
        console.print(f"simulated log (already rendered): {escape(str(log))}", highlight=False)
        return log
    with output_file(log, "the simulated log's cache folder ($SSMVPR_CACHE)"):
        return simulate_to_mcap(config, log, console)


def with_demo_odometry(config: SlamConfig, kind: str) -> SlamConfig:
    """`config` with the demo's odometry (`kiss_icp` or `logged`). The logged odometry is the
    simulator's drifting wheel odometry: the demo then shows camera loops alone, so loops are
    registered without the scans (`pipeline.use_lidar_for_loops` off) whatever the preset says."""
    config = config.model_copy(deep=True)
    config.frontend.odometry.kind = kind  # type: ignore[assignment]  # validated on assignment
    if config.frontend.odometry.kind == "logged":
        config.pipeline.use_lidar_for_loops = False
    return config
