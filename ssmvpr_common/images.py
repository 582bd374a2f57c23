"""Which files of a folder are images, in frame order: the one rule every reader of image
folders follows (the front end's folder and KITTI sources, the VPR benchmarks)."""

from __future__ import annotations

from pathlib import Path

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp")


def image_files(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, sorted by name (zero-padded names sort in frame order)."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
