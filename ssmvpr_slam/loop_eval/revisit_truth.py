"""Ground truth of a loop-closure stream: which earlier frames each frame truly revisits.

Three sources, one answer per stream frame (a sorted set of earlier stream frames, maybe empty):
* two passes of one route streamed one after the other: frame i of the second revisits frame
  i of the first (or the pairs of a `vpr-eval` ground-truth file);
* ground-truth poses: an earlier frame within `radius` metres, outside the detector's exclusion
  window (never a candidate, so never a loop to miss);
* a square 0/1 loop matrix as the loop-closure literature publishes them (.npy, .csv, MATLAB
  .mat), symmetrised, outside the exclusion window too. Only 0/1 (or true/false) is read as
  loops: a similarity matrix (0.05 .. 0.95) read as "non-zero is a loop" made every pair a
  revisit and the recall meaningless, so other values are refused unless a threshold is given.
A loop q -> m is correct when m lies within `tolerance` frames of a true place of q, or, with
poses, within `radius` metres of q.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from loopclosure.benchmark_truth import GroundTruth, load_ground_truth
from ssmvpr_common.quoting import shortened
from ssmvpr_slam.errors import SlamError


class LoopTruthError(SlamError, ValueError):
    """A ground truth that cannot judge this stream (names the file and what is wrong)."""


@dataclass(frozen=True)
class LoopTruth:
    matches: tuple[np.ndarray, ...]  # per stream frame: sorted earlier stream frames it truly revisits
    passes: np.ndarray  # (N,) which pass each stream frame belongs to (all 0 for one sequence)
    tolerance: int  # ± frames around a true place that still count as correct
    positions: np.ndarray | None = None  # (N, 3) ground-truth positions: loops judged by distance
    radius: float = 0.0
    source: str = ""

    def __len__(self) -> int:
        return len(self.matches)

    @property
    def has_truth(self) -> np.ndarray:
        return np.fromiter((len(m) > 0 for m in self.matches), bool, len(self.matches))

    def correct(self, query: int, match: int) -> bool:
        if self.positions is not None:
            return bool(np.linalg.norm(self.positions[query] - self.positions[match]) <= self.radius)
        true = self.matches[query]
        return bool(len(true) and np.min(np.abs(true - match)) <= self.tolerance)


def two_passes(
    first: Sequence[Path], second: Sequence[Path], ground_truth: Path | None, tolerance: int
) -> tuple[LoopTruth, GroundTruth]:
    """FIRST then SECOND as one stream: SECOND frame i revisits FIRST frame i (frame-aligned
    names), or the references a `vpr-eval` ground-truth file lists for it."""
    gt = load_ground_truth(ground_truth, list(first), list(second))
    n1 = len(first)
    matches = tuple([np.zeros(0, np.int64)] * n1 + [np.asarray(r, np.int64) for r in gt.refs])
    passes = np.r_[np.zeros(n1, np.int64), np.ones(len(second), np.int64)]
    return LoopTruth(matches, passes, tolerance, source=gt.source or "frame-aligned"), gt


def excluded(query: int, earlier: np.ndarray, travelled: np.ndarray, keyframes: int, distance: float) -> np.ndarray:
    """Which `earlier` frames the detector never considers for `query` (its exclusion window)."""
    return (query - earlier < keyframes) | (travelled[query] - travelled[earlier] < distance)


def from_poses(
    positions: np.ndarray, radius: float, travelled: np.ndarray, exclusion_keyframes: int, exclusion_distance: float
) -> LoopTruth:
    """A revisit is an earlier frame within `radius` metres, outside the exclusion window."""
    if radius <= 0:
        raise LoopTruthError(f"--radius must be positive, got {radius}")
    pos = np.asarray(positions, np.float64)
    matches = []
    for q in range(len(pos)):
        near = np.flatnonzero(np.linalg.norm(pos[:q] - pos[q], axis=1) <= radius)
        matches.append(near[~excluded(q, near, travelled, exclusion_keyframes, exclusion_distance)])
    return LoopTruth(tuple(matches), np.zeros(len(pos), np.int64), 0, pos, radius)


def read_matrix(path: Path, threshold: float | None = None) -> np.ndarray:
    """A square boolean loop matrix from .npy, .csv (comma or whitespace separated) or MATLAB
    .mat (v4-v7; the one square numeric variable in it). Without `threshold` it must hold 0/1;
    with it, values >= threshold are loops."""
    if not path.is_file():
        raise LoopTruthError(f"{path}: no such ground-truth matrix file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            matrix = np.load(path, allow_pickle=False)
        elif suffix in (".csv", ".txt"):
            text = path.read_text(encoding="utf-8", errors="strict")
            matrix = np.loadtxt(text.splitlines(), delimiter="," if "," in text else None, ndmin=2)
        elif suffix == ".mat":
            matrix = _mat_variable(path)
        else:
            raise LoopTruthError(f"{path}: unknown loop-matrix format {path.suffix!r}; use .npy, .csv or .mat")
    except LoopTruthError:
        raise
    except (ValueError, OSError, UnicodeDecodeError, NotImplementedError) as exc:
        raise LoopTruthError(
            f"{path}: not a readable loop matrix ({type(exc).__name__}: {shortened(str(exc))})"
        ) from None
    matrix = np.asarray(matrix)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or matrix.dtype.kind not in "biuf":
        raise LoopTruthError(f"{path}: a loop matrix must be square and numeric, got {matrix.dtype} {matrix.shape}")
    if matrix.dtype.kind == "f" and not np.isfinite(matrix).all():
        raise LoopTruthError(f"{path}: the loop matrix holds NaN or inf")
    if threshold is not None:
        return matrix >= threshold
    _check_zero_one(path, matrix)
    return matrix != 0


def _check_zero_one(path: Path, matrix: np.ndarray) -> None:
    """Refuse values other than 0 and 1, naming how many and their range."""
    if matrix.dtype.kind == "b":
        return
    other = matrix[(matrix != 0) & (matrix != 1)]
    if other.size:
        low, high = float(other.min()), float(other.max())
        found = f"of {low:.4g}" if low == high else f"between {low:.4g} and {high:.4g}"
        raise LoopTruthError(
            f"{path}: {other.size:,} values {found}, not 0/1; a loop matrix holds 0 or 1 "
            "(false/true): for a similarity matrix give --gt-threshold T (values >= T are loops)"
        )


def _mat_variable(path: Path) -> np.ndarray:
    from scipy.io import loadmat

    try:
        data = loadmat(str(path))
    except NotImplementedError:
        raise LoopTruthError(f"{path}: a MATLAB v7.3 (HDF5) file; save it with -v7 or convert it to .npy") from None
    square = {k: v for k, v in data.items() if not k.startswith("__") and np.ndim(v) == 2 and v.shape[0] == v.shape[1]}
    if len(square) != 1:
        names = ", ".join(sorted(square)) or "none"
        raise LoopTruthError(f"{path}: expected one square matrix variable, found {len(square)} ({names})")
    return np.asarray(next(iter(square.values())))


def from_matrix(
    path: Path,
    n_frames: int,
    tolerance: int,
    travelled: np.ndarray,
    exclusion_keyframes: int,
    exclusion_distance: float,
    threshold: float | None = None,
) -> LoopTruth:
    """Frame q revisits every earlier j with M[q, j] or M[j, q] set (>= `threshold` if given),
    outside the exclusion window."""
    matrix = read_matrix(path, threshold)
    if matrix.shape[0] != n_frames:
        raise LoopTruthError(f"{path}: a {matrix.shape[0]}x{matrix.shape[0]} loop matrix for {n_frames} images")
    either = matrix | matrix.T
    matches = []
    for q in range(n_frames):
        earlier = np.flatnonzero(either[q, :q])
        matches.append(earlier[~excluded(q, earlier, travelled, exclusion_keyframes, exclusion_distance)])
    return LoopTruth(tuple(matches), np.zeros(n_frames, np.int64), tolerance, source=str(path))
