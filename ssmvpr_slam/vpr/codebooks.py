"""`fit-pca`: PCA codebooks fitted ahead of time on an image folder, for runs and benchmarks that
should use codebooks of the place (`detector.codebooks`, `vpr-eval --pca`) rather than fit their
own on their first keyframes or references."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.markup import escape

from loopclosure.backbone import load_backbone
from loopclosure.backbone_input import list_images, read_image
from loopclosure.config import VPRConfig
from loopclosure.encoder import Encoder
from loopclosure.pca import Codebooks
from loopclosure.sampling import evenly_spaced


def fit_images(folder: Path, max_images: int) -> list[Path]:
    """At most `max_images` of the folder's images (name order), evenly spread over all of it."""
    files = list_images(folder)
    return [files[i] for i in evenly_spaced(len(files), max_images)]


def fit_codebooks(folder: Path, output: Path, config: VPRConfig, console: Console) -> Codebooks:
    """Fit both codebooks on up to `spatial.pca.max_fit_images` images of `folder` and save them
    to `output` (.npz)."""
    subset = fit_images(folder, config.spatial.pca.max_fit_images)
    encoder = Encoder(config, load_backbone(config.backbone, progress=True))
    with console.status(f"fitting PCA on {len(subset)} images of {escape(str(folder))}"):
        codebooks = encoder.fit_codebooks(encoder.prepare(read_image(p), str(p), strict=True) for p in subset)
    codebooks.save(output)
    return codebooks
