"""Results folders: one timestamped folder per run and a `latest` link, as kiss-icp does."""

from __future__ import annotations

import json
import os
from datetime import datetime
from pathlib import Path
from typing import Any

from loopclosure.atomic import atomic_write_text


def create_results_dir(base: str | Path, name: str) -> Path:
    """`base/<name>_<YYYY-mm-dd_HH-MM-SS>` plus `base/latest` pointing at it."""
    base = Path(base)
    stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    folder = base / f"{name}_{stamp}"
    suffix = 1
    while folder.exists():
        folder = base / f"{name}_{stamp}_{suffix}"
        suffix += 1
    folder.mkdir(parents=True)
    link = base / "latest"
    tmp_link = base / f".latest.{os.getpid()}"
    tmp_link.unlink(missing_ok=True)
    tmp_link.symlink_to(folder.name, target_is_directory=True)
    os.replace(tmp_link, link)  # atomic switch of the link
    return folder


def write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False, default=_plain) + "\n")


def _plain(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
