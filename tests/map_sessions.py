"""Simulated sessions in one city for the `map` tests (tests/conftest.py puts this folder on
sys.path): the logs are made once and cached by their settings, so the modules share them."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from frontend.simulation.sessions import city_sessions
from ssmvpr_slam.app.runner import simulate_to_mcap
from ssmvpr_slam.app.simulated_logs import simulated_log_path
from ssmvpr_slam.config.slam import SlamConfig, load_config


def map_config(weights: Path, out: Path, frames: int | None, workers: int = 2) -> SlamConfig:
    """The quick preset with both cameras, as the map tests run it."""
    overrides = {
        "simulation": {"camera": {"rear": True}, "max_frames": frames},
        "vpr": {"backbone": {"weights": str(weights)}},
        "results": {"out_dir": str(out), "mcap": False, "plots": True},
        "map": {"workers": workers, "codebook_images_per_session": 12},
    }
    return load_config("quick", overrides)


def session_log(weights: Path, out: Path, frames: int, index: int, seed: int = 0) -> Path:
    """Session `index` of the city of `seed` (`frames` frames), simulated once and cached."""
    config = map_config(weights, out, frames)
    simulation = city_sessions(config.simulation.model_copy(update={"seed": seed}), 1, start=index)[0]
    config = config.model_copy(update={"simulation": simulation})
    path = simulated_log_path(config)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        simulate_to_mcap(config, path, Console(quiet=True))
    return path


def linked_session_logs(weights: Path, out: Path, frames: int, indices: tuple[int, ...]) -> list[Path]:
    """Sessions `indices` of the city as `out/session<index>.mcap`, links to the cached logs (the
    names `map` gives the sessions)."""
    logs = []
    for index in indices:
        logs.append(out / f"session{index}.mcap")
        logs[-1].symlink_to(session_log(weights, out, frames, index))
    return logs
