"""The two stages together: filter the database, re-rank the survivors spatially."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from loopclosure.config import VPRConfig
from loopclosure.database import PlaceDatabase
from loopclosure.encoder import PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.filtering import Candidates
from loopclosure.spatial_torch import stage2_scores


@dataclass(frozen=True)
class Recognition:
    """One query's outcome. `ranked_*` are the candidates re-ranked by final score."""

    candidates: Candidates  # stage I, in voting order
    ranked_places: np.ndarray  # (C,) database indices, best first
    ranked_scores: np.ndarray  # (C,) final scores in [0, 1]
    ranked_shifts: np.ndarray  # (C, 2) dominant grid displacement (rows, columns)
    spatial_scores: np.ndarray  # (C,) stage-II scores in ranked order, before any prior

    @property
    def best_place(self) -> int | None:
        return int(self.ranked_places[0]) if len(self.ranked_places) else None

    @property
    def best_score(self) -> float:
        return float(self.ranked_scores[0]) if len(self.ranked_scores) else 0.0

    def __repr__(self) -> str:
        return (f"Recognition(best_place={self.best_place}, best_score={self.best_score:.3f}, "
                f"candidates={len(self.ranked_places)})")  # fmt: skip

    @property
    def won_without_boost(self) -> bool:
        """The best place would also be best on its stage-II score alone (no prior needed)."""
        return bool(len(self.spatial_scores)) and bool(self.spatial_scores[0] >= self.spatial_scores.max())


class TwoStageRanker:
    def __init__(self, config: VPRConfig, database: PlaceDatabase) -> None:
        self.config = config
        self.database = database
        database.configure_search(config.filtering)  # the database's stage-I index follows the config

    def query(
        self, codes: PlaceCodes, excluded: np.ndarray | None = None, boosted: np.ndarray | None = None
    ) -> Recognition:
        """Recognise one place. `boosted` places (a frame-correlation prior) join the candidates
        and get `frame_correlation.boost` added before scores are renormalised to [0, 1]."""
        if len(codes) != 1:
            raise LoopClosureInputError(f"query one place at a time, got {len(codes)}")
        if not codes.all_finite():
            raise LoopClosureInputError("query codes contain NaN or inf")
        filtering = self.config.filtering
        candidates = self.database.filter(codes.stage1[0], filtering.k_neighbours, filtering.num_candidates, excluded)
        return self.rerank(codes, candidates, boosted, excluded)

    def rerank(
        self,
        codes: PlaceCodes,
        candidates: Candidates,
        boosted: np.ndarray | None = None,
        excluded: np.ndarray | None = None,
        extra: np.ndarray | None = None,
    ) -> Recognition:
        """Stage II on given stage-I candidates (plus any boosted places not excluded, and
        `extra` places scored without a boost: the continuations of a sequence matcher)."""
        places = candidates.places
        if extra is not None and len(extra):
            places = np.concatenate([places, np.setdiff1d(np.asarray(extra, np.int64), places)])
        boost = np.zeros(len(places), np.float32)
        if boosted is not None and len(boosted):
            boosted = np.asarray(boosted, dtype=np.int64)
            boosted = boosted[(boosted >= 0) & (boosted < len(self.database))]
            if excluded is not None and len(excluded):
                boosted = np.setdiff1d(boosted, excluded)
            places = np.concatenate([places, np.setdiff1d(boosted, places)])
            boost = np.isin(places, boosted).astype(np.float32) * self.config.frame_correlation.boost
        if not len(places):
            empty = np.empty(0, np.float32)
            return Recognition(candidates, places, empty, np.empty((0, 2), np.int64), empty)

        spatial = stage2_scores(codes.stage2[0], self.database.stage2[places], self.config)
        final = (spatial.scores + boost) / (1.0 + float(boost.max(initial=0.0)))
        order = np.argsort(-final, kind="stable")
        return Recognition(candidates, places[order], final[order], spatial.shifts[order], spatial.scores[order])
