"""PCA codebooks: cube vectors (tens of thousands of dims) to compact codes.

Fitting uses scikit-learn; projection is a plain matrix product so a saved codebook needs
nothing but numpy to use.
"""

from __future__ import annotations

import io
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from loopclosure.config import PCAConfig
from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.atomic import atomic_write_bytes


@dataclass(frozen=True)
class PCAProjection:
    mean: np.ndarray  # (D,)
    components: np.ndarray  # (d, D)
    explained_variance: np.ndarray  # (d,)
    whiten: bool
    l2_normalize_output: bool

    @property
    def input_dim(self) -> int:
        return int(self.components.shape[1])

    @property
    def dim(self) -> int:
        return int(self.components.shape[0])

    def transform(self, x: np.ndarray) -> np.ndarray:
        """(..., D) -> (..., d) float32."""
        if x.shape[-1] != self.input_dim:
            raise LoopClosureInputError(f"PCA expects vectors of {self.input_dim} dims, got {x.shape[-1]}")
        lead = x.shape[:-1]
        y = (x.reshape(-1, self.input_dim) - self.mean) @ self.components.T
        if self.whiten:
            y /= np.sqrt(np.maximum(self.explained_variance, np.finfo(np.float32).eps))
        if self.l2_normalize_output:
            y /= np.maximum(np.linalg.norm(y, axis=1, keepdims=True), np.finfo(np.float32).tiny)
        return y.astype(np.float32, copy=False).reshape(*lead, self.dim)

    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        return {
            f"{prefix}mean": self.mean,
            f"{prefix}components": self.components,
            f"{prefix}explained_variance": self.explained_variance,
            f"{prefix}flags": np.array([self.whiten, self.l2_normalize_output]),
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], prefix: str) -> PCAProjection:
        flags = arrays[f"{prefix}flags"]
        return cls(
            mean=arrays[f"{prefix}mean"].astype(np.float32),
            components=arrays[f"{prefix}components"].astype(np.float32),
            explained_variance=arrays[f"{prefix}explained_variance"].astype(np.float32),
            whiten=bool(flags[0]),
            l2_normalize_output=bool(flags[1]),
        )


def fit_pca(samples: np.ndarray, config: PCAConfig, name: str = "PCA") -> PCAProjection:
    """Fit on (n, D) cube vectors; fewer samples than dimensions is an error, not a silent shrink."""
    from sklearn.decomposition import PCA

    if samples.ndim != 2:
        raise LoopClosureInputError(f"{name}: samples must be (n, D), got {samples.shape}")
    n, dim_in = samples.shape
    if min(n, config.max_fit_samples) < config.dim or dim_in < config.dim:
        raise LoopClosureInputError(
            f"{name}: {min(n, config.max_fit_samples)} samples of {dim_in} dims cannot give {config.dim} components; "
            + (
                "fit on more images or lower the PCA's dim (vpr.filtering.pca.dim / vpr.spatial.pca.dim)"
                if n < config.dim or dim_in < config.dim
                else "raise the PCA's max_fit_samples"
            )
        )
    if not np.isfinite(samples).all():
        raise LoopClosureInputError(f"{name}: samples contain NaN or inf")
    if n > config.max_fit_samples:
        rng = np.random.default_rng(config.seed)
        samples = samples[np.sort(rng.choice(n, config.max_fit_samples, replace=False))]
    solver = "randomized" if config.dim < 0.8 * min(samples.shape) else "full"
    pca = PCA(n_components=config.dim, svd_solver=solver, random_state=config.seed)
    pca.fit(samples.astype(np.float32, copy=False))
    return PCAProjection(
        mean=pca.mean_.astype(np.float32),
        components=pca.components_.astype(np.float32),
        explained_variance=pca.explained_variance_.astype(np.float32),
        whiten=config.whiten,
        l2_normalize_output=config.l2_normalize_output,
    )


@dataclass(frozen=True)
class Codebooks:
    """The two projections a database's codes were made with; they travel together."""

    stage1: PCAProjection
    stage2: PCAProjection

    def same_as(self, other: Codebooks) -> bool:
        """Both projections equal: codes made with either are comparable."""
        mine = {**self.stage1.to_arrays("stage1_"), **self.stage2.to_arrays("stage2_")}
        theirs = {**other.stage1.to_arrays("stage1_"), **other.stage2.to_arrays("stage2_")}
        return mine.keys() == theirs.keys() and all(np.array_equal(mine[k], theirs[k]) for k in mine)

    def save(self, path: str | Path) -> None:
        arrays = {**self.stage1.to_arrays("stage1_"), **self.stage2.to_arrays("stage2_")}
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub reads the first keyword as allow_pickle
        atomic_write_bytes(Path(path), buffer.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> Codebooks:
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = dict(data)
            books = cls(PCAProjection.from_arrays(arrays, "stage1_"), PCAProjection.from_arrays(arrays, "stage2_"))
        except FileNotFoundError:
            raise LoopClosureInputError(f"PCA codebooks not found: {path}") from None
        except (KeyError, ValueError, OSError, EOFError, IndexError, zipfile.BadZipFile, zlib.error) as exc:
            # a truncated or garbled .npz raises any of these, depending on where it was cut; numpy
            # takes a file that is neither .npz nor .npy for a pickle, and its advice does not apply
            why = (
                "neither an .npz archive nor an .npy array"
                if "allow_pickle" in str(exc)
                else f"{type(exc).__name__}: {exc}"
            )
            raise LoopClosureInputError(f"not a PCA codebook file: {path} ({why})") from None
        for name, p in (("stage1", books.stage1), ("stage2", books.stage2)):
            arrays_ok = (p.components.ndim == 2 and p.mean.shape == (p.input_dim,)
                         and p.explained_variance.shape == (p.dim,))  # fmt: skip
            if not arrays_ok or not all(np.isfinite(a).all() for a in (p.mean, p.components, p.explained_variance)):
                raise LoopClosureInputError(f"{path}: the {name} codebook's arrays are inconsistent or not finite")
        return books
