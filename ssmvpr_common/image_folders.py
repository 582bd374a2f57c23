"""Which files of a folder are images, in frame order, and which frame each one is: the rules
every reader of image folders follows (the front end's folder and KITTI sources, the VPR
benchmarks)."""

from __future__ import annotations

import re
from pathlib import Path

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp")
_RUNS = re.compile(r"(\d+)")


def natural_key(path: Path) -> tuple[tuple[int, int | str], ...]:
    """Sort key reading digit runs as numbers: ``frame9`` before ``frame10``, zero-padded names unchanged."""
    return tuple((0, int(run)) if run.isdigit() else (1, run) for run in _RUNS.split(path.name) if run)


def image_files(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, in frame order (names sorted with their numbers read as numbers)."""
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)


def frame_number(path: Path) -> int | None:
    """The frame a file is, when its name is a frame number (KITTI's ``000030.png``), else None."""
    return int(path.stem) if path.stem.isdigit() else None


def pair_by_number(files: list[Path], lines: int) -> tuple[list[Path | None], list[Path]] | None:
    """Files put at the line (frame) their name numbers: (one file or None per line, files
    numbered past the last line). A missing ``000030.png`` must leave frame 30 without an image,
    not shift every later image onto the next frame's scan and time. None, for the caller to pair
    by position (where counts must agree), when a name is not a frame number or the numbers run
    without a gap (then position and number agree, and a count that differs is a wrong file)."""
    numbers = [frame_number(p) for p in files]
    if not files or any(n is None for n in numbers):
        return None
    first = numbers[0]
    assert first is not None
    if numbers == list(range(first, first + len(numbers))):
        return None
    at: list[Path | None] = [None] * lines
    extra: list[Path] = []
    for number, path in zip(numbers, files):
        assert number is not None
        if number < lines:
            at[number] = path
        else:
            extra.append(path)
    return at, extra
