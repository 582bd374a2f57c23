"""The paper's single-frame recognition in one object: reference images in, the best place of a
query out. It owns what `vpr-eval` wires by hand (backbone, encoder, PCA codebooks fitted on
the references, place database, recogniser), for users who want SSM-VPR without the SLAM."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from loopclosure.backbone import load_backbone
from loopclosure.backbone_input import read_image
from loopclosure.config import VPRConfig
from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.encoder import Encoder, PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.two_stage import Recognition, TwoStageRanker

Image = np.ndarray | str | Path  # an RGB uint8 array, or an image file


def configured(config: VPRConfig | None, weights: str | Path | None, device: str | None) -> VPRConfig:
    """A copy of `config` (default: the ECMR 2019 settings) with the weights and device given."""
    vpr = (config or VPRConfig()).model_copy(deep=True)
    if weights is not None:
        vpr.backbone.weights = str(weights)
    if device is not None:
        vpr.backbone.device = device  # type: ignore[assignment]
    return vpr


class PlaceRecognizer:
    """SSM-VPR over a set of reference places. `add_references` fits the PCA codebooks on the
    first references it is given (as `vpr-eval` does), then every query is stage I + stage II."""

    def __init__(self, config: VPRConfig, encoder: Encoder) -> None:
        self.config = config
        self.encoder = encoder
        self.database: PlaceDatabase | None = None
        self._recognizer: TwoStageRanker | None = None

    @classmethod
    def from_config(
        cls, config: VPRConfig | None = None, weights: str | Path | None = None, device: str | None = None
    ) -> PlaceRecognizer:
        """Build the backbone (weights as configured: a path, $SSMVPR_WEIGHTS, the cache, a download)."""
        vpr = configured(config, weights, device)
        return cls(vpr, Encoder(vpr, load_backbone(vpr.backbone)))

    def __len__(self) -> int:
        return len(self.database) if self.database is not None else 0

    def _prepared(self, images: Iterable[Image]) -> list[np.ndarray]:
        out = []
        for image in images:
            name = str(image) if not isinstance(image, np.ndarray) else "image"
            array = read_image(image) if not isinstance(image, np.ndarray) else image
            out.append(self.encoder.prepare(array, name, strict=True))
        return out

    def add_references(self, images: Iterable[Image]) -> list[int]:
        """Add reference places (in order; their indices are returned). The first call fits PCA
        on its images, so give it the whole reference set, or at least a few dozen images."""
        prepared = self._prepared(images)
        if not prepared:
            raise LoopClosureInputError("add_references: no images given")
        if self.encoder.codebooks is None:
            self.encoder.codebooks, codes = self.encoder.fit_and_encode(prepared)
        else:
            codes = PlaceCodes.concatenate(list(self.encoder.encode_stream(prepared)))
        if self.database is None:
            self.database = PlaceDatabase(self.encoder.codebooks, self.config.database)
            self._recognizer = TwoStageRanker(self.config, self.database)
        first = len(self.database)
        return self.database.add(codes, [PlaceInfo(frame_id=first + i) for i in range(len(codes))])

    def query(self, image: Image) -> Recognition:
        """The reference places ranked for one query image (`best_place`, `best_score`)."""
        if self._recognizer is None:
            raise LoopClosureInputError("query: add reference images first (add_references)")
        return self._recognizer.query(self.encoder.encode(self._prepared([image])))
