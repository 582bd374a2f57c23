"""loopclosure.database.PlaceDatabase: appends, dtypes, persistence and crash safety."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from loopclosure.config import DatabaseConfig, FilteringConfig
from loopclosure.database import MANIFEST, PlaceDatabase, PlaceInfo, code_weights
from loopclosure.encoder import PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, PCAProjection

D1, N1, D2, GH, GW = 8, 16, 6, 3, 4


def _projection(dim_in: int, dim: int, seed: int) -> PCAProjection:
    rng = np.random.default_rng(seed)
    return PCAProjection(
        mean=rng.standard_normal(dim_in).astype(np.float32),
        components=np.linalg.qr(rng.standard_normal((dim_in, dim)))[0].T.astype(np.float32),
        explained_variance=np.sort(rng.uniform(0.5, 3.0, dim))[::-1].astype(np.float32),
        whiten=False,
        l2_normalize_output=True,
    )


@pytest.fixture
def codebooks() -> Codebooks:
    return Codebooks(_projection(30, D1, 1), _projection(20, D2, 2))


def _codes(n: int, seed: int = 0) -> PlaceCodes:
    rng = np.random.default_rng(seed)
    return PlaceCodes(
        rng.standard_normal((n, N1, D1)).astype(np.float32),
        rng.standard_normal((n, GH, GW, D2)).astype(np.float32),
    )


def _infos(n: int, start: int = 0) -> list[PlaceInfo]:
    return [
        PlaceInfo(frame_id=10 * (start + i), timestamp=0.5 * (start + i), name=f"p{start + i}", extra={"k": start + i})
        for i in range(n)
    ]


def _assert_same_db(a: PlaceDatabase, b: PlaceDatabase) -> None:
    assert len(a) == len(b)
    assert a.stage1.dtype == b.stage1.dtype and a.stage2.dtype == b.stage2.dtype
    np.testing.assert_array_equal(a.stage1, b.stage1)
    np.testing.assert_array_equal(a.stage2, b.stage2)
    assert [(p.frame_id, p.name, p.extra) for p in a.places] == [(p.frame_id, p.name, p.extra) for p in b.places]
    for pa, pb in zip(a.places, b.places):
        assert pa.timestamp == pb.timestamp or (math.isnan(pa.timestamp) and math.isnan(pb.timestamp))


def test_one_at_a_time_equals_batch(codebooks):
    codes = _codes(37)  # crosses the 16 -> 32 -> 64 capacity doublings
    batch = PlaceDatabase(codebooks)
    assert batch.add(codes) == list(range(37))
    single = PlaceDatabase(codebooks)
    for i in range(37):
        assert single.add(codes[i]) == [i]
    _assert_same_db(batch, single)
    np.testing.assert_array_equal(batch.stage1, codes.stage1)  # float32 stage I by default
    np.testing.assert_array_equal(batch.stage2, codes.stage2.astype(np.float16))  # float16 stage II
    assert [p.frame_id for p in single.places] == list(range(37))
    # earlier places survive every reallocation unchanged
    np.testing.assert_array_equal(single.stage1[:3], codes.stage1[:3])


def test_mixed_chunks_equal_batch(codebooks):
    codes = _codes(20, seed=3)
    chunked = PlaceDatabase(codebooks)
    for lo, hi in ((0, 1), (1, 17), (17, 18), (18, 20)):
        chunked.add(codes[lo:hi])
    whole = PlaceDatabase(codebooks)
    whole.add(codes)
    _assert_same_db(chunked, whole)


@pytest.mark.parametrize(
    "s1, s2", [("float32", "float16"), ("float16", "float32"), ("float32", "float32"), ("float16", "float16")]
)
def test_storage_dtypes_and_bytes_per_place(codebooks, tmp_path, s1, s2):
    db = PlaceDatabase(codebooks, DatabaseConfig(stage1_dtype=s1, stage2_dtype=s2))
    assert db.bytes_per_place == 0
    codes = _codes(3)
    db.add(codes)
    assert db.stage1.dtype == np.dtype(s1) and db.stage2.dtype == np.dtype(s2)
    expected = N1 * D1 * np.dtype(s1).itemsize + GH * GW * D2 * np.dtype(s2).itemsize
    assert db.bytes_per_place == expected
    np.testing.assert_array_equal(db.stage1, codes.stage1.astype(s1))
    loaded = PlaceDatabase.load(db.save(tmp_path / "db"))
    assert loaded.config == db.config
    assert loaded.stage1.dtype == np.dtype(s1) and loaded.stage2.dtype == np.dtype(s2)
    assert loaded.bytes_per_place == expected
    _assert_same_db(db, loaded)
    assert (tmp_path / "db" / "stage2.npy").stat().st_size >= 3 * GH * GW * D2 * np.dtype(s2).itemsize


def test_save_load_round_trip(codebooks, tmp_path):
    db = PlaceDatabase(codebooks)
    infos = _infos(5)
    infos[2] = PlaceInfo(frame_id=99)  # NaN timestamp, empty name and extra
    db.add(_codes(5), infos)
    folder = db.save(tmp_path / "db", extra={"note": "hello"})
    loaded = PlaceDatabase.load(folder)
    _assert_same_db(db, loaded)
    assert math.isnan(loaded.places[2].timestamp)
    for a, b in ((codebooks.stage1, loaded.codebooks.stage1), (codebooks.stage2, loaded.codebooks.stage2)):
        np.testing.assert_array_equal(a.components, b.components)
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.explained_variance, b.explained_variance)
    manifest = json.loads((folder / MANIFEST).read_text())
    assert manifest["num_places"] == 5 and manifest["extra"] == {"note": "hello"}
    assert not list(folder.glob("*.tmp")) and not list(folder.glob(".*.tmp"))


def test_append_after_reload_then_round_trip_again(codebooks, tmp_path):
    codes = _codes(9, seed=4)
    db = PlaceDatabase(codebooks)
    db.add(codes[0:4], _infos(4))
    db.save(tmp_path / "db")
    reloaded = PlaceDatabase.load(tmp_path / "db")
    assert reloaded.add(codes[4:9], _infos(5, start=4)) == [4, 5, 6, 7, 8]
    reloaded.add(codes[8], PlaceInfo(frame_id=1000))  # a lone PlaceInfo is accepted too
    reloaded.save(tmp_path / "db")
    again = PlaceDatabase.load(tmp_path / "db")
    reference = PlaceDatabase(codebooks)
    reference.add(codes, _infos(9))
    reference.add(codes[8], PlaceInfo(frame_id=1000))
    _assert_same_db(again, reference)


def test_empty_database_round_trip_and_filter(codebooks, tmp_path):
    db = PlaceDatabase(codebooks)
    c = db.filter(np.zeros((N1, D1), np.float32), 5, 5)
    assert len(c) == 0
    loaded = PlaceDatabase.load(db.save(tmp_path / "db"))
    assert len(loaded) == 0
    loaded.add(_codes(2))
    assert len(loaded) == 2 and loaded.stage1.shape == (2, N1, D1)


def test_filter_uses_stage_one_codes(codebooks):
    db = PlaceDatabase(codebooks)
    codes = _codes(6, seed=5)
    unit = codes.stage1 / np.linalg.norm(codes.stage1, axis=-1, keepdims=True)
    db.add(PlaceCodes(unit, codes.stage2))
    c = db.filter(unit[4], k_neighbours=1, num_candidates=3)
    assert c.places[0] == 4 and c.votes[0] == N1
    c = db.filter(unit[4], k_neighbours=1, num_candidates=3, excluded=np.array([4]))
    assert 4 not in c.places


@pytest.mark.parametrize(
    "codes, match",
    [
        (PlaceCodes(np.zeros((1, N1, D1 + 1), np.float32), np.zeros((1, GH, GW, D2), np.float32)), "stage-I codes"),
        (PlaceCodes(np.zeros((1, N1 * D1), np.float32), np.zeros((1, GH, GW, D2), np.float32)), "stage-I codes"),
        (PlaceCodes(np.zeros((1, N1, D1), np.float32), np.zeros((1, GH, GW, D2 - 1), np.float32)), "stage-II codes"),
        (PlaceCodes(np.zeros((1, N1, D1), np.float32), np.zeros((1, GH * GW, D2), np.float32)), "stage-II codes"),
    ],
)
def test_wrong_code_shapes_refused(codebooks, codes, match):
    db = PlaceDatabase(codebooks)
    with pytest.raises(LoopClosureInputError, match=match):
        db.add(codes)
    assert len(db) == 0


def test_codes_that_do_not_fit_the_existing_grid_refused(codebooks):
    db = PlaceDatabase(codebooks)
    db.add(_codes(2))
    other = PlaceCodes(np.zeros((1, N1 + 1, D1), np.float32), np.zeros((1, GH, GW, D2), np.float32))
    with pytest.raises(LoopClosureInputError, match="do not fit"):
        db.add(other)
    other = PlaceCodes(np.zeros((1, N1, D1), np.float32), np.zeros((1, GH + 1, GW, D2), np.float32))
    with pytest.raises(LoopClosureInputError, match="do not fit"):
        db.add(other)
    assert len(db) == 2 and db.stage1.shape[0] == 2 and db.stage2.shape[0] == 2


@pytest.mark.parametrize("stage, bad", [(1, np.nan), (2, np.nan), (1, np.inf), (2, -np.inf)])
def test_non_finite_codes_refused(codebooks, stage, bad):
    codes = _codes(3)
    (codes.stage1 if stage == 1 else codes.stage2)[1].flat[5] = bad
    db = PlaceDatabase(codebooks)
    with pytest.raises(LoopClosureInputError, match="NaN or inf"):
        db.add(codes)
    assert len(db) == 0


@pytest.mark.parametrize(
    "index, backend", [("numpy", "faiss"), ("exact", "faiss"), ("exact", "torch"), ("ivf", "faiss")]
)
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_non_finite_query_is_refused_by_every_search(codebooks, index, backend, bad):
    db = PlaceDatabase(codebooks)
    db.add(_codes(6, seed=3))
    db.configure_search(FilteringConfig(index=index, exact_backend=backend, torch_device="cpu", ivf_nlist=2))
    query = _codes(1, seed=4).stage1[0]
    assert len(db.filter(query, 5, 3)) == 3  # the clean query is answered
    query[2, 7] = bad
    with pytest.raises(LoopClosureInputError, match="stage-I query holds NaN or inf"):
        db.filter(query, 5, 3)


def test_info_count_mismatch_refused(codebooks):
    db = PlaceDatabase(codebooks)
    with pytest.raises(LoopClosureInputError, match="3 codes but 2 place infos"):
        db.add(_codes(3), _infos(2))
    assert len(db) == 0 and db.stage1.shape[0] == 0


def _saved(codebooks, tmp_path, n: int = 5):
    db = PlaceDatabase(codebooks)
    db.add(_codes(n), _infos(n))
    return db, db.save(tmp_path / "db")


def test_manifest_version_mismatch(codebooks, tmp_path):
    _, folder = _saved(codebooks, tmp_path)
    manifest = json.loads((folder / MANIFEST).read_text())
    manifest["version"] = 3
    (folder / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(LoopClosureInputError, match=r"manifest\.json has format version 3, this build reads 1 and 2"):
        PlaceDatabase.load(folder)


def test_manifest_of_another_format(codebooks, tmp_path):
    _, folder = _saved(codebooks, tmp_path)
    manifest = json.loads((folder / MANIFEST).read_text())
    manifest["format"] = "something-else"
    (folder / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(LoopClosureInputError, match="not a ssmvpr-place-database manifest"):
        PlaceDatabase.load(folder)


def test_corrupt_manifest_names_the_file(codebooks, tmp_path):
    _, folder = _saved(codebooks, tmp_path)
    (folder / MANIFEST).write_text('{"format": "ssmvpr-place-database", "vers')
    with pytest.raises(LoopClosureInputError, match=r"corrupt manifest .*db[/\\]manifest\.json"):
        PlaceDatabase.load(folder)


def test_missing_manifest_or_folder(tmp_path):
    with pytest.raises(LoopClosureInputError, match="not a place database"):
        PlaceDatabase.load(tmp_path)
    with pytest.raises(LoopClosureInputError, match=r"no such place database folder: .*absent"):
        PlaceDatabase.load(tmp_path / "absent")


def test_crash_between_arrays_and_manifest_loads_previous_state(codebooks, tmp_path):
    """A save of 7 places that died after writing the arrays and places.json but before the
    manifest: loading must give the 5 places the manifest vouches for."""
    db, folder = _saved(codebooks, tmp_path)
    grown = PlaceDatabase(codebooks)
    grown.add(_codes(5), _infos(5))
    grown.add(_codes(2, seed=9), _infos(2, start=5))
    np.save(folder / "stage1.npy", grown.stage1)
    np.save(folder / "stage2.npy", grown.stage2)
    (folder / "places.json").write_text(
        json.dumps(
            [{"frame_id": p.frame_id, "timestamp": p.timestamp, "name": p.name, "extra": p.extra} for p in grown.places]
        )
    )
    loaded = PlaceDatabase.load(folder)
    _assert_same_db(loaded, db)
    # and it keeps working: append and save a consistent state again
    loaded.add(_codes(1, seed=11))
    loaded.save(folder)
    assert len(PlaceDatabase.load(folder)) == 6


def test_arrays_shorter_than_manifest_are_an_error_naming_the_file(codebooks, tmp_path):
    db, folder = _saved(codebooks, tmp_path)
    np.save(folder / "stage2.npy", db.stage2[:3])
    with pytest.raises(LoopClosureInputError, match=r"stage2\.npy holds 3 places, its manifest says 5"):
        PlaceDatabase.load(folder)


def test_garbage_array_file_is_an_error_naming_the_file(codebooks, tmp_path):
    _, folder = _saved(codebooks, tmp_path)
    (folder / "stage1.npy").write_bytes(b"\x00garbage")
    with pytest.raises(LoopClosureInputError, match=r"stage1\.npy"):
        PlaceDatabase.load(folder)


def test_array_shape_disagreeing_with_manifest(codebooks, tmp_path):
    db, folder = _saved(codebooks, tmp_path)
    np.save(folder / "stage1.npy", np.zeros((5, N1, D1 + 2), np.float32))
    with pytest.raises(LoopClosureInputError, match=r"stage1\.npy: codes of shape .*, its manifest says"):
        PlaceDatabase.load(folder)


def test_places_json_shorter_than_manifest(codebooks, tmp_path):
    _, folder = _saved(codebooks, tmp_path)
    places = json.loads((folder / "places.json").read_text())
    (folder / "places.json").write_text(json.dumps(places[:4]))
    with pytest.raises(LoopClosureInputError, match=r"places\.json lists 4 places, manifest says 5"):
        PlaceDatabase.load(folder)


def test_missing_codebooks_file(codebooks, tmp_path):
    _, folder = _saved(codebooks, tmp_path)
    (folder / "codebooks.npz").unlink()
    with pytest.raises(LoopClosureInputError, match="codebooks.npz"):
        PlaceDatabase.load(folder)


def test_a_copy_grows_without_touching_the_original(codebooks):
    prior = PlaceDatabase(codebooks)
    prior.add(_codes(5), _infos(5))
    stage1, stage2 = prior.stage1.copy(), prior.stage2.copy()
    session = prior.copy()
    session.add(_codes(3, seed=1), _infos(3, start=5))
    assert len(prior) == 5 and len(session) == 8
    assert np.array_equal(prior.stage1, stage1) and np.array_equal(prior.stage2, stage2)
    assert np.array_equal(session.stage1[:5], stage1) and [p.frame_id for p in session.places] == [
        10 * i for i in range(8)
    ]
    session.stage1[0] += 1.0  # no shared buffers either
    assert np.array_equal(prior.stage1, stage1)
    empty = PlaceDatabase(codebooks).copy()
    assert len(empty) == 0


# ---- int8 codes -------------------------------------------------------------------------------
def test_int8_storage_round_trip_and_bytes(codebooks, tmp_path):
    config = DatabaseConfig(stage1_dtype="int8", stage2_dtype="int8")
    db = PlaceDatabase(codebooks, config)
    codes = _codes(6, seed=12)
    db.add(codes, _infos(6))
    assert db.bytes_per_place == N1 * D1 + N1 * 4 + GH * GW * D2 + GH * GW * 4
    for stored, original, projection in (
        (db.stage1, codes.stage1, codebooks.stage1),
        (db.stage2, codes.stage2, codebooks.stage2),
    ):
        values = np.asarray(stored)
        assert values.dtype == np.float32 and values.shape == original.shape
        # within half a step: the vector's own scale times the dimension's spread
        weights = code_weights(projection)
        assert weights.max() == 1.0 and len(np.unique(weights)) > 1  # the codebooks' variances differ
        step = np.abs(original / weights).max(axis=-1, keepdims=True) / 127 * weights
        assert (np.abs(values - original) <= 0.5 * step * (1 + 1e-5)).all()
        np.testing.assert_array_equal(stored[2:4], values[2:4])
    folder = db.save(tmp_path / "db")
    assert json.loads((folder / MANIFEST).read_text())["version"] == 2
    assert np.load(folder / "stage1.npy").dtype == np.int8 and np.load(folder / "stage2_scale.npy").shape == (6, GH, GW)
    for loaded in (PlaceDatabase.load(folder), PlaceDatabase.load(folder, mmap=True)):
        _assert_same_db(db, loaded)
        assert loaded.bytes_per_place == db.bytes_per_place


def test_int8_default_shapes_fit_in_20_kB(codebooks):
    cb = Codebooks(_projection(120, 100, 1), _projection(120, 100, 2))
    db = PlaceDatabase(cb, DatabaseConfig(stage1_dtype="int8", stage2_dtype="int8"))
    rng = np.random.default_rng(0)
    db.add(
        PlaceCodes(
            rng.standard_normal((1, 16, 100)).astype(np.float32),
            rng.standard_normal((1, 13, 13, 100)).astype(np.float32),
        )
    )
    assert db.bytes_per_place == 19_240 <= 20_000  # today's float32 + float16: 40,200


@pytest.mark.parametrize("edit, match", [
    (lambda f: np.save(f / "stage1_scale.npy", -np.ones((5, N1), np.float32)), r"stage1_scale\.npy: codes of 5 of 5 places are NaN, inf or negative"),
    (lambda f: (f / "stage2_scale.npy").unlink(), r"stage2_scale\.npy"),
    (lambda f: np.save(f / "stage1.npy", np.zeros((5, N1, D1), np.float32)), r"stage1\.npy: float32 codes, its manifest says int8"),
])  # fmt: skip
def test_broken_int8_files_are_named(codebooks, tmp_path, edit, match):
    db = PlaceDatabase(codebooks, DatabaseConfig(stage1_dtype="int8", stage2_dtype="int8"))
    db.add(_codes(5), _infos(5))
    folder = db.save(tmp_path / "db")
    edit(folder)
    for mmap in (False, True):
        with pytest.raises(LoopClosureInputError, match=match):
            PlaceDatabase.load(folder, mmap=mmap)


# ---- memory-mapped maps, grown in place ---------------------------------------------------------
def _write_v1_map(folder, codebooks, n: int = 5):
    """A map as the build before int8 and memory mapping wrote it (format version 1)."""
    folder.mkdir(parents=True)
    codes = _codes(n)
    codebooks.save(folder / "codebooks.npz")
    np.save(folder / "stage1.npy", codes.stage1)
    np.save(folder / "stage2.npy", codes.stage2.astype(np.float16))
    (folder / "places.json").write_text(
        json.dumps([{"frame_id": i, "timestamp": 0.0, "name": "", "extra": {}} for i in range(n)])
    )
    manifest = {
        "format": "ssmvpr-place-database",
        "version": 1,
        "num_places": n,
        "stage1_shape": [N1, D1],
        "stage2_shape": [GH, GW, D2],
        "config": {"stage1_dtype": "float32", "stage2_dtype": "float16"},
        "extra": {},
    }
    (folder / MANIFEST).write_text(json.dumps(manifest))
    return codes


@pytest.mark.parametrize("dtype", ["float32", "int8"])
def test_memory_mapped_load_reads_the_same_and_copies_to_ram(codebooks, tmp_path, dtype):
    db = PlaceDatabase(codebooks, DatabaseConfig(stage1_dtype=dtype, stage2_dtype=dtype))
    db.add(_codes(7), _infos(7))
    mapped = PlaceDatabase.load(db.save(tmp_path / "db"), mmap=True)
    assert mapped.memory_mapped
    assert isinstance(mapped._codes["stage2"].values.view, np.memmap)
    _assert_same_db(db, mapped)
    np.testing.assert_array_equal(
        mapped.filter(_codes(1).stage1[0], 5, 3).places, db.filter(_codes(1).stage1[0], 5, 3).places
    )
    with pytest.raises(RuntimeError, match="read-only"):
        mapped.add(_codes(1))
    session = mapped.copy()  # a session grows its own copy in RAM
    session.add(_codes(1, seed=3))
    assert len(session) == 8 and len(mapped) == 7 and not session.memory_mapped


def test_a_version_1_map_loads_mapped_and_grows_in_place(codebooks, tmp_path):
    folder = tmp_path / "old"
    codes = _write_v1_map(folder, codebooks)
    ram = PlaceDatabase.load(folder)
    np.testing.assert_array_equal(ram.stage1, codes.stage1)
    db = PlaceDatabase.open(folder)
    _assert_same_db(ram, db)
    db.add(_codes(2, seed=5), _infos(2, start=5))
    db.commit()
    again = PlaceDatabase.load(folder)
    assert len(again) == 7 and json.loads((folder / MANIFEST).read_text())["version"] == 1
    np.testing.assert_array_equal(again.stage1[5:], _codes(2, seed=5).stage1)
    np.testing.assert_array_equal(np.load(folder / "stage1.npy")[:5], codes.stage1)  # a plain .npy still


@pytest.mark.parametrize("dtype", ["float32", "int8"])
def test_open_append_commit_equals_a_database_built_in_ram(codebooks, tmp_path, dtype):
    config = DatabaseConfig(stage1_dtype=dtype, stage2_dtype="float16" if dtype == "float32" else dtype)
    codes = _codes(12, seed=6)
    reference = PlaceDatabase(codebooks, config)
    reference.add(codes, _infos(12))
    db = PlaceDatabase(codebooks, config)
    db.add(codes[0:3], _infos(3))
    folder = db.save(tmp_path / "db")
    grown = PlaceDatabase.open(folder)
    for lo, hi in ((3, 4), (4, 9), (9, 12)):
        grown.add(codes[lo:hi], _infos(hi - lo, start=lo))
        grown.save(folder)  # to its own folder: a commit
    _assert_same_db(grown, reference)
    _assert_same_db(PlaceDatabase.load(folder), reference)
    _assert_same_db(PlaceDatabase.load(folder, mmap=True), reference)


def test_an_empty_map_opened_for_appending_starts_its_files(codebooks, tmp_path):
    folder = PlaceDatabase(codebooks).save(tmp_path / "db")
    db = PlaceDatabase.open(folder)
    db.add(_codes(2), _infos(2))
    db.commit()
    db.add(_codes(1, seed=2), _infos(1, start=2))
    db.commit()
    assert db.memory_mapped and len(PlaceDatabase.load(folder)) == 3


@pytest.mark.parametrize("dtype", ["float32", "int8"])
def test_crash_between_the_data_and_the_manifest_of_an_append(codebooks, tmp_path, monkeypatch, dtype):
    """Append to a mapped map, fail at the manifest (the commit point): a reload gives the
    previous consistent count; opening it again cuts the orphan rows off and appends cleanly."""
    config = DatabaseConfig(stage1_dtype=dtype, stage2_dtype=dtype)
    db = PlaceDatabase(codebooks, config)
    db.add(_codes(5), _infos(5))
    folder = db.save(tmp_path / "db")
    before = PlaceDatabase.load(folder)

    import loopclosure.database as database_module

    def crash(path, manifest):
        raise OSError("simulated crash before the manifest")

    grown = PlaceDatabase.open(folder)
    grown.add(_codes(3, seed=8), _infos(3, start=5))  # the rows are in the files already
    assert np.load(folder / "stage1.npy", mmap_mode="r").shape[0] == 8
    monkeypatch.setattr(database_module, "write_manifest", crash)
    with pytest.raises(OSError, match="simulated crash"):
        grown.commit()
    monkeypatch.undo()
    assert len(json.loads((folder / "places.json").read_text())) == 8  # places.json went before the manifest
    _assert_same_db(PlaceDatabase.load(folder), before)
    _assert_same_db(PlaceDatabase.load(folder, mmap=True), before)

    reopened = PlaceDatabase.open(folder)
    assert np.load(folder / "stage1.npy").shape[0] == 5  # the uncommitted rows are gone
    reopened.add(_codes(1, seed=9), _infos(1, start=5))
    reopened.commit()
    final = PlaceDatabase.load(folder)
    assert len(final) == 6
    np.testing.assert_array_equal(final.stage1[5:], _stored(codebooks, config, _codes(1, seed=9)))


def _stored(codebooks, config, codes):
    db = PlaceDatabase(codebooks, config)
    db.add(codes)
    return np.asarray(db.stage1)


_KILL_CHILD = """
import os, signal, sys
import numpy as np
sys.path.insert(0, {tests!r})
from test_database import _codes, _infos
from loopclosure.database import PlaceDatabase
import loopclosure.database as m
db = PlaceDatabase.open({folder!r})
db.add(_codes(4, seed=21), _infos(4, start=5))
m.write_manifest = lambda path, manifest: os.kill(os.getpid(), signal.SIGKILL)
db.commit()
"""


def test_sigkill_mid_append_leaves_the_previous_map(codebooks, tmp_path):
    import os
    import signal
    import subprocess
    import sys

    db = PlaceDatabase(codebooks)
    db.add(_codes(5), _infos(5))
    folder = db.save(tmp_path / "db")
    script = _KILL_CHILD.format(tests=os.path.dirname(__file__), folder=str(folder))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert np.load(folder / "stage1.npy", mmap_mode="r").shape[0] == 9  # the killed append's rows
    _assert_same_db(PlaceDatabase.load(folder), db)
    _assert_same_db(PlaceDatabase.load(folder, mmap=True), db)


def test_code_weights_follow_the_pca_variances():
    def projection(ev: list[float], whiten: bool = False) -> PCAProjection:
        return PCAProjection(
            np.zeros(5, np.float32), np.eye(4, 5, dtype=np.float32), np.array(ev, np.float32), whiten, False
        )

    assert code_weights(projection([4.0, 1.0, 0.0, np.nan])).tolist() == [1.0] * 4  # a NaN variance: no weighting
    np.testing.assert_allclose(code_weights(projection([4.0, 1.0, 0.0, 0.25])), [1.0, 0.5, 1e-3, 0.25])
    assert code_weights(projection([4.0, 1.0, 0.0, 0.25], whiten=True)).tolist() == [1.0] * 4  # already even


def test_float16_stage_one_widens_exactly_for_the_search(codebooks):
    """A float16 map's stage-I rows reach the search (and the index's float32 mirror) as their
    exact float32 values, in any slice."""
    codes = _codes(300, seed=11)
    db = PlaceDatabase(codebooks, DatabaseConfig(stage1_dtype="float16"))
    db.add(codes)
    rows = db._codes["stage1"].flat_rows(0, None)
    assert rows.dtype == np.float32
    np.testing.assert_array_equal(rows, codes.stage1.astype(np.float16).astype(np.float32).reshape(-1, D1))
    np.testing.assert_array_equal(db._codes["stage1"].flat_rows(17, 301), rows[17:301])


def test_what_a_save_would_refuse_is_refused_when_added(codebooks, tmp_path):
    """Codes or infos that made a database whose saved map `load` then refused (a tester found
    each): stage counts that differ, float16 overflow to inf, a frame id that is not an integer."""
    db = PlaceDatabase(codebooks)
    codes = _codes(3)
    with pytest.raises(LoopClosureInputError, match="3 stage-I but 2 stage-II codes"):
        db.add(PlaceCodes(codes.stage1, codes.stage2[:2]))
    with pytest.raises(LoopClosureInputError, match=r"stage2 codes reach 7e\+04, beyond float16's range"):
        db.add(PlaceCodes(codes.stage1, codes.stage2 * 0 + 70000.0))
    with pytest.raises(LoopClosureInputError, match="frame_id must be an integer, got 'abc'"):
        db.add(codes[:1], PlaceInfo(frame_id="abc"))  # type: ignore[arg-type]
    assert len(db) == 0
    with pytest.raises(LoopClosureInputError, match="timestamp must be a number, got 'later'"):
        db.add(codes[:1], PlaceInfo(frame_id=1, timestamp="later"))  # type: ignore[arg-type]
    db.add(codes, [PlaceInfo(frame_id=np.int64(k), timestamp=np.float32(k)) for k in range(3)])  # numpy scalars
    db.save(tmp_path / "map")
    assert [p.frame_id for p in PlaceDatabase.load(tmp_path / "map").places] == [0, 1, 2]
    wide = PlaceDatabase(codebooks, DatabaseConfig(stage2_dtype="float32"))
    wide.add(PlaceCodes(codes.stage1, codes.stage2 * 0 + 70000.0))  # float32 storage holds them
    assert len(db) == len(wide) == 3


def test_merged_keeps_every_place_in_order_and_says_where_each_part_starts(codebooks):
    """`map` matches a session against the others' places through one merged database: the
    codes and records of each part come back unchanged, at the offset it reports."""
    a, b = PlaceDatabase(codebooks), PlaceDatabase(codebooks)
    a.add(_codes(3, seed=1), _infos(3))
    b.add(_codes(4, seed=2), _infos(4, start=3))
    merged, starts = PlaceDatabase.merged([a, PlaceDatabase(codebooks), b])
    assert starts == [0, 3, 3] and len(merged) == 7
    np.testing.assert_array_equal(merged.codes_of([3, 6]).stage1, b.codes_of([0, 3]).stage1)
    np.testing.assert_array_equal(merged.codes_of(np.arange(3)).stage2, a.codes_of(np.arange(3)).stage2)
    np.testing.assert_allclose(a.codes_of(np.arange(3)).stage1, _codes(3, seed=1).stage1, atol=1e-2)
    assert [p.name for p in merged.places] == [f"p{k}" for k in range(7)]


def test_merged_refuses_parts_encoded_with_other_codebooks(codebooks):
    other = Codebooks(_projection(30, D1, 7), _projection(20, D2, 8))
    a, b = PlaceDatabase(codebooks), PlaceDatabase(other)
    a.add(_codes(2))
    b.add(_codes(2))
    assert codebooks.same_as(Codebooks(_projection(30, D1, 1), _projection(20, D2, 2)))
    assert not codebooks.same_as(other)
    with pytest.raises(LoopClosureInputError, match="other codebooks"):
        PlaceDatabase.merged([a, b])


def test_codes_of_refuses_places_it_does_not_hold(codebooks):
    db = PlaceDatabase(codebooks)
    db.add(_codes(2))
    with pytest.raises(LoopClosureInputError, match="outside a database of 2"):
        db.codes_of([0, 2])
