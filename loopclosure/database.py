"""PlaceDatabase: the growing map of places, their codes, and the codebooks that made them.

Places are appended one at a time (streaming SLAM) or in batches (a reference folder).
Storage grows by doubling so appends are amortised O(1). On disk a database is a folder:
arrays in .npy files, the codebooks, and a versioned manifest written last. Every file is
replaced atomically and the manifest records how many places are valid, so a crash while
saving leaves the previous consistent state readable.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from loopclosure.atomic import atomic_write_bytes, atomic_write_text
from loopclosure.config import DatabaseConfig
from loopclosure.encoder import PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.filtering import Candidates, vote
from loopclosure.pca import Codebooks

FORMAT = "ssmvpr-place-database"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"


@dataclass
class PlaceInfo:
    """What the caller wants back about a place: its frame/keyframe id, time and a name."""

    frame_id: int
    timestamp: float = float("nan")
    name: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


class _GrowingArray:
    """A numpy array that appends along axis 0 with capacity doubling."""

    def __init__(self, row_shape: tuple[int, ...], dtype: np.dtype, data: np.ndarray | None = None) -> None:
        self.row_shape = row_shape
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


class PlaceDatabase:
    def __init__(self, codebooks: Codebooks, config: DatabaseConfig | None = None) -> None:
        self.codebooks = codebooks
        self.config = config or DatabaseConfig()
        self._stage1: _GrowingArray | None = None
        self._stage2: _GrowingArray | None = None
        self.places: list[PlaceInfo] = []
        self.extra: dict[str, Any] = {}  # the manifest's free-form record (e.g. encoder settings)

    def __len__(self) -> int:
        return len(self.places)

    @property
    def stage1(self) -> np.ndarray:
        """(P, n1, d1) stage-I codes of all places."""
        return self._stage1.view if self._stage1 is not None else np.empty((0, 0, self.codebooks.stage1.dim))

    @property
    def stage2(self) -> np.ndarray:
        """(P, gh, gw, d2) stage-II grids of all places."""
        return self._stage2.view if self._stage2 is not None else np.empty((0, 0, 0, self.codebooks.stage2.dim))

    @property
    def bytes_per_place(self) -> int:
        if not len(self):
            return 0
        return int(self.stage1[0].nbytes + self.stage2[0].nbytes)

    def add(self, codes: PlaceCodes, infos: list[PlaceInfo] | PlaceInfo | None = None) -> list[int]:
        """Append places; returns their database indices."""
        if isinstance(infos, PlaceInfo):
            infos = [infos]
        first = len(self)
        if infos is None:
            infos = [PlaceInfo(frame_id=first + i) for i in range(len(codes))]
        if len(infos) != len(codes):
            raise LoopClosureInputError(f"{len(codes)} codes but {len(infos)} place infos")
        self._check_codes(codes)
        if self._stage1 is None:
            self._stage1 = _GrowingArray(codes.stage1.shape[1:], np.dtype(self.config.stage1_dtype))
            self._stage2 = _GrowingArray(codes.stage2.shape[1:], np.dtype(self.config.stage2_dtype))
        elif codes.stage1.shape[1:] != self._stage1.row_shape or codes.stage2.shape[1:] != self._stage2.row_shape:
            raise LoopClosureInputError(
                f"codes of shape {codes.stage1.shape[1:]}/{codes.stage2.shape[1:]} do not fit a database of "
                f"{self._stage1.row_shape}/{self._stage2.row_shape}"
            )
        self._stage1.extend(codes.stage1)
        self._stage2.extend(codes.stage2)
        self.places.extend(infos)
        return list(range(first, len(self)))

    def copy(self) -> "PlaceDatabase":
        """An independent database holding the same places: a session grows its own copy of a
        prior map, so the loaded map (and what is reported of it) stays as it was read."""
        other = PlaceDatabase(self.codebooks, self.config)
        if self._stage1 is not None and self._stage2 is not None:
            other._stage1 = _GrowingArray(self._stage1.row_shape, self._stage1.view.dtype, self._stage1.view.copy())
            other._stage2 = _GrowingArray(self._stage2.row_shape, self._stage2.view.dtype, self._stage2.view.copy())
        other.places = list(self.places)
        other.extra = dict(self.extra)
        return other

    def _check_codes(self, codes: PlaceCodes) -> None:
        if codes.stage1.ndim != 3 or codes.stage1.shape[-1] != self.codebooks.stage1.dim:
            raise LoopClosureInputError(f"stage-I codes must be (B, n, {self.codebooks.stage1.dim}), got {codes.stage1.shape}")
        if codes.stage2.ndim != 4 or codes.stage2.shape[-1] != self.codebooks.stage2.dim:
            raise LoopClosureInputError(f"stage-II codes must be (B, gh, gw, {self.codebooks.stage2.dim}), got {codes.stage2.shape}")
        if not (np.isfinite(codes.stage1).all() and np.isfinite(codes.stage2).all()):
            raise LoopClosureInputError("place codes contain NaN or inf")

    def filter(
        self, query_stage1: np.ndarray, k_neighbours: int, num_candidates: int, excluded: np.ndarray | None = None
    ) -> Candidates:
        """Stage I against every place not excluded."""
        if not len(self):
            return Candidates(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.float32))
        return vote(query_stage1, self.stage1, k_neighbours, num_candidates, excluded)

    # ---- persistence -------------------------------------------------------------------
    def save(self, folder: str | Path, extra: dict[str, Any] | None = None) -> Path:
        """Write (or overwrite) the folder; the manifest goes last and names the valid count."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.codebooks.save(folder / "codebooks.npz")
        for name, array in (("stage1.npy", self.stage1), ("stage2.npy", self.stage2)):
            atomic_write_bytes(folder / name, _npy_bytes(array))
        places = [{"frame_id": p.frame_id, "timestamp": p.timestamp, "name": p.name, "extra": p.extra} for p in self.places]
        atomic_write_text(folder / "places.json", json.dumps(places, allow_nan=True))
        manifest = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "num_places": len(self),
            "stage1_shape": list(self.stage1.shape[1:]),
            "stage2_shape": list(self.stage2.shape[1:]),
            "config": self.config.model_dump(),
            "extra": {**self.extra, **(extra or {})},
        }
        atomic_write_text(folder / MANIFEST, json.dumps(manifest, indent=2))
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> "PlaceDatabase":
        """Read a saved folder; anything malformed is a `LoopClosureInputError` naming its file."""
        folder = Path(folder)
        manifest_path = folder / MANIFEST
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
        stage1, stage2 = (_load_npy(folder / name, n) for name in ("stage1.npy", "stage2.npy"))
        if len(places) < n:
            raise LoopClosureInputError(f"{folder / 'places.json'} lists {len(places)} places, manifest says {n}")
        for name, array in (("stage1.npy", stage1), ("stage2.npy", stage2)):
            wanted = manifest[f"{name[:6]}_shape"]
            if list(array.shape[1:]) != wanted:
                raise LoopClosureInputError(
                    f"{folder / name}: codes of shape {list(array.shape[1:])}, its manifest says {wanted}"
                )
        for name, array in (("stage1.npy", stage1), ("stage2.npy", stage2)):
            finite = np.isfinite(array[:n].reshape(n, -1)).all(axis=1)
            if not finite.all():  # NaN codes would vote for nothing or match everything
                bad = np.flatnonzero(~finite)
                raise LoopClosureInputError(
                    f"{folder / name}: codes of {len(bad)} of {n} places are NaN or inf (first: place {bad[0]})"
                )
        db._stage1 = _GrowingArray(stage1.shape[1:], np.dtype(db.config.stage1_dtype), stage1[:n])
        db._stage2 = _GrowingArray(stage2.shape[1:], np.dtype(db.config.stage2_dtype), stage2[:n])
        db.places = places[:n]
        return db


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
    if manifest.get("version") != FORMAT_VERSION:
        raise LoopClosureInputError(f"{path} has format version {manifest.get('version')}, this build reads {FORMAT_VERSION}")
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
        out.append(info)
    return out


def _npy_bytes(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def _load_npy(path: Path, n: int) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise LoopClosureInputError(f"cannot read {path}: {exc}") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiu" or array.ndim < 1:
        raise LoopClosureInputError(f"{path}: not an array of numeric codes")
    if len(array) < n:
        raise LoopClosureInputError(f"{path} holds {len(array)} places, its manifest says {n}")
    return array
