"""PlaceDatabase: the growing map of places, their codes, and the codebooks that made them.

Places are appended one at a time (streaming SLAM) or in batches (a reference folder).
Storage grows by doubling so appends are amortised O(1). On disk a database is a folder:
arrays in .npy files, the codebooks, and a versioned manifest written last. Every file is
replaced atomically and the manifest records how many places are valid, so a crash while
saving leaves the previous consistent state readable.

Codes are stored as float32, float16, or int8 with one float32 scale per vector
(`vpr.database.stage1_dtype` / `stage2_dtype`). An int8 code quantises the vector divided by
its stage's per-dimension spread w (sqrt of each PCA component's variance, from the map's own
codebooks), so the low-variance components keep their precision: it reads back as
q * s * w in float32. On Corridor that halved the error (1.07 % -> 0.63 % of the norm) and
kept every stage-II top-1 (docs/benchmarks.md, "Speed").

A saved map can also be opened memory-mapped (`load(folder, mmap=True)`: nothing is read
until used, so a map larger than RAM opens at once) and grown in place (`open(folder)`, then
`add` and `commit`): new rows are written after the last row of each .npy file, the file's
header is given the new row count in place (numpy pads headers so the count can grow without
moving the data), then places.json is replaced and the manifest last. The manifest is the
commit point: a crash anywhere before it leaves the previous count readable; rows past it are
ignored on load and cut off when the map is next opened for appending.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from pydantic import ValidationError

from loopclosure.config import DatabaseConfig, FilteringConfig
from loopclosure.device_search import check_search_device
from loopclosure.encoder import PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.filtering import Candidates, empty_candidates, max_row_norm, rank_neighbours, vote
from loopclosure.pca import Codebooks
from ssmvpr_common.atomic import atomic_write, atomic_write_text
from ssmvpr_common.disk_full import writing

FORMAT = "ssmvpr-place-database"
FORMAT_VERSION = 1  # float codes only: what every earlier build reads
FORMAT_VERSION_INT8 = 2  # int8 codes with their scale files
READ_VERSIONS = (FORMAT_VERSION, FORMAT_VERSION_INT8)
MANIFEST = "manifest.json"
STAGES = ("stage1", "stage2")


@dataclass
class PlaceInfo:
    """What the caller wants back about a place: its frame/keyframe id, time and a name."""

    frame_id: int
    timestamp: float = float("nan")
    name: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def _plain_info(info: PlaceInfo, where: str) -> PlaceInfo:
    """`info` with a plain int id, float time and str name (numpy scalars made plain, JSON
    writes them), or an error naming `where`: `add` refuses now what `load` would refuse after a
    save, and `load` refuses what a damaged places.json holds, by the same rules."""
    if not isinstance(info.frame_id, (int, np.integer)) or isinstance(info.frame_id, bool):
        raise LoopClosureInputError(f"{where} frame_id must be an integer, got {info.frame_id!r:.60}")
    if not isinstance(info.timestamp, (int, float, np.integer, np.floating)) or isinstance(info.timestamp, bool):
        raise LoopClosureInputError(f"{where} timestamp must be a number, got {info.timestamp!r:.60}")
    if not isinstance(info.name, str):
        raise LoopClosureInputError(f"{where} name must be a string, got {info.name!r:.60}")
    return replace(info, frame_id=int(info.frame_id), timestamp=float(info.timestamp))


# ---- row stores: RAM (capacity doubling) or a .npy file appended in place ---------------------
class _GrowingArray:
    """A numpy array that appends along axis 0 with capacity doubling."""

    def __init__(self, row_shape: tuple[int, ...], dtype: np.dtype, data: np.ndarray | None = None) -> None:
        self.row_shape = tuple(row_shape)
        self._data = np.empty((0, *row_shape), dtype) if data is None else np.ascontiguousarray(data, dtype)
        self._size = len(self._data)

    def extend(self, rows: np.ndarray) -> None:
        needed = self._size + len(rows)
        if needed > len(self._data):
            grown = np.empty((max(needed, 2 * len(self._data), 16), *self.row_shape), self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown
        self._data[self._size : needed] = rows
        self._size = needed

    @property
    def view(self) -> np.ndarray:
        return self._data[: self._size]

    def copy(self) -> _GrowingArray:
        return _GrowingArray(self.row_shape, self._data.dtype, self.view.copy())


class _MappedArray:
    """Rows of a .npy file, memory-mapped; appends (when writable) go to the file itself."""

    def __init__(self, path: Path, n: int, writable: bool) -> None:
        self.path = path
        self.writable = writable
        with open(path, "rb") as handle:
            version = np.lib.format.read_magic(handle)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read(handle)
            self._offset = handle.tell()
        if fortran or not shape:
            raise LoopClosureInputError(f"{path}: not a C-ordered array of codes")
        self._version, self.dtype, self.row_shape = version, np.dtype(dtype), tuple(shape[1:])
        self._row_bytes = int(np.prod(self.row_shape, dtype=np.int64)) * self.dtype.itemsize
        self._size = n
        if writable:  # cut off rows a crash left past the committed count
            os.truncate(path, self._offset + n * self._row_bytes)
            self._write_header(n)
        self._map()

    def _map(self) -> None:
        if self._size == 0:
            self._view = np.empty((0, *self.row_shape), self.dtype)
        else:
            self._view = np.memmap(self.path, self.dtype, "r", self._offset, (self._size, *self.row_shape))

    def _write_header(self, rows: int) -> None:
        """The row count, rewritten in place at the same length (numpy leaves room to grow)."""
        import io

        header = io.BytesIO()
        d = {
            "descr": np.lib.format.dtype_to_descr(self.dtype),
            "fortran_order": False,
            "shape": (rows, *self.row_shape),
        }
        write = (
            np.lib.format.write_array_header_1_0 if self._version == (1, 0) else np.lib.format.write_array_header_2_0
        )
        write(header, d)  # the padding rule np.save uses: room for a 21-digit row count
        if header.tell() != self._offset:
            raise LoopClosureInputError(
                f"{self.path}: its header cannot grow in place ({header.tell()} != {self._offset} bytes)"
            )
        with open(self.path, "r+b") as handle:
            handle.write(header.getvalue())
            handle.flush()
            os.fsync(handle.fileno())

    def extend(self, rows: np.ndarray) -> None:
        if not self.writable:
            raise RuntimeError(f"{self.path} is mapped read-only")
        rows = np.ascontiguousarray(rows, self.dtype)
        with writing(self.path), open(self.path, "r+b") as handle:  # data first, then the header's count
            handle.seek(self._offset + self._size * self._row_bytes)
            handle.write(rows.tobytes())
            handle.flush()
            os.fsync(handle.fileno())
        self._size += len(rows)
        self._write_header(self._size)
        self._map()

    @property
    def view(self) -> np.ndarray:
        return self._view

    def copy(self) -> _GrowingArray:
        return _GrowingArray(self.row_shape, self.dtype, np.array(self._view))


def code_weights(projection: Any) -> np.ndarray:
    """(d,) float32 per-dimension spread of a stage's codes: sqrt of each PCA component's
    variance relative to the largest (1 when the PCA whitens), floored at 1e-3."""
    dim = int(projection.dim)
    if projection.whiten:
        return np.ones(dim, np.float32)
    spread = np.sqrt(np.maximum(np.asarray(projection.explained_variance, np.float64), 0.0))
    if not spread.size or not np.isfinite(spread).all() or spread.max() <= 0:
        return np.ones(dim, np.float32)
    return np.maximum(spread / spread.max(), 1e-3).astype(np.float32)


def quantise(values: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """int8 codes and one float32 scale per vector (last axis): x ~ q * s * w, s = max|x / w| / 127."""
    values = np.asarray(values, np.float32)
    if weights is not None:
        values = values / weights
    scale = (np.abs(values).max(axis=-1) / np.float32(127.0)).astype(np.float32)
    safe = np.where(scale > 0, scale, np.float32(1.0))
    codes = np.clip(np.rint(values / safe[..., None]), -127, 127).astype(np.int8)
    return codes, scale


def dequantise(codes: np.ndarray, scale: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """float32 q * s * w, elementwise (the same value whichever rows are read together)."""
    out = codes.astype(np.float32) * np.asarray(scale, np.float32)[..., None]
    return out if weights is None else out * weights


class QuantisedArray:
    """int8 codes with a scale per vector that read as float32 when indexed or converted."""

    def __init__(self, codes: np.ndarray, scale: np.ndarray, weights: np.ndarray | None = None) -> None:
        self.codes, self.scale, self.weights = codes, scale, weights

    shape = property(lambda self: self.codes.shape)
    ndim = property(lambda self: self.codes.ndim)
    dtype = np.dtype(np.float32)

    @property
    def nbytes(self) -> int:
        """Bytes stored (codes and scales), not the float32 size it reads as."""
        return int(self.codes.nbytes + self.scale.nbytes)

    def __len__(self) -> int:
        return len(self.codes)

    def __getitem__(self, index: Any) -> np.ndarray:
        return dequantise(self.codes[index], self.scale[index], self.weights)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = dequantise(self.codes, self.scale, self.weights)
        return out if dtype is None else out.astype(dtype)


class _Codes:
    """One stage's codes: a row store of the storage dtype, plus a scale store for int8."""

    def __init__(self, values: Any, scales: Any | None, weights: np.ndarray | None = None) -> None:
        self.values, self.scales, self.weights = values, scales, weights

    @classmethod
    def empty(cls, row_shape: tuple[int, ...], dtype: str, weights: np.ndarray) -> _Codes:
        if dtype == "int8":
            scales = _GrowingArray(row_shape[:-1], np.dtype(np.float32))
            return cls(_GrowingArray(row_shape, np.dtype(np.int8)), scales, weights)
        return cls(_GrowingArray(row_shape, np.dtype(dtype)), None)

    @property
    def row_shape(self) -> tuple[int, ...]:
        return self.values.row_shape

    def extend(self, values: np.ndarray) -> None:
        if self.scales is None:
            self.values.extend(values)
            return
        codes, scale = quantise(values, self.weights)
        self.scales.extend(scale)  # scales first: the codes' file decides nothing on its own
        self.values.extend(codes)

    @property
    def view(self) -> np.ndarray | QuantisedArray:
        return (
            self.values.view
            if self.scales is None
            else QuantisedArray(self.values.view, self.scales.view, self.weights)
        )

    def flat_rows(self, start: int, stop: int | None) -> np.ndarray:
        """Vectors [start, stop) of the (N, d) flattening, as float32."""
        d = self.row_shape[-1]
        values = self.values.view.reshape(-1, d)[start:stop]
        if self.scales is None:
            return values.astype(np.float32, copy=False)
        return dequantise(values, self.scales.view.reshape(-1)[start:stop], self.weights)

    def flat_rows_at(self, ids: np.ndarray) -> np.ndarray:
        d = self.row_shape[-1]
        values = self.values.view.reshape(-1, d)[ids]
        return values if self.scales is None else dequantise(values, self.scales.view.reshape(-1)[ids], self.weights)

    def place_bytes(self) -> int:
        row = int(np.prod(self.row_shape)) * self.values.view.dtype.itemsize
        return row + (int(np.prod(self.row_shape[:-1])) * 4 if self.scales is not None else 0)

    def copy(self) -> _Codes:
        return _Codes(self.values.copy(), None if self.scales is None else self.scales.copy(), self.weights)


class PlaceDatabase:
    def __init__(self, codebooks: Codebooks, config: DatabaseConfig | None = None) -> None:
        self.codebooks = codebooks
        self.config = config or DatabaseConfig()
        self._codes: dict[str, _Codes] = {}
        self.places: list[PlaceInfo] = []
        self.extra: dict[str, Any] = {}  # the manifest's free-form record (e.g. encoder settings)
        self.filtering = FilteringConfig()  # how stage I searches (TwoStageRanker sets the configured one)
        self._index = None  # loopclosure.ann_index.StageOneIndex, built on the first query
        self._max_norm: float | None = None  # numpy mode: bound on stage-I norms, for exact votes
        self._folder: Path | None = None  # the folder appends go to (open())

    def __len__(self) -> int:
        return len(self.places)

    def _stage(self, name: str) -> np.ndarray | QuantisedArray:
        if name in self._codes:
            return self._codes[name].view
        dim = self.codebooks.stage1.dim if name == "stage1" else self.codebooks.stage2.dim
        return np.empty((0, 0, dim) if name == "stage1" else (0, 0, 0, dim))

    @property
    def stage1(self) -> np.ndarray | QuantisedArray:
        """(P, n1, d1) stage-I codes of all places (int8 storage reads as float32 when indexed)."""
        return self._stage("stage1")

    @property
    def stage2(self) -> np.ndarray | QuantisedArray:
        """(P, gh, gw, d2) stage-II grids of all places (int8 storage reads as float32 when indexed)."""
        return self._stage("stage2")

    @property
    def bytes_per_place(self) -> int:
        """Stored bytes of one place's codes (int8: codes and their float32 scales)."""
        if not len(self):
            return 0
        return sum(codes.place_bytes() for codes in self._codes.values())

    @property
    def memory_mapped(self) -> bool:
        return bool(self._codes) and isinstance(self._codes["stage1"].values, _MappedArray)

    def add(self, codes: PlaceCodes, infos: list[PlaceInfo] | PlaceInfo | None = None) -> list[int]:
        """Append places; returns their database indices. A database from `open` writes the
        codes to its files at once; `commit` makes them part of the saved map."""
        if isinstance(infos, PlaceInfo):
            infos = [infos]
        first = len(self)
        if infos is None:
            infos = [PlaceInfo(frame_id=first + i) for i in range(len(codes))]
        self._check_codes(codes)
        if len(infos) != len(codes):
            raise LoopClosureInputError(f"{len(codes)} codes but {len(infos)} place infos")
        infos = [_plain_info(info, "place info") for info in infos]  # what save() writes and load() checks
        if not self._codes:
            self._codes = {
                "stage1": _Codes.empty(
                    codes.stage1.shape[1:], self.config.stage1_dtype, code_weights(self.codebooks.stage1)
                ),
                "stage2": _Codes.empty(
                    codes.stage2.shape[1:], self.config.stage2_dtype, code_weights(self.codebooks.stage2)
                ),
            }
        elif (
            codes.stage1.shape[1:] != self._codes["stage1"].row_shape
            or codes.stage2.shape[1:] != self._codes["stage2"].row_shape
        ):
            raise LoopClosureInputError(
                f"codes of shape {codes.stage1.shape[1:]}/{codes.stage2.shape[1:]} do not fit a database of "
                f"{self._codes['stage1'].row_shape}/{self._codes['stage2'].row_shape}"
            )
        self._codes["stage1"].extend(codes.stage1)
        self._codes["stage2"].extend(codes.stage2)
        self.places.extend(infos)
        if self._max_norm is not None:
            self._max_norm = max(
                self._max_norm, max_row_norm(self._codes["stage1"].flat_rows(first * codes.stage1.shape[1], None))
            )
        return list(range(first, len(self)))

    def codes_of(self, places: np.ndarray | list[int]) -> PlaceCodes:
        """The stored codes of `places` as float32, as `add` took them (within the storage's precision)."""
        index = np.asarray(places, dtype=np.int64)
        if index.size and (index.min() < 0 or index.max() >= len(self)):
            raise LoopClosureInputError(f"places {index.min()}..{index.max()} outside a database of {len(self)}")
        return PlaceCodes(
            np.asarray(self.stage1[index], dtype=np.float32), np.asarray(self.stage2[index], dtype=np.float32)
        )

    @classmethod
    def merged(
        cls, parts: list[PlaceDatabase], config: DatabaseConfig | None = None
    ) -> tuple[PlaceDatabase, list[int]]:
        """One database of every place of `parts`, in order, and the index each part starts at.
        The parts must share their codebooks: codes of other projections are not comparable."""
        if not parts:
            raise LoopClosureInputError("no databases to merge")
        first = parts[0]
        out = cls(first.codebooks, config or first.config)
        starts = []
        for k, part in enumerate(parts):
            if not part.codebooks.same_as(first.codebooks):
                raise LoopClosureInputError(
                    f"database {k} of those merged was encoded with other codebooks: its codes are not comparable"
                )
            starts.append(len(out))
            if len(part):
                out.add(part.codes_of(np.arange(len(part))), list(part.places))
        return out, starts

    def copy(self) -> PlaceDatabase:
        """An independent database holding the same places, in RAM: a session grows its own copy
        of a prior map, so the loaded map (and what is reported of it) stays as it was read."""
        other = PlaceDatabase(self.codebooks, self.config)
        other._codes = {name: codes.copy() for name, codes in self._codes.items()}
        other.places = list(self.places)
        other.extra = dict(self.extra)
        other.filtering = self.filtering
        return other

    def _check_codes(self, codes: PlaceCodes) -> None:
        if codes.stage1.ndim != 3 or codes.stage1.shape[-1] != self.codebooks.stage1.dim:
            raise LoopClosureInputError(
                f"stage-I codes must be (B, n, {self.codebooks.stage1.dim}), got {codes.stage1.shape}"
            )
        if codes.stage2.ndim != 4 or codes.stage2.shape[-1] != self.codebooks.stage2.dim:
            raise LoopClosureInputError(
                f"stage-II codes must be (B, gh, gw, {self.codebooks.stage2.dim}), got {codes.stage2.shape}"
            )
        if len(codes.stage1) != len(codes.stage2):  # one place is one row of each
            raise LoopClosureInputError(
                f"{len(codes.stage1)} stage-I but {len(codes.stage2)} stage-II codes: one of each per place"
            )
        if not codes.all_finite():
            raise LoopClosureInputError("place codes contain NaN or inf")
        for stage, dtype in (("stage1", self.config.stage1_dtype), ("stage2", self.config.stage2_dtype)):
            values = getattr(codes, stage)
            if dtype == "float16" and values.size and np.abs(values).max() > np.finfo(np.float16).max:
                raise LoopClosureInputError(
                    f"{stage} codes reach {np.abs(values).max():.3g}, beyond float16's range: "
                    f"store them as float32 (vpr.database.{stage}_dtype)"
                )

    # ---- stage I -----------------------------------------------------------------------
    def configure_search(self, filtering: FilteringConfig) -> None:
        """Search stage I as `filtering` says. A change of what shapes the index (its kind, IVF
        lists, HNSW links, ...) drops it; one of search-time settings only (probes, threads,
        blocks, N) keeps it, retuned."""
        from loopclosure.ann_index import same_build

        check_search_device(filtering)  # a missing GPU is refused now, not at the first query
        if filtering == self.filtering:
            return
        if self._index is not None and same_build(self._index.config, filtering):
            self._index.retune(filtering)
        else:
            self._index = None
        self.filtering = filtering

    def filter(
        self, query_stage1: np.ndarray, k_neighbours: int, num_candidates: int, excluded: np.ndarray | None = None
    ) -> Candidates:
        """Stage I against every place not excluded, through the configured search."""
        if not len(self):
            return empty_candidates()
        stage1 = self._codes["stage1"]
        per_place, dim = stage1.row_shape
        if query_stage1.ndim != 2 or query_stage1.shape[1] != dim:
            raise ValueError(f"stage-I query must be (n, {dim}), got {query_stage1.shape}")
        if not np.isfinite(query_stage1).all():  # every backend would rank NaN similarities silently
            raise LoopClosureInputError("a stage-I query holds NaN or inf")
        if self.filtering.index == "numpy":
            if self._max_norm is None:
                self._max_norm = max_row_norm(stage1.flat_rows(0, None))
            dense = np.asarray(self.stage1)  # float storage: the array itself, no copy
            return vote(query_stage1, dense, k_neighbours, num_candidates, excluded, self._max_norm)
        excluded = _checked_excluded(excluded, len(self))
        n_allowed = len(self) - len(excluded)
        if n_allowed == 0:
            return empty_candidates()
        index = self.search_index()
        k = min(k_neighbours, n_allowed * per_place)
        candidates = index.candidates(query_stage1, k, excluded, self._float32_view())
        return rank_neighbours(query_stage1, stage1.flat_rows_at, candidates, k, per_place, num_candidates)

    def search_index(self):  # noqa: ANN201 - loopclosure.ann_index.StageOneIndex (faiss imported lazily)
        """The stage-I index, brought up to date with every place added so far."""
        from loopclosure.ann_index import StageOneIndex

        stage1 = self._codes["stage1"]
        if self._index is None:
            self._index = StageOneIndex(self.filtering, stage1.row_shape[1], stage1.row_shape[0])
        self._index.sync(len(self), stage1.flat_rows, self._float32_view())
        return self._index

    def _float32_view(self) -> np.ndarray | None:
        stage1 = self._codes["stage1"]
        view = stage1.values.view
        return view.reshape(-1, view.shape[-1]) if stage1.scales is None and view.dtype == np.float32 else None

    # ---- persistence -------------------------------------------------------------------
    def _manifest(self, extra: dict[str, Any] | None) -> dict[str, Any]:
        int8 = "int8" in (self.config.stage1_dtype, self.config.stage2_dtype)
        return {
            "format": FORMAT,
            "version": FORMAT_VERSION_INT8 if int8 else FORMAT_VERSION,
            "num_places": len(self),
            "stage1_shape": list(self.stage1.shape[1:]),
            "stage2_shape": list(self.stage2.shape[1:]),
            "config": self.config.model_dump(),
            "extra": {**self.extra, **(extra or {})},
        }

    def _write_places_and_manifest(self, folder: Path, extra: dict[str, Any] | None) -> None:
        places = [
            {"frame_id": p.frame_id, "timestamp": p.timestamp, "name": p.name, "extra": p.extra} for p in self.places
        ]
        atomic_write_text(folder / "places.json", json.dumps(places, allow_nan=True))
        write_manifest(folder / MANIFEST, self._manifest(extra))

    def save(self, folder: str | Path, extra: dict[str, Any] | None = None) -> Path:
        """Write (or overwrite) the folder; the manifest goes last and names the valid count.
        Saving a database from `open` to its own folder is `commit`."""
        folder = Path(folder)
        if self._folder is not None and folder.resolve() == self._folder.resolve():
            return self.commit(extra)
        folder.mkdir(parents=True, exist_ok=True)
        self.codebooks.save(folder / "codebooks.npz")
        for name in STAGES:
            codes = self._codes.get(name)
            arrays = {name: self._stage(name) if codes is None else codes.values.view}
            if codes is not None and codes.scales is not None:
                arrays[f"{name}_scale"] = codes.scales.view
            for file, array in arrays.items():
                atomic_write(folder / f"{file}.npy", partial(_save_npy, array=array))
        self._write_places_and_manifest(folder, extra)
        return folder

    def commit(self, extra: dict[str, Any] | None = None) -> Path:
        """Make the places added since `open` part of its folder: places.json, then the manifest."""
        if self._folder is None:
            raise RuntimeError("commit: this database was not opened for appending (PlaceDatabase.open)")
        self.extra = {**self.extra, **(extra or {})}
        if self._codes and not self.memory_mapped:  # opened empty: the first codes are whole files
            folder, self._folder = self._folder, None
            self.save(folder)
            self._folder = folder
            for name, codes in self._codes.items():
                scales = None if codes.scales is None else _MappedArray(folder / f"{name}_scale.npy", len(self), True)
                self._codes[name] = _Codes(_MappedArray(folder / f"{name}.npy", len(self), True), scales, codes.weights)
            return folder
        self._write_places_and_manifest(self._folder, None)
        return self._folder

    @classmethod
    def open(cls, folder: str | Path) -> PlaceDatabase:
        """A saved map, memory-mapped, that grows in its folder: `add` writes the codes to the
        files, `commit` (or `save` to the same folder) records them in the manifest."""
        db = cls.load(folder, mmap=True, writable=True)
        db._folder = Path(folder)
        return db

    @classmethod
    def load(cls, folder: str | Path, mmap: bool = False, writable: bool = False) -> PlaceDatabase:
        """Read a saved folder; anything malformed is a `LoopClosureInputError` naming its file.

        mmap: map the code files instead of reading them (checked for NaN chunk by chunk)."""
        folder = Path(folder)
        manifest_path = folder / MANIFEST
        if not folder.exists():
            raise LoopClosureInputError(f"no such place database folder: {folder}")
        if not manifest_path.is_file():
            raise LoopClosureInputError(f"not a place database (no {MANIFEST}): {folder}")
        manifest = _read_manifest(manifest_path)
        n = manifest["num_places"]
        try:
            config = DatabaseConfig(**manifest.get("config") or {})
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"])
            raise LoopClosureInputError(f"{manifest_path}: config.{where}: {first['msg']}") from None
        except TypeError:  # not a mapping
            raise LoopClosureInputError(f"{manifest_path}: config must be an object") from None
        db = cls(Codebooks.load(folder / "codebooks.npz"), config)
        extra = manifest.get("extra") or {}
        if not isinstance(extra, dict):
            raise LoopClosureInputError(f"{manifest_path}: 'extra' must be an object, got {type(extra).__name__}")
        db.extra = dict(extra)
        dims = (db.codebooks.stage1.dim, db.codebooks.stage2.dim)
        if n and (manifest["stage1_shape"][-1], manifest["stage2_shape"][-1]) != dims:
            raise LoopClosureInputError(
                f"{folder / 'codebooks.npz'}: codebooks give {dims[0]}/{dims[1]}-dim codes, "
                f"{manifest_path} says {manifest['stage1_shape'][-1]}/{manifest['stage2_shape'][-1]}"
            )
        places = _read_places(folder / "places.json")
        if n == 0:
            return db
        for name in STAGES:
            dtype = getattr(config, f"{name}_dtype")
            wanted = manifest[f"{name}_shape"]
            values = _load_npy(folder / f"{name}.npy", n, mmap, writable)
            if list(values.row_shape) != wanted:
                raise LoopClosureInputError(
                    f"{folder / name}.npy: codes of shape {list(values.row_shape)}, its manifest says {wanted}"
                )
            scales = None
            if dtype == "int8":
                if values.view.dtype != np.int8:
                    raise LoopClosureInputError(
                        f"{folder / name}.npy: {values.view.dtype} codes, its manifest says int8"
                    )
                scales = _load_npy(folder / f"{name}_scale.npy", n, mmap, writable)
                if scales.row_shape != tuple(wanted[:-1]) or scales.view.dtype != np.float32:
                    raise LoopClosureInputError(
                        f"{folder / name}_scale.npy: {scales.view.dtype} scales of shape {list(scales.row_shape)}, "
                        f"codes of shape {wanted} need float32 {wanted[:-1]}"
                    )
                _check_finite(folder / f"{name}_scale.npy", scales.view, n, non_negative=True)
            else:
                _check_finite(folder / f"{name}.npy", values.view, n)
                if not mmap:
                    values = _GrowingArray(values.row_shape, np.dtype(dtype), values.view)
                elif values.view.dtype != np.dtype(dtype):
                    raise LoopClosureInputError(
                        f"{folder / name}.npy: {values.view.dtype} codes, its manifest says {dtype}"
                    )
            db._codes[name] = _Codes(
                values, scales, code_weights(getattr(db.codebooks, name)) if scales is not None else None
            )
        if len(places) < n:
            raise LoopClosureInputError(f"{folder / 'places.json'} lists {len(places)} places, manifest says {n}")
        db.places = places[:n]
        return db


def write_manifest(path: Path, manifest: dict[str, Any]) -> None:
    """The commit point of a save or an append (a function of its own so tests can fail it)."""
    atomic_write_text(path, json.dumps(manifest, indent=2))


def _checked_excluded(excluded: np.ndarray | None, n_places: int) -> np.ndarray:
    """Sorted unique excluded place indices, each in [0, n_places)."""
    if excluded is None or not len(excluded):
        return np.empty(0, np.int64)
    excluded = np.asarray(excluded, dtype=np.int64)
    if excluded[0] >= 0 and excluded[-1] == n_places - 1 and excluded[-1] - excluded[0] == len(excluded) - 1:
        if len(excluded) < 3 or bool((np.diff(excluded) == 1).all()):
            return excluded  # the usual suffix window, already sorted and unique
    if excluded.min() < 0 or excluded.max() >= n_places:
        raise ValueError(f"excluded place indices must lie in [0, {n_places}), got {excluded.min()}..{excluded.max()}")
    return np.unique(excluded)


def _check_finite(path: Path, array: np.ndarray, n: int, non_negative: bool = False, chunk: int = 4096) -> None:
    """NaN codes would vote for nothing or match everything: refuse them, chunk by chunk."""
    bad: list[int] = []
    for start in range(0, n, chunk):
        part = np.asarray(array[start : min(n, start + chunk)]).reshape(min(n, start + chunk) - start, -1)
        ok = np.isfinite(part).all(axis=1)
        if non_negative:
            ok &= (part >= 0).all(axis=1)
        bad.extend((start + np.flatnonzero(~ok)).tolist())
    if bad:
        what = "NaN, inf or negative" if non_negative else "NaN or inf"
        raise LoopClosureInputError(f"{path}: codes of {len(bad)} of {n} places are {what} (first: place {bad[0]})")


def _read_manifest(path: Path) -> dict[str, Any]:
    """The manifest as a checked mapping: format, version, a place count and the code shapes."""
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LoopClosureInputError(f"corrupt manifest {path}: {exc}") from None
    if not isinstance(manifest, dict):
        raise LoopClosureInputError(f"{path}: the manifest must be a JSON object, got {type(manifest).__name__}")
    if manifest.get("format") != FORMAT:
        raise LoopClosureInputError(f"{path} is not a {FORMAT} manifest")
    if manifest.get("version") not in READ_VERSIONS:
        raise LoopClosureInputError(
            f"{path} has format version {manifest.get('version')}, this build reads {' and '.join(map(str, READ_VERSIONS))}"
        )
    n = manifest.get("num_places")
    if "num_places" not in manifest:
        raise LoopClosureInputError(f"{path}: no num_places")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise LoopClosureInputError(f"{path}: num_places must be a whole number >= 0, got {n!r}")
    for key, ndim in (("stage1_shape", 2), ("stage2_shape", 3)):
        shape = manifest.get(key)
        if not (isinstance(shape, list) and len(shape) == ndim and all(type(d) is int and d >= 0 for d in shape)):
            raise LoopClosureInputError(f"{path}: {key} must be {ndim} whole numbers, got {shape!r}")
    return manifest


def _read_places(path: Path) -> list[PlaceInfo]:
    try:
        places = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LoopClosureInputError(f"cannot read {path}: {exc}") from None
    if not isinstance(places, list):
        raise LoopClosureInputError(f"{path}: must be a JSON list of places, got {type(places).__name__}")
    out = []
    for index, place in enumerate(places):
        try:
            info = PlaceInfo(**place)
        except TypeError:  # not an object, or unknown/missing keys
            info = None
        if info is None or type(info.frame_id) is not int or not isinstance(info.extra, dict):
            raise LoopClosureInputError(f"{path}: place {index} is not a place record ({str(place)[:80]})")
        out.append(_plain_info(info, f"{path}: place {index}:"))  # a NaN time: a place without one (vpr-eval's)
    return out


def _load_npy(path: Path, n: int, mmap: bool, writable: bool) -> _GrowingArray | _MappedArray:
    """The first n rows of a .npy file: read (mmap False) or mapped."""
    try:
        if mmap:
            array = np.load(path, mmap_mode="r", allow_pickle=False)
        else:
            array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise LoopClosureInputError(f"cannot read {path}: {exc}") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiu" or array.ndim < 1:
        raise LoopClosureInputError(f"{path}: not an array of numeric codes")
    if len(array) < n:
        raise LoopClosureInputError(f"{path} holds {len(array)} places, its manifest says {n}")
    if mmap:
        del array
        return _MappedArray(path, n, writable)
    return _GrowingArray(array.shape[1:], array.dtype, array[:n])


def _save_npy(handle: BinaryIO, array: Any) -> None:  # a stored array or its memory map
    np.save(handle, array, allow_pickle=False)
