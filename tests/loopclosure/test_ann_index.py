"""Stage I through faiss (loopclosure.ann_index): exact mode votes as numpy brute force does,
bit for bit (places, counts, tie order), on random data, exact ties and real Corridor codes;
IVF and HNSW honour exclusions, append incrementally and find most of the exact candidates.
Exact search through torch (the GPU path, run here on the CPU device) is held to the same votes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopclosure.ann_index import StageOneIndex, auto_nlist
from loopclosure.config import DatabaseConfig, FilteringConfig
from loopclosure.database import PlaceDatabase
from loopclosure.encoder import PlaceCodes
from loopclosure.filtering import Candidates, vote
from loopclosure.pca import Codebooks, PCAProjection

pytest.importorskip("faiss")


def _vote_float32_before_faiss(query, database, k_neighbours, num_candidates, excluded=None) -> Candidates:
    """`filtering.vote` as it was before the faiss index (neighbours chosen on float32 BLAS
    similarities): the reference the exact modes must reproduce."""
    n_places, per_place, dim = database.shape
    allowed = np.ones(n_places, dtype=bool)
    if excluded is not None and len(excluded):
        allowed[np.asarray(excluded, dtype=np.int64)] = False
    n_allowed = int(allowed.sum())
    if n_allowed == 0:
        return Candidates(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.float32))
    sims = query.astype(np.float32, copy=False) @ database.reshape(-1, dim).T.astype(np.float32, copy=False)
    if n_allowed < n_places:
        sims.reshape(len(query), n_places, per_place)[:, ~allowed, :] = -np.inf
    k = min(k_neighbours, n_allowed * per_place)
    n_vectors = sims.shape[1]
    if k < n_vectors:
        neighbours = np.empty((len(query), k), dtype=np.int64)
        for row, values in enumerate(sims):
            threshold = np.partition(values, n_vectors - k)[n_vectors - k]
            neighbours[row] = np.flatnonzero(values >= threshold)[:k]
    else:
        neighbours = np.broadcast_to(np.arange(n_vectors), sims.shape)
    neighbour_sims = np.take_along_axis(sims, neighbours, axis=1).ravel()
    neighbour_places = (neighbours // per_place).ravel()
    votes = np.bincount(neighbour_places, minlength=n_places)
    similarity = np.bincount(neighbour_places, weights=neighbour_sims, minlength=n_places)
    voted = np.flatnonzero(votes)
    order = np.lexsort((-similarity[voted], -votes[voted]))[:num_candidates]
    places = voted[order]
    max_votes = len(query) * min(k, per_place)
    return Candidates(places, votes[places], (votes[places] / max_votes).astype(np.float32))


def _same(a: Candidates, b: Candidates) -> None:
    np.testing.assert_array_equal(a.places, b.places)
    np.testing.assert_array_equal(a.votes, b.votes)
    np.testing.assert_array_equal(a.scores, b.scores)


def _projection(dim_in: int, dim: int, seed: int) -> PCAProjection:
    rng = np.random.default_rng(seed)
    return PCAProjection(
        mean=np.zeros(dim_in, np.float32),
        components=np.linalg.qr(rng.standard_normal((dim_in, dim)))[0].T.astype(np.float32),
        explained_variance=np.ones(dim, np.float32),
        whiten=False,
        l2_normalize_output=True,
    )


def _database(
    stage1: np.ndarray, config: DatabaseConfig | None = None, index: str = "exact", **filtering
) -> PlaceDatabase:
    p, n, d = stage1.shape
    db = PlaceDatabase(Codebooks(_projection(max(d, 8), d, 1), _projection(8, 3, 2)), config)
    db.configure_search(FilteringConfig(index=index, **filtering))
    db.add(PlaceCodes(stage1, np.zeros((p, 2, 2, 3), np.float32)))
    return db


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


# exact search in faiss, and through torch matrix products (on the CPU here; a GPU runs the same code)
# and torch scanning the map in blocks of 7 vectors (a city on a GPU: 1 GB of similarities per block),
# and from a float16 copy (a GPU's default: the rounding is the GPU's, the products are widened here)
BACKENDS = {
    "faiss": {},
    "torch": {"exact_backend": "torch", "torch_device": "cpu"},
    "torch-blocks": {"exact_backend": "torch", "torch_device": "cpu", "torch_block_rows": 7},
    "torch-float16": {"exact_backend": "torch", "torch_device": "cpu", "torch_storage": "float16"},
    "torch-float16-blocks": {"exact_backend": "torch", "torch_device": "cpu", "torch_storage": "float16",
                             "torch_block_rows": 7},
}  # fmt: skip


def _exclusions(draw, places: int) -> list[np.ndarray | None]:
    window = draw(st.integers(0, places))
    arbitrary = np.array(draw(st.lists(st.integers(0, places - 1), max_size=places, unique=True)), np.int64)
    return [None, np.arange(places - window, places), arbitrary]


# ---- exact: the same votes as numpy ------------------------------------------------------------
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(1, 8),
    per_place=st.integers(1, 6),
    places=st.integers(1, 40),
    d=st.integers(1, 12),
    k=st.integers(1, 60),
    lattice=st.booleans(),
    data=st.data(),
)
@settings(max_examples=120, deadline=None)
@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_exact_index_votes_as_numpy_brute_force(backend, seed, n, per_place, places, d, k, lattice, data):
    """Random vectors, and vectors on a small integer lattice (many exact ties, duplicated
    vectors and places), under no, a suffix and an arbitrary exclusion."""
    rng = np.random.default_rng(seed)
    if lattice:
        db = rng.integers(-1, 2, (places, per_place, d)).astype(np.float32)
        query = rng.integers(-1, 2, (n, d)).astype(np.float32)
    else:
        db = rng.standard_normal((places, per_place, d)).astype(np.float32)
        query = rng.standard_normal((n, d)).astype(np.float32)
    database = _database(db, **BACKENDS[backend])
    for excluded in _exclusions(data.draw, places):
        expected = vote(query, db, k, places, excluded)
        _same(database.filter(query, k, places, excluded), expected)
        if not lattice:  # no near-ties: the float32 selection of before agrees too
            _same(expected, _vote_float32_before_faiss(query, db, k, places, excluded))


@pytest.mark.parametrize("backend", sorted(BACKENDS))
@pytest.mark.parametrize("dtype", ["float32", "float16", "int8"])
def test_exact_equals_numpy_for_every_storage(dtype, backend):
    rng = np.random.default_rng(3)
    db = _unit(rng.standard_normal((300, 16, 20)))
    query = _unit(db[17] + 0.4 * rng.standard_normal((16, 20)))
    config = DatabaseConfig(stage1_dtype=dtype)
    exact, numpy_ = _database(db, config, "exact", **BACKENDS[backend]), _database(db, config, "numpy")
    stored = np.asarray(exact.stage1)  # the values as stored (float16 / int8 * scale)
    for excluded in (None, np.arange(250, 300), np.array([17, 3, 299, 150])):
        expected = vote(query, stored, 50, 50, excluded)
        _same(exact.filter(query, 50, 50, excluded), expected)
        _same(numpy_.filter(query, 50, 50, excluded), expected)
    assert exact.filter(query, 50, 50).places[0] == 17


def test_the_default_block_follows_the_similarity_budget(monkeypatch):
    """Without torch_block_rows a block holds SIMILARITY_BYTES of a query's similarities: a small
    budget scans in many blocks, with the same votes."""
    from loopclosure import device_search

    rng = np.random.default_rng(8)
    db = _unit(rng.standard_normal((120, 16, 10)))
    query = _unit(db[40] + 0.3 * rng.standard_normal((16, 10)))
    blocks = []
    similarities = device_search.TorchExactSearch._similarities
    monkeypatch.setattr(device_search.TorchExactSearch, "_similarities",
                        lambda self, q, lo, hi, ex: (blocks.append(hi - lo), similarities(self, q, lo, hi, ex))[1])  # fmt: skip
    monkeypatch.setattr(device_search, "SIMILARITY_BYTES", 16 * 4 * 100)  # 100 vectors a block for 16 rows
    database = _database(db, **BACKENDS["torch"])
    for excluded, scanned in ((None, 120 * 16), (np.arange(100, 120), 100 * 16)):  # a recent suffix is not scanned
        blocks.clear()
        _same(database.filter(query, 30, 20, excluded), vote(query, db, 30, 20, excluded))
        assert max(blocks) == 100 and sum(blocks) >= scanned  # 100 vectors at a time


@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_exact_widens_until_every_tie_is_in(backend):
    """200 copies of one vector: the k-th similarity is shared by all of them; the lowest ids win."""
    db = np.tile(_unit(np.ones((1, 1, 8))), (200, 1, 1))
    query = _unit(np.ones((1, 8)))
    database = _database(db, **BACKENDS[backend])
    got = database.filter(query, 5, 10)
    _same(got, vote(query, db, 5, 10))
    np.testing.assert_array_equal(got.places, [0, 1, 2, 3, 4])


@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_exact_index_grows_with_the_database(backend):
    """Places added one and many at a time, past the device buffer's first capacity (1,024 vectors)."""
    rng = np.random.default_rng(4)
    db = _unit(rng.standard_normal((400, 4, 10)))
    query = _unit(rng.standard_normal((4, 10)))
    database = _database(db[:50], **BACKENDS[backend])
    database.filter(query, 8, 10)
    for lo, hi in ((50, 51), (51, 120), (120, 400)):
        database.add(PlaceCodes(db[lo:hi], np.zeros((hi - lo, 2, 2, 3), np.float32)))
        _same(database.filter(query, 8, 10, np.arange(hi - 5, hi)), vote(query, db[:hi], 8, 10, np.arange(hi - 5, hi)))


@pytest.fixture(scope="module")
def corridor_codes(
    corridor_dir: Path, weights_path: Path, shared_backbone_passes: object
) -> tuple[PlaceCodes, PlaceCodes]:
    from loopclosure.backbone import load_backbone
    from loopclosure.backbone_input import list_images, read_image
    from loopclosure.config import VPRConfig
    from loopclosure.encoder import Encoder

    cfg = VPRConfig()
    cfg.backbone.weights = str(weights_path)
    cfg.backbone.device = "cpu"
    encoder = Encoder(cfg, load_backbone(cfg.backbone))
    refs = [encoder.prepare(read_image(p)) for p in list_images(corridor_dir / "ref")[::2]]
    queries = [encoder.prepare(read_image(p)) for p in list_images(corridor_dir / "query")[::4]]
    _, ref_codes = encoder.fit_and_encode(refs)
    return ref_codes, encoder.encode(queries)


@pytest.fixture(scope="module")
def corridor_expected_votes() -> dict[bytes, list[Candidates]]:
    """numpy's votes on the Corridor codes (checked once against the float32 vote from before
    faiss), per dtype and stored map (its bytes): the backends of one dtype store the same map,
    so each is held to votes worked out once instead of five times."""
    return {}


@pytest.mark.parametrize("backend", sorted(BACKENDS))
@pytest.mark.parametrize("dtype", ["float32", "int8"])
def test_exact_votes_as_numpy_on_real_corridor_codes(corridor_codes, corridor_expected_votes, dtype, backend):
    refs, queries = corridor_codes
    config = DatabaseConfig(stage1_dtype=dtype)
    database = _database(refs.stage1, config, **BACKENDS[backend])
    stored = np.asarray(database.stage1)
    p = len(refs)
    cases = [
        (q, excluded) for q in range(len(queries)) for excluded in (None, np.arange(p - 10, p), np.arange(0, p, 3))
    ]
    key = f"{dtype} {stored.dtype} {stored.shape}".encode() + np.ascontiguousarray(stored).tobytes()
    if key not in corridor_expected_votes:
        corridor_expected_votes[key] = [vote(queries.stage1[q], stored, 50, 50, excluded) for q, excluded in cases]
        if dtype == "float32":
            for expected, (q, excluded) in zip(corridor_expected_votes[key], cases):
                _same(expected, _vote_float32_before_faiss(queries.stage1[q], stored, 50, 50, excluded))
    for expected, (q, excluded) in zip(corridor_expected_votes[key], cases):
        _same(database.filter(queries.stage1[q], 50, 50, excluded), expected)


# ---- approximate: ivf, hnsw -------------------------------------------------------------------
def _streets(places: int, per_place: int, d: int, seed: int) -> np.ndarray:
    """Places along streets: each vector slot drifts slowly from place to place (as keyframes do)."""
    rng = np.random.default_rng(seed)
    out = np.empty((places, per_place, d), np.float32)
    x = rng.standard_normal((per_place, d))
    for p in range(places):
        x = 0.95 * x + 0.31 * rng.standard_normal((per_place, d)) if p % 100 else rng.standard_normal((per_place, d))
        out[p] = x
    return _unit(out)


def _recall(a: Candidates, b: Candidates) -> float:
    return len(np.intersect1d(a.places, b.places)) / max(1, len(b.places))


@pytest.mark.parametrize("kind", ["ivf", "hnsw"])
def test_approximate_indexes_find_the_exact_candidates_and_honour_exclusions(kind):
    db = _streets(3000, 16, 24, seed=5)
    rng = np.random.default_rng(6)
    database = _database(db, index=kind, ivf_nprobe=128)
    recalls = []
    for _ in range(12):
        p = int(rng.integers(0, 3000))
        query = _unit(db[p] + 0.1 * rng.standard_normal((16, 24)))
        for excluded in (None, np.arange(2900, 3000), np.arange(p - 3, p + 4) % 3000):
            got = database.filter(query, 50, 50, excluded)
            assert len(got) == 50 and not np.isin(got.places, excluded if excluded is not None else []).any()
            recalls.append(_recall(got, vote(query, db, 50, 50, excluded)))
    assert np.mean(recalls) >= 0.9, np.mean(recalls)


def test_search_time_settings_keep_the_index_and_build_settings_replace_it():
    """Changing IVF probes (or threads, blocks, N) answers as a fresh index with those settings
    does, without training the lists again; changing the lists builds a new index."""
    db = _streets(1500, 8, 16, seed=9)
    query = _unit(db[700] + 0.1 * np.random.default_rng(10).standard_normal((8, 16)))
    database = _database(db, index="ivf", ivf_nlist=64, ivf_nprobe=1)
    built = database.search_index()
    narrow = database.filter(query, 30, 30)
    wide_config = database.filtering.model_copy(update={"ivf_nprobe": 64, "faiss_threads": 2, "num_candidates": 20})
    database.configure_search(wide_config)
    assert database.search_index() is built and built.config == wide_config  # not trained again
    wide = database.filter(query, 30, 30)
    _same(wide, _database(db, index="ivf", ivf_nlist=64, ivf_nprobe=64).filter(query, 30, 30))
    _same(wide, vote(query, db, 30, 30))  # all 64 lists probed: exact
    assert not np.array_equal(narrow.votes, wide.votes)  # the probes did change
    database.configure_search(wide_config.model_copy(update={"ivf_nlist": 32}))
    assert database.search_index() is not built and database.search_index()._index.nlist == 32

    torch_db = _database(db[:50], **BACKENDS["torch"])
    device_index = torch_db.search_index()
    torch_db.configure_search(torch_db.filtering.model_copy(update={"torch_block_rows": 5}))
    assert torch_db.search_index() is device_index and device_index._device.block_rows == 5
    _same(torch_db.filter(query, 30, 30), vote(query, db[:50], 30, 30))
    with pytest.raises(ValueError, match="build settings differ"):
        device_index.retune(torch_db.filtering.model_copy(update={"exact_backend": "faiss"}))


def test_ivf_appends_then_retrains_at_the_growth_milestone():
    db = _streets(2000, 8, 16, seed=7)
    config = FilteringConfig(index="ivf", ivf_retrain_growth=2.0)
    index = StageOneIndex(config, 16, 8)
    rows = lambda lo, hi: db.reshape(-1, 16)[lo:hi]  # noqa: E731
    index.sync(600, rows)
    index.sync(900, rows)  # 1.5x: appended to the trained lists
    index.sync(1300, rows)  # 2.2x the 600 trained on: trained anew
    assert [what for what, _, _ in index.build_seconds] == ["ivf train + add", "ivf add", "ivf train + add"]
    assert index._index.ntotal == 1300 * 8 and index._trained_at == 1300
    query = _unit(db[1250] + 0.1)
    ids = index.candidates(query, 20, np.arange(1290, 1300))
    assert all(len(i) and i.max() < 1290 * 8 for i in ids)


def test_auto_switches_from_exact_to_ivf_past_the_threshold():
    db = _streets(400, 4, 12, seed=8)
    database = _database(db[:100], index="auto", ann_threshold_places=300)
    query = _unit(db[50] + 0.05)
    database.filter(query, 10, 10)
    assert database.search_index().kind == "exact"
    database.add(PlaceCodes(db[100:], np.zeros((300, 2, 2, 3), np.float32)))
    assert database.filter(query, 10, 10).places[0] == 50
    assert database.search_index().kind == "ivf"


def test_auto_on_the_cpu_switches_to_ivf_with_the_torch_backend_too():
    """Only a GPU keeps `auto` exact past the threshold: torch on the CPU scans no faster than faiss."""
    db = _streets(400, 4, 12, seed=8)
    database = _database(db[:100], index="auto", ann_threshold_places=300, **BACKENDS["torch"])
    query = _unit(db[50] + 0.05)
    assert database.filter(query, 10, 10).places[0] == 50
    assert database.search_index().kind == "exact" and database.search_index().search_device == "cpu"
    database.add(PlaceCodes(db[100:], np.zeros((300, 2, 2, 3), np.float32)))
    assert database.filter(query, 10, 10).places[0] == 50
    assert database.search_index().kind == "ivf" and database.search_index().search_device is None


def test_auto_stays_exact_past_the_threshold_on_a_gpu(monkeypatch):
    """The device's kind decides (a GPU is stood in for by the CPU device here): exact votes at
    every size, appended to the device rows as places come."""
    from loopclosure.device_search import TorchExactSearch

    monkeypatch.setattr(TorchExactSearch, "on_gpu", property(lambda self: True))
    db = _streets(400, 4, 12, seed=8)
    database = _database(db[:100], index="auto", ann_threshold_places=300, **BACKENDS["torch"])
    query = _unit(db[50] + 0.05)
    database.filter(query, 10, 10)
    for lo, hi in ((100, 350), (350, 400)):
        database.add(PlaceCodes(db[lo:hi], np.zeros((hi - lo, 2, 2, 3), np.float32)))
        _same(database.filter(query, 10, 10), vote(query, db[:hi], 10, 10))
    assert database.search_index().kind == "exact" and len(database.search_index()._device) == 400 * 4


def test_torch_device_cuda_without_a_gpu_is_refused_when_configured(monkeypatch):
    import torch

    from loopclosure.device_search import resolve_device
    from loopclosure.errors import LoopClosureInputError

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu"
    with pytest.raises(LoopClosureInputError, match="torch_device: cuda"):
        StageOneIndex(FilteringConfig(exact_backend="torch", torch_device="cuda"), 8, 2)
    database = _database(_unit(np.ones((3, 2, 4))))
    with pytest.raises(LoopClosureInputError, match="torch_device: cuda"):  # before any query
        database.configure_search(FilteringConfig(exact_backend="torch", torch_device="cuda"))
    # IVF and HNSW never use it
    assert (
        StageOneIndex(FilteringConfig(index="ivf", exact_backend="torch", torch_device="cuda"), 8, 2).search_device
        is None
    )


def test_a_sync_cut_short_is_redone_at_the_right_rows():
    """An error half way through a load (out of device memory, say) leaves no misplaced rows."""
    from loopclosure.device_search import TorchExactSearch

    search = TorchExactSearch(3, "cpu")
    search.write(0, np.ones((5, 3), np.float32))
    search.write(5, np.full((4, 3), 2.0, np.float32))  # rows 5..8 of a load that then failed
    search.write(5, np.full((2, 3), 3.0, np.float32))  # the next sync starts again at row 5
    assert len(search) == 7
    got = search.propose(np.ones((1, 3), np.float32), 2, len(search), np.empty(0, np.int64), 1.0)
    np.testing.assert_array_equal(got[0], [5, 6])
    with pytest.raises(ValueError, match="write at vector 9"):
        search.write(9, np.ones((1, 3), np.float32))


def _matmul_precision() -> tuple[str, ...]:
    import torch

    backends = (torch.backends.cuda.matmul, torch.backends.mkldnn.matmul)
    if all(hasattr(b, "fp32_precision") for b in backends):  # torch >= 2.9: one setting per backend
        return tuple(b.fp32_precision for b in backends)
    return (torch.get_float32_matmul_precision(),)


@pytest.mark.parametrize("caller", ["legacy", "per_backend"])
def test_torch_exact_search_multiplies_in_full_float32_and_restores_the_callers_setting(monkeypatch, caller):
    """The rounding margin assumes full float32 products: TF32 / bf16 are off while the
    similarities are computed, and the caller's setting (either API) is back afterwards."""
    import torch

    seen: list[tuple[str, ...]] = []
    topk = torch.topk
    monkeypatch.setattr(torch, "topk", lambda *a, **kw: (seen.append(_matmul_precision()), topk(*a, **kw))[1])
    before = _matmul_precision()
    if caller == "legacy":
        torch.set_float32_matmul_precision("medium")
    elif hasattr(torch.backends.cuda.matmul, "fp32_precision"):
        torch.backends.cuda.matmul.fp32_precision = "tf32"  # legacy reads raise after this (torch >= 2.9)
    setting = _matmul_precision()
    try:
        db = _unit(np.random.default_rng(9).standard_normal((60, 4, 10)))
        query = _unit(np.random.default_rng(10).standard_normal((4, 10)))
        _same(_database(db, **BACKENDS["torch"]).filter(query, 8, 10), vote(query, db, 8, 10))
        assert seen and all(s in (("ieee", "ieee"), ("highest",)) for s in seen)
        assert _matmul_precision() == setting
    finally:
        if len(before) == 2:
            torch.backends.cuda.matmul.fp32_precision, torch.backends.mkldnn.matmul.fp32_precision = before
        else:
            torch.set_float32_matmul_precision(before[0])


def test_auto_nlist():
    assert auto_nlist(100) == 64 and auto_nlist(16_000_000) == 16384
    assert auto_nlist(1_600_000) == 4096


def test_torch_on_the_cpu_searches_with_faiss_threads_and_restores_torchs(monkeypatch):
    """As faiss gets its own threads for a search, so does torch on the CPU; the backbone's
    setting comes back after."""
    import torch

    seen = []
    topk = torch.topk
    monkeypatch.setattr(torch, "topk", lambda *a, **kw: (seen.append(torch.get_num_threads()), topk(*a, **kw))[1])
    rng = np.random.default_rng(12)
    db = _unit(rng.standard_normal((60, 4, 8)))
    query = _unit(rng.standard_normal((4, 8)))
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        for threads in (1, 2):
            seen.clear()
            database = _database(db, **BACKENDS["torch"], faiss_threads=threads)
            _same(database.filter(query, 8, 10), vote(query, db, 8, 10))
            assert seen and set(seen) == {threads} and torch.get_num_threads() == 3
        database.configure_search(database.filtering.model_copy(update={"faiss_threads": 1}))  # retuned
        seen.clear()
        database.filter(query, 8, 10)
        assert set(seen) == {1}
    finally:
        torch.set_num_threads(before)


def test_a_map_too_large_for_the_device_is_an_error_naming_its_size(monkeypatch):
    import torch

    from loopclosure.device_search import TorchExactSearch
    from loopclosure.errors import LoopClosureError

    def no_room(*args, **kwargs):
        raise torch.cuda.OutOfMemoryError("CUDA out of memory")

    search = TorchExactSearch(100, "cpu")
    search.write(0, np.ones((3, 100), np.float32))
    monkeypatch.setattr(torch, "zeros", no_room)
    with pytest.raises(LoopClosureError, match=r"stage-I vectors \(6\.4 GB float32\) do not fit on cpu"):
        search.reserve(16_000_000)
    assert len(search) == 3  # what was held stays


# ---- the GPU's selection of a row's top k ------------------------------------------------------
@given(
    seed=st.integers(0, 2**31 - 1),
    rows=st.integers(1, 5),
    columns=st.integers(1, 3000),
    chunk=st.sampled_from([4, 16, 64]),
    kk=st.integers(1, 40),
    levels=st.sampled_from([0, 3, 50]),
    excluded=st.floats(0.0, 0.9),
)
@settings(max_examples=200, deadline=None)
def test_chunk_selection_keeps_the_values_topk_keeps(seed, rows, columns, chunk, kk, levels, excluded):
    """The selection a GPU runs (forced here on the CPU) keeps each row's kk largest values, as
    torch.topk does, and ids that point at them: ties (a few levels: mass ties fall back to
    topk), excluded columns at -inf, columns past the last whole chunk."""
    import torch

    from loopclosure.device_search import top_k_columns

    rng = np.random.default_rng(seed)
    values = rng.integers(0, levels, (rows, columns)) if levels else rng.standard_normal((rows, columns))
    sims = torch.from_numpy(values.astype(np.float32))
    sims[torch.from_numpy(rng.random((rows, columns)) < excluded)] = -torch.inf
    kk = min(kk, columns)
    got_values, got_ids = top_k_columns(sims, kk, chunk=chunk, select=True)
    expected = torch.topk(sims, kk, dim=1).values
    assert torch.equal(torch.sort(got_values, dim=1, descending=True).values, expected)
    assert torch.equal(torch.gather(sims, 1, got_ids), got_values)
    assert all(len(set(row.tolist())) == kk for row in got_ids)  # no column twice


def test_the_float16_copy_is_a_gpus_default_and_refuses_values_it_cannot_hold(monkeypatch):
    from loopclosure.device_search import TorchExactSearch
    from loopclosure.errors import LoopClosureInputError

    assert TorchExactSearch(8, "cpu").storage == "float32"  # the CPU's float16 products are slow
    monkeypatch.setattr(TorchExactSearch, "on_gpu", property(lambda self: True))
    search = TorchExactSearch(10, "cpu")
    assert search.storage == "float16" and search._rows is None
    search.write(0, np.full((2, 10), 3.0, np.float32))
    assert tuple(search._rows.shape[1:]) == (16,)  # padded to the width tensor cores take
    with pytest.raises(LoopClosureInputError, match="torch_storage: float32"):
        search.write(2, np.full((1, 10), 7e4, np.float32))
    assert len(search) == 2  # what was held stays
    query = np.ones((1, 10), np.float32)
    with pytest.raises(LoopClosureInputError, match="query values beyond"):
        search.propose(query * 7e4, 1, 2, np.empty(0, np.int64), 3.0 * np.sqrt(10))
    for bad in (np.nan, np.inf):
        with pytest.raises(LoopClosureInputError, match="vectors 2..2 hold NaN or inf"):
            search.write(2, np.full((1, 10), bad, np.float32))
        with pytest.raises(LoopClosureInputError, match="query holds NaN or inf"):
            search.propose(query * bad, 1, 2, np.empty(0, np.int64), 3.0 * np.sqrt(10))
    assert len(search.propose(query, 1, 2, np.empty(0, np.int64), 3.0 * np.sqrt(10))[0]) == 2  # a tie
    with pytest.raises(LoopClosureInputError, match="vectors 1..1 hold NaN"):
        search.write(1, np.full((1, 10), np.nan, np.float32))  # a refused rewrite keeps what it would replace
    assert len(search) == 2
    assert TorchExactSearch(10, "cpu", storage="float32").storage == "float32"


def test_the_exact_backend_is_torch_where_torch_sees_a_gpu(monkeypatch):
    """auto: a GPU scans a city exactly, so a GPU user gets it without a setting; the CPU keeps
    faiss (as fast there), and torch_device cpu or an explicit backend is obeyed."""
    import torch

    from loopclosure.device_search import resolve_backend

    assert resolve_backend(FilteringConfig()) == "faiss"  # no GPU here
    assert StageOneIndex(FilteringConfig(), 8, 2).search_device is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_backend(FilteringConfig()) == "torch"
    assert resolve_backend(FilteringConfig(torch_device="cpu")) == "faiss"
    assert resolve_backend(FilteringConfig(exact_backend="faiss")) == "faiss"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_backend(FilteringConfig(exact_backend="torch", torch_device="cpu")) == "torch"
