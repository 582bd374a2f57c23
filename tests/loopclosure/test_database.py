"""loopclosure.database.PlaceDatabase: appends, dtypes, persistence and crash safety."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from loopclosure.config import DatabaseConfig
from loopclosure.database import MANIFEST, PlaceDatabase, PlaceInfo
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
    return [PlaceInfo(frame_id=10 * (start + i), timestamp=0.5 * (start + i), name=f"p{start + i}", extra={"k": start + i}) for i in range(n)]


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


@pytest.mark.parametrize("s1, s2", [("float32", "float16"), ("float16", "float32"), ("float32", "float32"), ("float16", "float16")])
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
    manifest["version"] = 2
    (folder / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(LoopClosureInputError, match=r"manifest\.json has format version 2, this build reads 1"):
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
    with pytest.raises(LoopClosureInputError, match="not a place database"):
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
        json.dumps([{"frame_id": p.frame_id, "timestamp": p.timestamp, "name": p.name, "extra": p.extra} for p in grown.places])
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
    assert np.array_equal(session.stage1[:5], stage1) and [p.frame_id for p in session.places] == [10 * i for i in range(8)]
    session.stage1[0] += 1.0  # no shared buffers either
    assert np.array_equal(prior.stage1, stage1)
    empty = PlaceDatabase(codebooks).copy()
    assert len(empty) == 0
