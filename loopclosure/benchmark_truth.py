"""Ground truth for a reference-folder + query-folder VPR benchmark.

A benchmark's truth is, per query, the set of reference indices that show the same place.
Sets (not a single index) because benchmarks disagree: VPR-Bench lists several references per
query, Berlin-style CSVs may too, and a frame-aligned pair of folders has exactly one. The
evaluation tolerance (the paper's ±2 frames) is applied on top of these sets by
:func:`correct_mask`, never baked in here. A file whose queries already list a window of
consecutive references (VPR-Bench's Corridor: query q -> q-2..q+2) carries its own tolerance, so
a tolerance on top widens it (±2 on ±2 counts ±4): :func:`truth_windows` finds such files, and
``vpr-eval`` warns and records it.
"""

from __future__ import annotations

import csv
import io
import pickle
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import numpy as np

from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.quoting import quoted, shortened

__all__ = [
    "GroundTruth",
    "TruthWindows",
    "correct_mask",
    "frame_aligned",
    "from_csv",
    "from_vprbench_npy",
    "is_correct",
    "load_ground_truth",
    "truth_windows",
]

_OTHER_FORMS = (
    "give a ground-truth file instead: a VPR-Bench .npy (rows [query_index, [ref indices]]) "
    "or a .csv with Reference,Live or Serial No,Query,Ref columns"
)


@dataclass(frozen=True)
class GroundTruth:
    """Per query index, the sorted reference indices that are a true match (may be empty)."""

    refs: tuple[np.ndarray, ...]
    n_ref: int
    n_query: int
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if len(self.refs) != self.n_query:
            raise LoopClosureInputError(f"ground truth: {len(self.refs)} query entries for n_query={self.n_query}")
        for q, r in enumerate(self.refs):
            if r.ndim != 1 or (r.size > 1 and np.any(np.diff(r) <= 0)):
                raise LoopClosureInputError(f"ground truth: query {q} reference indices are not a sorted 1-D set")
            if r.size and (r[0] < 0 or r[-1] >= self.n_ref):
                raise LoopClosureInputError(
                    f"ground truth: query {q} has reference indices outside 0..{self.n_ref - 1}"
                )

    @property
    def has_truth(self) -> np.ndarray:
        """Boolean mask of the queries that have at least one true reference."""
        return np.fromiter((r.size > 0 for r in self.refs), dtype=bool, count=self.n_query)

    @classmethod
    def from_sets(cls, sets: Sequence[Iterable[int]], n_ref: int, source: str = "") -> GroundTruth:
        """Build from one iterable of reference indices per query (sorted, deduplicated)."""
        refs = tuple(np.unique(np.asarray(list(s), dtype=np.int64)) for s in sets)
        return cls(refs=refs, n_ref=int(n_ref), n_query=len(refs), source=source)


# --------------------------------------------------------------------------- loaders


def frame_aligned(ref_files: Sequence[object], query_files: Sequence[object]) -> GroundTruth:
    """Query i <-> reference i: the default when both folders are the same traverse, in step."""
    n_ref, n_query = len(ref_files), len(query_files)
    if n_ref != n_query:
        raise LoopClosureInputError(
            f"frame-aligned ground truth needs as many query images as reference images, "
            f"got {n_query} query and {n_ref} reference; {_OTHER_FORMS}"
        )
    return GroundTruth.from_sets([[i] for i in range(n_query)], n_ref, source="frame-aligned")


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Admits the few globals an object-dtype .npy needs, so a GT file cannot run code."""

    _ALLOWED = {
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("_codecs", "encode"),
    }

    def find_class(self, module: str, name: str) -> object:
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed")
        if module == "_codecs":
            import codecs

            return codecs.encode
        if module.startswith("numpy.") and name in ("_reconstruct", "scalar"):
            from numpy._core import multiarray  # numpy>=2 home of numpy.core.multiarray

            return getattr(multiarray, name)
        return getattr(np, name)


def _load_npy(path: Path) -> np.ndarray:
    """np.load, but object arrays go through an unpickler that admits numpy arrays only."""
    from numpy.lib import format as npy_format

    try:
        with path.open("rb") as fh:
            version = npy_format.read_magic(fh)
            if version == (1, 0):
                _, _, dtype = npy_format.read_array_header_1_0(fh)
            else:
                _, _, dtype = npy_format.read_array_header_2_0(fh)
            if not dtype.hasobject:
                fh.seek(0)
                return np.load(fh, allow_pickle=False)
            data = _NumpyOnlyUnpickler(io.BytesIO(fh.read())).load()
    except (OSError, ValueError, EOFError, pickle.UnpicklingError) as exc:
        raise LoopClosureInputError(f"ground truth {path}: not a readable .npy file ({exc})") from exc
    if not isinstance(data, np.ndarray):
        raise LoopClosureInputError(f"ground truth {path}: does not hold a numpy array")
    return data


def _as_int(value: object, what: str) -> int:
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return int(value)
    try:
        as_float = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise LoopClosureInputError(f"{what}: {shortened(repr(value))} is not an integer index") from None
    if not as_float.is_integer():
        raise LoopClosureInputError(f"{what}: {shortened(repr(value))} is not an integer index")
    return int(as_float)


def from_vprbench_npy(path: str | Path, n_ref: int, n_query: int) -> GroundTruth:
    """VPR-Bench ``ground_truth_new.npy``: rows ``[query_index, [ref indices]]`` or ``[q, ref]``."""
    path = Path(path)
    data = _load_npy(path)
    if data.ndim == 0:
        raise LoopClosureInputError(f"ground truth {path}: expected rows [query_index, ref indices]")
    sets: list[set[int]] = [set() for _ in range(n_query)]
    for row_no, row in enumerate(data):
        if np.ndim(row) == 0 or len(row) != 2:
            raise LoopClosureInputError(
                f"ground truth {path} row {row_no}: expected [query_index, ref indices], got {shortened(repr(row))}"
            )
        q = _as_int(row[0], f"ground truth {path} row {row_no} query index")
        if not 0 <= q < n_query:
            raise LoopClosureInputError(
                f"ground truth {path} row {row_no}: query index {q} exceeds the query folder "
                f"({n_query} images, valid 0..{n_query - 1})"
            )
        for r in np.atleast_1d(np.asarray(row[1], dtype=object)).ravel():
            ref = _as_int(r, f"ground truth {path} row {row_no} reference index")
            if not 0 <= ref < n_ref:
                raise LoopClosureInputError(
                    f"ground truth {path} row {row_no} (query {q}): reference index {ref} exceeds "
                    f"the reference folder ({n_ref} images, valid 0..{n_ref - 1})"
                )
            sets[q].add(ref)
    return GroundTruth.from_sets(sets, n_ref, source=str(path))


# --------------------------------------------------------------------------- CSV

_QUERY_COLUMNS = ("live", "query")
_REF_COLUMNS = ("reference", "ref", "references", "refs")
_MULTI_SEP = re.compile(r"[;\s|]+")
_INT = re.compile(r"^[+-]?\d+(\.0*)?$")


def _norm_header(name: str) -> str:
    return re.sub(r"[\s_]+", "", name.strip().lstrip("\ufeff")).lower()


class _FolderIndex:
    """Resolves CSV cells to indices in one folder: by basename, with or without extension."""

    def __init__(self, files: Sequence[object], label: str) -> None:
        self.label, self.n = label, len(files)
        self.by_name: dict[str, int] = {}
        for i, f in enumerate(files):
            p = PurePath(str(f))
            for key in {p.name, p.stem}:
                # -1 marks a basename shared by two files: ambiguous, refused on lookup.
                self.by_name[key] = -1 if key in self.by_name else i
        self.example = PurePath(str(files[0])).name if files else "(empty)"

    def _lookup(self, token: str) -> int | None:
        """Index of the file the cell names, -1 if several match, None if none does."""
        return self.by_name.get(PurePath(token.replace("\\", "/")).name)

    def resolve_column(self, tokens: list[str], path: Path, column: str) -> list[int]:
        """Filenames if every cell names a file here; else integer indices; else an error."""
        looked = [self._lookup(t) for t in tokens]
        if all(i is not None for i in looked):
            for t, i in zip(tokens, looked):
                if i == -1:
                    raise LoopClosureInputError(
                        f"ground truth {path}: {column} {quoted(t)} matches several files in the {self.label} folder"
                    )
            return [int(i) for i in looked]  # type: ignore[arg-type]
        if all(_INT.match(t) for t in tokens):
            out = [int(t.split(".")[0]) for t in tokens]
            for t, i in zip(tokens, out):
                if not 0 <= i < self.n:
                    raise LoopClosureInputError(
                        f"ground truth {path}: {column} index {t} is outside the {self.label} folder "
                        f"({self.n} images, valid 0..{self.n - 1})"
                    )
            return out
        bad = next(t for t, i in zip(tokens, looked) if i is None and not _INT.match(t))
        raise LoopClosureInputError(
            f"ground truth {path}: {column} {quoted(bad)} is not a file in the {self.label} folder "
            f"({self.n} images, e.g. {self.example}) nor an integer index"
        )


def _read_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise LoopClosureInputError(f"ground truth {path}: cannot read ({exc})") from exc
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise LoopClosureInputError(f"ground truth {path}: the CSV file is empty")
    delimiter = "," if "," in lines[0] or "\t" not in lines[0] else "\t"
    reader = csv.reader(lines, delimiter=delimiter)
    try:
        rows = [[c.strip() for c in r] for r in reader]
    except csv.Error as exc:  # a cell past the csv module's limit (128 KiB), a NUL byte: not a ground truth
        raise LoopClosureInputError(
            f"ground truth {path}: not a readable CSV file (row {reader.line_num}: {exc})"
        ) from None
    return rows[0], rows[1:]


def from_csv(path: str | Path, ref_files: Sequence[object], query_files: Sequence[object]) -> GroundTruth:
    """CSV ground truth: SSM-VPR ``Reference,Live`` or Berlin ``Serial No,Query,Ref`` columns.

    Cells hold filenames (matched by basename, extension optional) or 0-based indices; one
    column is read one way throughout. A Ref cell may list several references separated by
    spaces or semicolons, and a query may appear on several rows. An empty Ref cell, or a
    query that appears on no row, means the query has no true match.
    """
    path = Path(path)
    header, rows = _read_rows(path)
    names = [_norm_header(h) for h in header]
    q_col = next((names.index(c) for c in _QUERY_COLUMNS if c in names), None)
    r_col = next((names.index(c) for c in _REF_COLUMNS if c in names), None)
    if q_col is None or r_col is None:
        raise LoopClosureInputError(
            f"ground truth {path}: header {shortened(str(header))} needs a query column (Live or Query) and a "
            f"reference column (Reference or Ref)"
        )
    query_tokens: list[str] = []
    ref_tokens: list[list[str]] = []
    for line_no, row in enumerate(rows, start=2):
        if q_col >= len(row) or not row[q_col]:
            raise LoopClosureInputError(f"ground truth {path} line {line_no}: no {header[q_col]} value")
        cells = row[r_col:] if r_col == len(header) - 1 else row[r_col : r_col + 1]
        query_tokens.append(row[q_col])
        ref_tokens.append([t for c in cells for t in _MULTI_SEP.split(c) if t])
    queries = _FolderIndex(query_files, "query").resolve_column(query_tokens, path, header[q_col])
    flat = [t for ts in ref_tokens for t in ts]
    flat_idx = _FolderIndex(ref_files, "reference").resolve_column(flat, path, header[r_col]) if flat else []
    sets: list[set[int]] = [set() for _ in range(len(query_files))]
    pos = 0
    for q, ts in zip(queries, ref_tokens):
        sets[q].update(flat_idx[pos : pos + len(ts)])
        pos += len(ts)
    return GroundTruth.from_sets(sets, len(ref_files), source=str(path))


def load_ground_truth(
    spec: str | Path | None, ref_files: Sequence[object], query_files: Sequence[object]
) -> GroundTruth:
    """None -> frame-aligned; ``.npy`` -> VPR-Bench; ``.csv`` -> SSM-VPR / Berlin CSV."""
    if spec is None:
        return frame_aligned(ref_files, query_files)
    path = Path(spec)
    if not path.is_file():
        raise LoopClosureInputError(f"ground truth file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return from_vprbench_npy(path, len(ref_files), len(query_files))
    if suffix == ".csv":
        return from_csv(path, ref_files, query_files)
    raise LoopClosureInputError(
        f"ground truth file {path}: unknown suffix {path.suffix!r}; use .npy (VPR-Bench) or .csv"
    )


# --------------------------------------------------------------------------- correctness


def _check_tolerance(tolerance: int) -> int:
    if isinstance(tolerance, bool) or int(tolerance) != tolerance or tolerance < 0:
        raise LoopClosureInputError(f"tolerance must be a non-negative integer, got {tolerance!r}")
    return int(tolerance)


def is_correct(gt: GroundTruth, query_idx: int, ref_idx: int, tolerance: int) -> bool:
    """Whether ref_idx lies within ±tolerance of one of the query's true references."""
    tol = _check_tolerance(tolerance)
    if not 0 <= query_idx < gt.n_query:
        raise LoopClosureInputError(f"query index {query_idx} outside 0..{gt.n_query - 1}")
    truth = gt.refs[query_idx]
    return bool(truth.size and np.min(np.abs(truth - int(ref_idx))) <= tol) and ref_idx >= 0


def correct_mask(gt: GroundTruth, matches: np.ndarray, tolerance: int) -> np.ndarray:
    """Vectorised :func:`is_correct`: matches is (n_query,) or (n_query, k) reference indices.

    Negative entries mean "no match" (e.g. padding of short candidate lists) and are never
    correct. Implemented with one sorted key array, so it stays O((n_gt + n_match) log n_gt)
    instead of a dense n_query x n_ref table.
    """
    tol = _check_tolerance(tolerance)
    m = np.asarray(matches)
    if m.ndim not in (1, 2) or m.shape[0] != gt.n_query:
        raise LoopClosureInputError(f"matches: expected shape ({gt.n_query},) or ({gt.n_query}, k), got {m.shape}")
    if m.size and not np.issubdtype(m.dtype, np.integer):
        if not np.all(np.isfinite(m)) or not np.all(m == np.round(m)):
            raise LoopClosureInputError("matches: reference indices must be integers")
    m2 = m.reshape(gt.n_query, -1).astype(np.int64)
    if m2.size and m2.max() >= gt.n_ref:
        raise LoopClosureInputError(
            f"matches: reference index {int(m2.max())} exceeds the reference set ({gt.n_ref} images)"
        )
    stride = gt.n_ref + 2 * tol + 1  # one disjoint key range per query
    counts = np.fromiter((r.size for r in gt.refs), dtype=np.int64, count=gt.n_query)
    gt_q = np.repeat(np.arange(gt.n_query, dtype=np.int64), counts)
    gt_r = np.concatenate(gt.refs) if gt.n_query else np.zeros(0, np.int64)
    keys = gt_q * stride + tol + gt_r.astype(np.int64)  # sorted: by query, then ref
    base = np.arange(gt.n_query, dtype=np.int64)[:, None] * stride
    lo = np.searchsorted(keys, base + m2, side="left")
    hi = np.searchsorted(keys, base + m2 + 2 * tol, side="right")
    return ((hi > lo) & (m2 >= 0)).reshape(m.shape)


# --------------------------------------------------------------------------- windows


@dataclass(frozen=True)
class TruthWindows:
    """How many queries list a run of consecutive references: a window that already holds a
    frame tolerance, so the evaluation tolerance widens it instead of being the whole margin."""

    queries: int
    """Queries whose reference set holds at least two consecutive indices."""
    with_truth: int
    """Queries with at least one true reference."""
    median_refs: float
    """Median number of references of those window queries (0 when there are none)."""

    @property
    def windowed(self) -> bool:
        """At least half the queries with truth list a window: the file's own tolerance."""
        return self.queries > 0 and 2 * self.queries >= self.with_truth


def _has_run(refs: np.ndarray) -> bool:
    return bool(refs.size > 1 and np.any(np.diff(refs) == 1))


def truth_windows(gt: GroundTruth) -> TruthWindows:
    """Count the queries listing consecutive references (VPR-Bench's ±2-frame windows)."""
    sizes = [r.size for r in gt.refs if _has_run(r)]
    median = float(np.median(sizes)) if sizes else 0.0
    return TruthWindows(queries=len(sizes), with_truth=int(gt.has_truth.sum()), median_refs=median)
