"""Where `demo` keeps the logs it simulates: in the user cache, outside the results folders, one
file per simulation (its settings, the writer's and the simulator's own code), so a second
`demo` with the same settings streams the log it already has instead of rendering it again."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import frontend.simulation
import frontend.sources.mcap_writer
from loopclosure.weights import default_cache_dir
from ssmvpr_slam.config import SlamConfig

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
