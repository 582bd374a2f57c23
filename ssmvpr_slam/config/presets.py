"""Where the YAML presets live, apart from the config models so that `--help` can list them
without importing the models (and the simulator they pull in)."""

from __future__ import annotations

from pathlib import Path


def _presets_dir() -> Path:
    """The YAML presets: shipped in the package (`ssmvpr_slam/config/presets`, a wheel install), or the
    checkout's top-level `configs/` (an editable install), which pyproject maps to the same place."""
    here = Path(__file__).resolve().parent
    packaged = here / "presets"
    return packaged if packaged.is_dir() else here.parents[1] / "configs"


PRESETS_DIR = _presets_dir()


def available_presets() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))
