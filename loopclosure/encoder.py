"""Images to SSM-VPR codes: one backbone pass, then stage-I vectors and the stage-II grid."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from loopclosure.backbone import Backbone
from loopclosure.backbone_input import as_rgb, resize_square, too_small
from loopclosure.blas import one_blas_thread
from loopclosure.config import VPRConfig
from loopclosure.cubes import extract_cubes
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, fit_pca
from loopclosure.torch_projection import TorchProjection, uses_torch_projection

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlaceCodes:
    """Codes of B images: stage1 (B, n_vectors, d1) and stage2 (B, gh, gw, d2), float32."""

    stage1: np.ndarray
    stage2: np.ndarray

    def __len__(self) -> int:
        return int(self.stage1.shape[0])

    def __getitem__(self, index: int | slice) -> PlaceCodes:
        if isinstance(index, int):
            index = slice(index, index + 1)
        return PlaceCodes(self.stage1[index], self.stage2[index])

    def all_finite(self) -> bool:
        """No NaN or inf in either stage: such a code votes for nothing or matches everything."""
        return bool(np.isfinite(self.stage1).all() and np.isfinite(self.stage2).all())

    @staticmethod
    def concatenate(parts: Sequence[PlaceCodes]) -> PlaceCodes:
        return PlaceCodes(np.concatenate([p.stage1 for p in parts]), np.concatenate([p.stage2 for p in parts]))


@dataclass(frozen=True)
class RawCubes:
    """Cube vectors before PCA: stage1 (B, n1, D1), stage2 (B, gh, gw, D2)."""

    stage1: np.ndarray
    stage2: np.ndarray


class Encoder:
    """Owns the backbone and the codebooks; everything image-side of the method."""

    def __init__(self, config: VPRConfig, backbone: Backbone, codebooks: Codebooks | None = None) -> None:
        self.config = config
        self.backbone = backbone
        self.codebooks = codebooks
        self._torch_projection: TorchProjection | None = None  # the codebooks' copy on the device

    def prepare(self, image: np.ndarray, name: str = "image", strict: bool = False) -> np.ndarray:
        """Square RGB input for the backbone. A tiny image is refused when `strict` (a benchmark
        or a PCA fit on files the user chose), else it is used with a warning (a stream)."""
        rgb = as_rgb(image, name)
        problem = too_small(rgb, name)
        if problem is not None:
            if strict:
                raise LoopClosureInputError(problem)
            log.warning("%s", problem)
        return resize_square(rgb, self.config.backbone.input_size)

    def raw_cubes(self, images: Sequence[np.ndarray]) -> RawCubes:
        """Backbone + cube extraction for one batch of prepared (square RGB) images."""
        maps1, maps2 = self.backbone(np.stack(images))
        stage1 = extract_cubes(maps1, self.config.filtering.cubes)
        return RawCubes(
            stage1.reshape(stage1.shape[0], -1, stage1.shape[-1]), extract_cubes(maps2, self.config.spatial.cubes)
        )

    def project(self, raw: RawCubes) -> PlaceCodes:
        if self.codebooks is None:
            raise LoopClosureInputError("no PCA codebooks: fit them (ssmvpr-slam fit-pca) or load a database")
        # One BLAS thread: right after a backbone pass torch's threads still hold the cores, and a
        # second BLAS thread on these small products fights them (docs/benchmarks.md).
        with one_blas_thread():
            return PlaceCodes(self.codebooks.stage1.transform(raw.stage1), self.codebooks.stage2.transform(raw.stage2))

    def codes(self, images: Sequence[np.ndarray]) -> PlaceCodes:
        """Codes of one batch of prepared images: `project(raw_cubes(images))`, or, where
        `vpr.backbone.projection` resolves to torch, the same computed where the maps are."""
        if self.codebooks is None or not uses_torch_projection(self.config, self.backbone.device):
            return self.project(self.raw_cubes(images))
        projection = self._torch_projection
        if (
            projection is None
            or projection.codebooks is not self.codebooks
            or projection.device != self.backbone.device
        ):
            projection = self._torch_projection = TorchProjection(self.config, self.codebooks, self.backbone.device)
        return PlaceCodes(*projection(*self.backbone.maps(np.stack(images))))

    def encode(self, images: Sequence[np.ndarray]) -> PlaceCodes:
        """Codes of already-prepared images, batched as configured."""
        return PlaceCodes.concatenate(
            [self.codes(batch) for batch in _batches(images, self.config.backbone.batch_size)]
        )

    def encode_stream(
        self, images: Iterable[np.ndarray], on_batch: Callable[[int], None] | None = None
    ) -> Iterator[PlaceCodes]:
        """Codes batch by batch, for folders too big to hold as images."""
        for batch in _batches(images, self.config.backbone.batch_size):
            yield self.codes(batch)
            if on_batch is not None:
                on_batch(len(batch))

    def fit_codebooks(self, images: Iterable[np.ndarray], on_batch: Callable[[int], None] | None = None) -> Codebooks:
        """Fit both PCA codebooks on prepared images (e.g. the reference set) and keep them."""
        return self._fit(images, on_batch, keep_raw=False)[0]

    def fit_and_encode(
        self, images: Iterable[np.ndarray], on_batch: Callable[[int], None] | None = None
    ) -> tuple[Codebooks, PlaceCodes]:
        """Fit on a set and encode that same set with one backbone pass (cubes held in memory)."""
        codebooks, raws = self._fit(images, on_batch, keep_raw=True)
        return codebooks, PlaceCodes.concatenate([self.project(raw) for raw in raws])

    def _fit(
        self, images: Iterable[np.ndarray], on_batch: Callable[[int], None] | None, keep_raw: bool
    ) -> tuple[Codebooks, list[RawCubes]]:
        raws: list[RawCubes] = []
        samples = _FitSamples(self.config)
        for batch in _batches(images, self.config.backbone.batch_size):
            raw = self.raw_cubes(batch)
            samples.add(raw)
            if keep_raw:
                raws.append(raw)
            if on_batch is not None:
                on_batch(len(batch))
        self.codebooks = samples.fit()
        return self.codebooks, raws

    def fit_codebooks_from_raw(self, raws: Iterable[RawCubes]) -> Codebooks:
        """Fit on cubes already computed (a streaming detector's first keyframes)."""
        samples = _FitSamples(self.config)
        for raw in raws:
            samples.add(raw)
        self.codebooks = samples.fit()
        return self.codebooks


class _FitSamples:
    """Cube vectors collected for fitting; a seeded subset of each grid keeps memory bounded."""

    def __init__(self, config: VPRConfig) -> None:
        self.config = config
        self.stage1: list[np.ndarray] = []
        self.stage2: list[np.ndarray] = []
        self.rng = np.random.default_rng(config.spatial.pca.seed)
        self.per_image = per_image_cells(config)

    def add(self, raw: RawCubes) -> None:
        self.stage1.append(raw.stage1.reshape(-1, raw.stage1.shape[-1]))
        grid = raw.stage2.reshape(raw.stage2.shape[0], -1, raw.stage2.shape[-1])
        keep = min(self.per_image, grid.shape[1])
        for cells in grid:
            self.stage2.append(cells[np.sort(self.rng.choice(grid.shape[1], keep, replace=False))])

    def fit(self) -> Codebooks:
        if not self.stage1:
            raise LoopClosureInputError("no images to fit the PCA codebooks on")
        # one BLAS thread: right after backbone passes, torch's threads still hold the cores
        with one_blas_thread():
            return self._fit_both()

    def _fit_both(self) -> Codebooks:
        return Codebooks(
            fit_pca(np.concatenate(self.stage1), self.config.filtering.pca, "stage-I PCA"),
            fit_pca(np.concatenate(self.stage2), self.config.spatial.pca, "stage-II PCA"),
        )


def per_image_cells(config: VPRConfig) -> int:
    """Stage-II cells kept per image so the fit set stays near pca.max_fit_samples."""
    pca = config.spatial.pca
    return max(1, -(-pca.max_fit_samples // pca.max_fit_images))


def _batches(items: Iterable[np.ndarray], size: int) -> Iterator[list[np.ndarray]]:
    batch: list[np.ndarray] = []
    for item in items:
        batch.append(item)
        if len(batch) == size:
            yield batch
            batch = []
    if batch:
        yield batch
