"""Benchmark SSM-VPR: CNN encoding, stage-I filtering, stage-II spatial matching, storage.

Prints ONE JSON object to stdout (progress goes to stderr).

Usage:
  python tools/bench_vpr.py [--weights PATH|random] [--images DIR] [--device auto|cpu|cuda]
                            [--precision auto|fp32|bf16|int8]
                            [--sizes 1000,10000,100000] [--repeats N] [--quick]
                            [--index-sizes 10000,100000,1000000 [--nlists 4096] [--only-index]
                             [--exact-backend faiss|torch --torch-device auto|cpu|cuda] [--check-votes N]]
                            [--mapped-places 100000]

What is measured (all through the library's own code paths):
  cnn_encode           Backbone (VGG16 to conv5_2) + cube extraction + PCA projection on real
                       images (Corridor ref by default), batch 1 and batch 8, at --precision
                       (int8 is calibrated on the timed images; tools/bench_backbone.py compares
                       the precisions side by side). The PCA codebooks
                       are random projections of the real shapes: projection speed does not depend
                       on their values. Real weights when found, else random weights (said so).
  filtering_query_ms   `loopclosure.filtering.vote(query, db.stage1, k=50, num_candidates=50,
                       excluded)` on synthetic unit-norm stage-I codes in the PlaceDatabase stage-I
                       layout (P, 16, 100) and dtype (DatabaseConfig.stage1_dtype), with and
                       without an exclusion window of the most recent places.
  spatial_matching_ms  `loopclosure.spatial.spatial_scores` on N candidates gathered from a
                       stage-II store in DatabaseConfig.stage2_dtype (float16 by default, the
                       conversion to float32 happens inside), as `TwoStageRanker.query` does.
  bytes_per_place      `PlaceDatabase.bytes_per_place` (in memory) and the .npy bytes on disk, for
                       the default, float32, int8 (scale per vector) and stage-II-only int8 storage;
                       --mapped-places P: a saved map of P places opened memory-mapped vs read into
                       RAM (seconds, resident memory), and add + commit of one place in place.
  stage1_index         (--index-sizes) `loopclosure.ann_index.StageOneIndex` + `filtering.rank_neighbours`
                       as `PlaceDatabase.filter` runs them, exact (faiss, or torch on --torch-device with
                       --exact-backend torch: the GPU path) vs IVF (--nlists, --nprobes; --hnsw-ef adds HNSW) on `street_codes` (synthetic codes with Corridor's spectrum and
                       street-to-street drift; queries keep --query-cosine to their place): query ms,
                       recall@N of the IVF candidates against exact voting, whether the revisited place
                       (within 2) is a candidate, build seconds, append ms per place after the build;
                       --check-votes N: whether N queries' exact votes equal numpy brute force's.
  sequence_query_ms    One query of a stream with sequence matching, as `LoopDetector` runs it:
                       stage-I vote over --store-places places (minus the exclusion window),
                       stage II of the N candidates plus the continued places, then
                       `SequenceMatcher.step` (the earlier queries' terms, scored on demand),
                       with numpy's BLAS capped at 1 thread as in the detector. The stream is a
                       synthetic revisit (queries are noisy copies of consecutive places), so the
                       true sequence is cached as in use and the other candidates are not: about
                       the worst case for the matcher's cache. For L in --sequence-lengths, one
                       direction (forward) and both, all N candidates (K=all: L x N scores) and
                       the default K best.

The machine is shared: every time is a median (and p90, min) over repeats, with the process
CPU time (cpu_median, all threads) beside it, and the load average before/after is recorded, so
noisy runs can be recognised: for single-threaded work wall >> cpu means time spent descheduled.
blas_threads_ab_ms and pca_after_backbone_blas_ab_batch_1 interleave numpy's BLAS threads as they
are vs capped at 1 (threadpoolctl), repeat by repeat, so both see the same load.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from loopclosure.config import (  # noqa: E402
    BackboneConfig,
    DatabaseConfig,
    DetectorConfig,
    SequenceMatchConfig,
    VPRConfig,
    feature_side,
    grid_side,
)
from loopclosure.database import PlaceDatabase  # noqa: E402
from loopclosure.encoder import PlaceCodes  # noqa: E402
from loopclosure.filtering import max_row_norm, rank_neighbours, vote  # noqa: E402
from loopclosure.pca import Codebooks, PCAProjection  # noqa: E402
from loopclosure.spatial import as_float32, best_query_cells, consistency_counts, spatial_scores  # noqa: E402
from ssmvpr_common.atomic import atomic_write_text  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memory import rss_mb  # noqa: E402

SHARED = Path(os.environ.get("SSMVPR_SHARED", ROOT.parent / "shared"))
DEFAULT_IMAGES = SHARED / "data" / "corridor" / "ref"
SHARED_WEIGHTS = SHARED / "weights" / "vgg16_imagenet_conv.pth"

PAPER_SPATIAL_MS = {50: 1600.0, 15: 750.0, 5: 400.0}  # ECMR 2019, per query
PAPER_BYTES_PER_PLACE = 175_000  # 25 kB stage I + 150 kB stage II
TARGETS = {"spatial_50_ms": 5.0, "filtering_10k_ms": 20.0, "sequence_query_L5_N50_ms": 30.0}


# ---- helpers ---------------------------------------------------------------------------------
def log(msg: str) -> None:
    print(f"[bench_vpr] {msg}", file=sys.stderr, flush=True)


class Samples(list):
    """Wall-clock milliseconds, with the process CPU milliseconds (all threads) beside them."""

    def __init__(self) -> None:
        super().__init__()
        self.cpu: list[float] = []


def stats(samples_ms: list[float]) -> dict[str, float]:
    """median / p90 / min of wall ms; cpu_median (process CPU ms, all threads) when recorded.

    On a busy machine wall >> cpu for single-threaded work: the gap is time spent descheduled."""
    a = np.asarray(samples_ms, dtype=np.float64)
    out = {
        "median": round(float(np.median(a)), 3),
        "p90": round(float(np.percentile(a, 90)), 3),
        "min": round(float(a.min()), 3),
        "n": int(a.size),
    }
    cpu = getattr(samples_ms, "cpu", None)
    if cpu:
        out["cpu_median"] = round(float(np.median(cpu)), 3)
    return out


def time_ms(fn: Callable[[int], object], repeats: int, warmup: int = 1) -> Samples:
    """Call fn(i) warmup + repeats times; milliseconds of the timed calls (wall and CPU)."""
    for i in range(warmup):
        fn(-1 - i)
    gc.collect()
    out = Samples()
    for i in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn(i)
        out.append((time.perf_counter() - t0) * 1e3)
        out.cpu.append((time.process_time() - c0) * 1e3)
    return out


def unit_rows(x: np.ndarray) -> np.ndarray:
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    return x


def emit(result: dict, t_start: float, output: str | None) -> dict:
    """Stamp the wall time, print the JSON and write it to `output` (atomically) when given."""
    result["wall_s"] = round(time.perf_counter() - t_start, 1)
    text = json.dumps(result, indent=2)
    if output:
        atomic_write_text(output, text + "\n")
    print(text)
    return result


def loadavg() -> list[float] | None:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def layout(config: VPRConfig) -> dict[str, tuple[int, ...]]:
    """Code shapes the config produces: stage I (n1, d1), stage II (gh, gw, d2)."""
    b = config.backbone
    g1 = grid_side(feature_side(b.stage1_layer, b.input_size), config.filtering.cubes)
    g2 = grid_side(feature_side(b.stage2_layer, b.input_size), config.spatial.cubes)
    return {"stage1": (g1 * g1, config.filtering.pca.dim), "stage2": (g2, g2, config.spatial.pca.dim)}


def random_projection(rng: np.random.Generator, d_in: int, d_out: int, l2_out: bool) -> PCAProjection:
    comps = rng.standard_normal((d_out, d_in), dtype=np.float32) / np.float32(np.sqrt(d_in))
    return PCAProjection(
        mean=rng.standard_normal(d_in, dtype=np.float32) * np.float32(1e-3),
        components=comps,
        explained_variance=np.ones(d_out, np.float32),
        whiten=False,
        l2_normalize_output=l2_out,
    )


def random_codebooks(config: VPRConfig, d1_in: int, d2_in: int, seed: int = 0) -> Codebooks:
    rng = np.random.default_rng(seed)
    return Codebooks(
        random_projection(rng, d1_in, config.filtering.pca.dim, config.filtering.pca.l2_normalize_output),
        random_projection(rng, d2_in, config.spatial.pca.dim, config.spatial.pca.l2_normalize_output),
    )


def blas_limit(n: int | None):
    """Context that caps numpy's BLAS threads (threadpoolctl); a no-op when n is None."""
    import contextlib

    if n is None:
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(n, user_api="blas")


def thread_pools() -> list[dict] | None:
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return None
    keep = ("user_api", "internal_api", "num_threads", "prefix", "version", "threading_layer")
    return [{k: p.get(k) for k in keep if k in p} for p in threadpool_info()]


# ---- machine ---------------------------------------------------------------------------------
def machine_info(device: str) -> dict:
    import torch

    info = {
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "cpu_model": cpu_model(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": device,
        "cuda_available": torch.cuda.is_available(),
        "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "loadavg_start": loadavg(),
        "thread_pools": thread_pools(),
    }
    try:
        info["blas"] = np.show_config(mode="dicts")["Build Dependencies"]["blas"]["name"]
    except Exception:  # noqa: BLE001 - informational only
        pass
    return info


# ---- weights ---------------------------------------------------------------------------------
def pick_weights(requested: str | None, allow_download: bool) -> tuple[dict | None, dict]:
    """State dict (or None = random) and a description of where it came from."""
    from loopclosure.weights import load_state_dict, resolve_weights

    if requested == "random":
        return None, {"source": "random", "random_weights": True, "reason": "--weights random"}
    failures: list[str] = []
    candidates: list[tuple[str, Callable[[], Path]]] = []
    if requested:
        candidates.append(("--weights", lambda: resolve_weights(requested, allow_download=False)))
    else:
        candidates.append(("resolve_weights", lambda: resolve_weights(None, allow_download=allow_download)))
        candidates.append(("shared", lambda: SHARED_WEIGHTS))
    for label, get in candidates:
        try:
            path = get()
            t0 = time.perf_counter()
            state = load_state_dict(path)
            return state, {
                "source": label,
                "path": str(path),
                "random_weights": False,
                "load_s": round(time.perf_counter() - t0, 3),
            }
        except Exception as exc:  # noqa: BLE001 - any failure falls through to the next way
            failures.append(f"{label}: {type(exc).__name__}: {str(exc).splitlines()[0][:300]}")
    log("no VGG16 weights found; timing the CNN with RANDOM weights (speed does not depend on them)")
    return None, {"source": "random", "random_weights": True, "reason": "; ".join(failures)}


# ---- images ----------------------------------------------------------------------------------
def load_images(folder: Path, limit: int, size: int) -> tuple[list[np.ndarray], dict]:
    """Prepared (square RGB uint8) images and the per-image read+resize cost."""
    from loopclosure.backbone_input import list_images, read_image, resize_square

    try:
        files = list_images(folder)[:limit]
    except Exception as exc:  # noqa: BLE001
        log(f"no images in {folder} ({exc}); using synthetic images")
        rng = np.random.default_rng(0)
        imgs = [rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for _ in range(limit)]
        return imgs, {"images": "synthetic", "reason": str(exc), "count": limit}
    times, imgs = [], []
    for f in files:
        t0 = time.perf_counter()
        imgs.append(resize_square(read_image(f), size))
        times.append((time.perf_counter() - t0) * 1e3)
    raw = read_image(files[0])
    return imgs, {
        "images": str(folder),
        "count": len(files),
        "source_shape": list(raw.shape),
        "read_and_resize_ms_per_image": stats(times),
    }


# ---- stage: CNN encode -----------------------------------------------------------------------
def bench_encode(args, config: VPRConfig, repeats: dict[int, int]) -> dict:
    import torch

    from loopclosure.backbone import Backbone, cube_dims
    from loopclosure.cubes import extract_cubes
    from loopclosure.encoder import Encoder, RawCubes

    state, weights_info = pick_weights(args.weights, args.allow_download)
    backbone_cfg = config.backbone.model_copy(update={"weights": "random" if state is None else None})
    images, images_info = load_images(Path(args.images), args.max_images, config.backbone.input_size)
    calibration = np.stack(images) if backbone_cfg.precision == "int8" else None
    backbone = Backbone(backbone_cfg, state, calibration_images=calibration)
    del state

    # Codebook shapes as the net makes them; values are random (projection cost is value-independent).
    dims = cube_dims(config)
    codebooks = random_codebooks(config, dims["stage1"], dims["stage2"])
    encoder = Encoder(config, backbone, codebooks)

    def encode_parts(batch: list[np.ndarray]) -> tuple[PlaceCodes, float, float, float]:
        """Encoder.raw_cubes + Encoder.project, timed step by step (same calls, same order)."""
        t0 = time.perf_counter()
        maps1, maps2 = backbone(np.stack(batch))
        t1 = time.perf_counter()
        s1 = extract_cubes(maps1, config.filtering.cubes)
        raw = RawCubes(s1.reshape(s1.shape[0], -1, s1.shape[-1]), extract_cubes(maps2, config.spatial.cubes))
        t2 = time.perf_counter()
        codes = encoder.project(raw)
        t3 = time.perf_counter()
        return codes, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3

    # The step-by-step path must be the library's path (these two passes also warm the net up).
    ref = encoder.encode(images[:1])
    mine = encode_parts(images[:1])[0]
    same = bool(np.allclose(ref.stage1, mine.stage1, atol=1e-4) and np.allclose(ref.stage2, mine.stage2, atol=1e-3))

    out: dict = {
        "weights": weights_info,
        "precision": {"requested": backbone_cfg.precision, "resolved": backbone.precision},
        "pca_codebooks": "random projections of the real shapes (speed does not depend on values)",
        "input_size": config.backbone.input_size,
        "layers": [config.backbone.stage1_layer, config.backbone.stage2_layer],
        "code_shapes": {"stage1": list(ref.stage1.shape[1:]), "stage2": list(ref.stage2.shape[1:])},
        "cube_dims": dims,
        "matches_encoder_encode": same,
        **images_info,
    }
    cursor = [0]

    for n_bs, (bs, reps) in enumerate(repeats.items()):
        parts: dict[str, list[float]] = {"backbone": [], "cubes": [], "pca": [], "total": []}

        def run(i: int, bs: int = bs, parts=parts) -> None:
            start = cursor[0]
            batch = [images[(start + j) % len(images)] for j in range(bs)]
            cursor[0] += bs
            _, a, b, c = encode_parts(batch)
            if i >= 0:
                for key, v in zip(("backbone", "cubes", "pca", "total"), (a, b, c, a + b + c)):
                    parts[key].append(v)

        log(f"cnn_encode batch {bs}: {reps} repeats")
        # Batch 1 is warm after the check; a new batch shape gets one untimed pass (not in --quick).
        samples = time_ms(run, reps, warmup=0 if (bs == 1 or (args.quick and n_bs > 0)) else 1)
        total = stats(samples)
        med_s = total["median"] / 1e3
        out[f"batch_{bs}"] = {
            "images_per_s": round(bs / med_s, 2),
            "ms_per_image": round(total["median"] / bs, 2),
            "ms_per_batch": total,
            "breakdown_ms_per_batch_median": {k: round(float(np.median(v)), 2) for k, v in parts.items()},
        }
    if args.ab_repeats and 1 in repeats:
        ab_reps = max(1, args.ab_repeats // 2)
        out["pca_after_backbone_blas_ab_batch_1"] = pca_blas_ab(backbone, encoder, config, images, ab_reps)
    out["torch_threads"] = torch.get_num_threads()
    return out


def pca_blas_ab(backbone, encoder, config: VPRConfig, images: list[np.ndarray], repeats: int) -> dict:
    """PCA projection timed right after a backbone pass (the streaming case), BLAS threads as
    they are vs capped at 1: torch's OpenMP workers and OpenBLAS's pthreads fight for the cores."""
    from loopclosure.cubes import extract_cubes
    from loopclosure.encoder import RawCubes

    samples: dict[str, list[float]] = {"blas_default": [], "blas_1": []}
    for i in range(repeats):
        for label, limit in (("blas_default", None), ("blas_1", 1)):
            maps1, maps2 = backbone(np.stack(images[i % len(images) : i % len(images) + 1]))
            s1 = extract_cubes(maps1, config.filtering.cubes)
            raw = RawCubes(s1.reshape(s1.shape[0], -1, s1.shape[-1]), extract_cubes(maps2, config.spatial.cubes))
            with blas_limit(limit):
                t0 = time.perf_counter()
                encoder.project(raw)
                samples[label].append((time.perf_counter() - t0) * 1e3)
    return {k: stats(v) for k, v in samples.items()}


# ---- stage I: filtering ----------------------------------------------------------------------
def synthetic_stage1(
    n_places: int, shape: tuple[int, int], dtype: np.dtype, seed: int, chunk: int = 8192
) -> np.ndarray:
    """(P, n1, d1) unit-norm codes in the database's stage-I layout, filled chunk by chunk."""
    rng = np.random.default_rng(seed)
    db = np.empty((n_places, *shape), dtype)
    for start in range(0, n_places, chunk):
        stop = min(start + chunk, n_places)
        db[start:stop] = unit_rows(rng.standard_normal((stop - start, *shape), dtype=np.float32))
    return db


def filtering_breakdown(query: np.ndarray, database: np.ndarray, k: int, excluded: np.ndarray | None) -> dict:
    """The steps of `vote`, replicated one by one to see where the time goes (profiling only)."""
    n_places, per_place, dim = database.shape
    t = [time.perf_counter()]
    allowed = np.ones(n_places, dtype=bool)
    if excluded is not None and len(excluded):
        allowed[excluded] = False
    n_allowed = int(allowed.sum())
    t.append(time.perf_counter())
    sims = query.astype(np.float32, copy=False) @ database.reshape(-1, dim).T.astype(np.float32, copy=False)
    t.append(time.perf_counter())
    if n_allowed < n_places:
        sims.reshape(len(query), n_places, per_place)[:, ~allowed, :] = -np.inf
    t.append(time.perf_counter())
    neg = -sims
    t.append(time.perf_counter())
    part = np.argpartition(neg, k - 1, axis=1)
    t.append(time.perf_counter())
    neighbours = part[:, :k]
    neighbour_sims = np.take_along_axis(sims, neighbours, axis=1).ravel()
    neighbour_places = (neighbours // per_place).ravel()
    votes = np.bincount(neighbour_places, minlength=n_places)
    similarity = np.bincount(neighbour_places, weights=neighbour_sims, minlength=n_places)
    voted = np.flatnonzero(votes)
    np.lexsort((-similarity[voted], -votes[voted]))
    t.append(time.perf_counter())
    names = ("mask_setup", "matmul", "exclude_fill", "negate_copy", "argpartition", "votes_and_rank")
    return {n: (b - a) * 1e3 for n, a, b in zip(names, t[:-1], t[1:])}


def bench_filtering(args, config: VPRConfig, sizes: list[int], repeats: int) -> dict:
    shape = layout(config)["stage1"]
    dtype = np.dtype(DatabaseConfig().stage1_dtype)
    k, n_cand = config.filtering.k_neighbours, config.filtering.num_candidates
    window = args.exclude_recent
    out: dict = {
        "k_neighbours": k,
        "num_candidates": n_cand,
        "stage1_shape": list(shape),
        "stage1_dtype": str(dtype),
        "exclusion_window_places": window,
        "codes": "synthetic unit-norm float32 (PlaceDatabase stage-I layout)",
        "sizes": {},
    }
    # Same layout as a real PlaceDatabase: check on a tiny one.
    cb = random_codebooks(config, 8, 8)
    tiny = PlaceDatabase(cb)
    s2 = layout(config)["stage2"]
    tiny.add(PlaceCodes(np.zeros((1, *shape), np.float32), np.zeros((1, *s2), np.float32)))
    assert tiny.stage1.shape[1:] == shape and tiny.stage1.dtype == dtype, (tiny.stage1.shape, tiny.stage1.dtype)

    rng = np.random.default_rng(1)
    for n_places in sizes:
        gc.collect()
        t0 = time.perf_counter()
        db = synthetic_stage1(n_places, shape, dtype, seed=n_places)
        build_s = time.perf_counter() - t0
        # Queries: noisy copies of database places, so the neighbours are realistic.
        picks = rng.integers(0, n_places, size=repeats + 2)
        noise = [0.3 * rng.standard_normal(shape, dtype=np.float32) for _ in picks]
        queries = [unit_rows(db[p].astype(np.float32) + e) for p, e in zip(picks, noise)]
        excluded = np.arange(max(0, n_places - window), n_places)
        norm = max_row_norm(db.reshape(-1, shape[-1]))  # a database keeps this bound up to date
        entry: dict = {"build_s": round(build_s, 2), "db_mb": round(db.nbytes / 2**20, 1)}
        for label, exc in (("no_exclusion", None), ("with_exclusion", excluded)):
            log(f"filtering P={n_places} {label}: {repeats} repeats")
            samples = time_ms(lambda i, exc=exc: vote(queries[i], db, k, n_cand, exc, norm), repeats, warmup=1)
            entry[label] = stats(samples)
        bd = [filtering_breakdown(queries[i % len(queries)], db, k, excluded) for i in range(max(3, repeats // 2))]
        entry["breakdown_ms_median_with_exclusion"] = {
            key: round(float(np.median([b[key] for b in bd])), 3) for key in bd[0]
        }
        # Transient memory a query allocates: sims, -sims, argpartition's int64 index array.
        n_vec = shape[0] * (n_places * shape[0])  # (query vectors) x (database vectors)
        entry["transient_mb_per_query"] = {
            "sims_f32": round(n_vec * 4 / 2**20, 1),
            "negated_copy_f32": round(n_vec * 4 / 2**20, 1),
            "argpartition_int64": round(n_vec * 8 / 2**20, 1),
        }
        out["sizes"][str(n_places)] = entry
        db = None  # freed before the next size (the lambdas above ran already)
    return out


# ---- stage I through faiss: exact vs IVF at growing sizes ----------------------------------------
def street_codes(n_places: int, shape: tuple[int, int], seed: int, street: int = 200, rho: float = 0.93) -> np.ndarray:
    """Synthetic stage-I codes shaped like real ones (measured on Corridor's PCA codes): a
    power-law spectrum (variance of component i ~ 1/i: effective dimension 16.5, Corridor 16.5),
    slots of one place independent (Corridor: cosine 0.016), each slot drifting along a street
    of `street` places (AR(1), consecutive cosine ~rho; Corridor 0.93), a new street afresh."""
    n, d = shape
    rng = np.random.default_rng(seed)
    sd = (np.arange(1, d + 1, dtype=np.float32) ** -0.5).astype(np.float32)
    out = np.empty((n_places, n, d), np.float32)
    n_streets = -(-n_places // street)
    keep = np.float32(np.sqrt(1 - rho**2))
    z = None
    for step in range(street):  # all streets advance together
        rows = np.arange(step, n_places, street)
        e = rng.standard_normal((len(rows), n, d), dtype=np.float32) * sd
        z = e if step == 0 else np.float32(rho) * z[: len(rows)] + keep * e
        out[rows] = z
    del n_streets
    for start in range(0, n_places, 65536):
        unit_rows(out[start : start + 65536])
    return out


def revisit_queries(db: np.ndarray, count: int, cosine: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Noisy copies of random places whose vectors keep `cosine` to the originals (Corridor's
    query vectors: 0.71 to their best vector in the right place)."""
    rng = np.random.default_rng(seed)
    n, d = db.shape[1:]
    sd = (np.arange(1, d + 1, dtype=np.float32) ** -0.5).astype(np.float32)
    places = rng.integers(0, len(db), count)
    noise = unit_rows(rng.standard_normal((count, n, d), dtype=np.float32) * sd)
    sigma = np.float32(np.sqrt(1.0 / cosine**2 - 1.0))
    return unit_rows(db[places] + sigma * noise), places


def _same_votes(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("places", "votes", "scores"))


def bench_stage1_index(args, config: VPRConfig, sizes: list[int], repeats: int) -> dict:
    """Exact (faiss) vs IVF stage I: query ms and recall@N of the candidates against exact voting,
    build and append seconds, on street-like synthetic codes with an exclusion window."""
    from loopclosure.ann_index import StageOneIndex

    shape = layout(config)["stage1"]
    per, d = shape
    k, n_cand, window = config.filtering.k_neighbours, config.filtering.num_candidates, args.exclude_recent
    nprobes = _ints(args.nprobes)
    out: dict = {
        "codes": "street_codes: power-law spectrum, AR(1) slots along 200-place streets (see its docstring)",
        "query_cosine": args.query_cosine, "k_neighbours": k, "num_candidates": n_cand,
        "exclusion_window_places": window, "faiss_threads": config.filtering.faiss_threads,
        "recall": "|ANN top-N places & exact top-N places| / N, mean (and min) over queries", "sizes": {},
    }  # fmt: skip
    for n_places in sizes:
        gc.collect()
        log(f"stage-I index P={n_places}: generating codes")
        t0 = time.perf_counter()
        db = street_codes(n_places + args.append_places, shape, seed=n_places)
        flat = db.reshape(-1, d)
        entry: dict = {"generate_s": round(time.perf_counter() - t0, 1), "loadavg_start": loadavg()}
        queries, sources = revisit_queries(db[:n_places], repeats + 2, args.query_cosine, seed=1)
        # the place a query revisits (within 2) among the candidates: what recognition needs
        found = lambda c, i: bool(np.any(np.abs(c.places - sources[i]) <= 2))  # noqa: E731
        excluded = np.arange(n_places - window, n_places)
        rows = lambda lo, hi: flat[lo:hi]  # noqa: E731

        exact_config = config.filtering.model_copy(
            update={
                "index": "exact",
                "exact_backend": args.exact_backend,
                "torch_device": args.torch_device,
                "torch_block_rows": args.torch_block_rows,
                "torch_storage": args.torch_storage,
            }
        )
        exact = StageOneIndex(exact_config, d, per)
        entry["exact_search"] = {"backend": args.exact_backend, "device": exact.search_device or "cpu (faiss)",
                                 "storage": exact.search_storage or "float32"}  # fmt: skip
        t0 = time.perf_counter()
        exact.sync(n_places, rows, flat[: n_places * per])
        entry["exact_build_s"] = round(time.perf_counter() - t0, 3)

        def run(index, q, view=None):
            return rank_neighbours(q, lambda ids: flat[ids], index.candidates(q, k, excluded, view), k, per, n_cand)

        log(f"stage-I index P={n_places}: exact, {args.exact_repeats} queries")
        view = flat[: n_places * per]
        truth = [run(exact, q, view) for q in queries[: args.exact_repeats]]
        entry["exact_true_place_in_candidates"] = round(float(np.mean([found(c, i) for i, c in enumerate(truth)])), 4)
        entry["exact_query_ms"] = stats(
            time_ms(lambda i: run(exact, queries[i], view), min(repeats, args.exact_repeats))
        )
        if args.check_votes:  # the index's exact votes against numpy brute force (places, votes, scores)
            log(f"stage-I index P={n_places}: {args.check_votes} queries against numpy brute force")
            stored = db[:n_places]
            agree = [_same_votes(truth[i], vote(queries[i], stored, k, n_cand, excluded))
                     for i in range(min(args.check_votes, len(truth)))]  # fmt: skip
            entry["exact_equals_numpy"] = {"queries": len(agree), "equal": int(sum(agree))}
        exact = None  # freed before the next size (the lambdas above ran already)
        gc.collect()
        for nlist in (_ints(args.nlists) or [None]) if args.nprobes else []:
            cfg = config.filtering.model_copy(
                update={
                    "index": "ivf",
                    "ivf_nlist": nlist,
                    "faiss_threads": args.build_threads,
                    "ivf_codes": args.ivf_codes,
                }
            )
            ivf = StageOneIndex(cfg, d, per)
            log(f"stage-I index P={n_places}: IVF nlist={nlist or 'auto'} train + add")
            t0 = time.perf_counter()
            ivf.sync(n_places, rows)
            key = f"ivf_nlist_{ivf._index.nlist}"
            res: dict = {"build_s": round(time.perf_counter() - t0, 1), "build_threads": args.build_threads,
                         "train_vectors": min(n_places * per, cfg.ivf_train_vectors * ivf._index.nlist), "nprobe": {}}  # fmt: skip
            for nprobe in nprobes:
                ivf.config = cfg.model_copy(
                    update={"ivf_nprobe": nprobe, "faiss_threads": config.filtering.faiss_threads}
                )
                recall, hits = [], []
                for i, (q, ref) in enumerate(zip(queries, truth)):
                    got = run(ivf, q)
                    recall.append(len(np.intersect1d(got.places, ref.places)) / max(1, len(ref.places)))
                    hits.append(found(got, i))
                res["nprobe"][str(nprobe)] = {
                    "query_ms": stats(time_ms(lambda i: run(ivf, queries[i]), repeats)),
                    "recall_at_n_mean": round(float(np.mean(recall)), 4), "recall_at_n_min": round(float(np.min(recall)), 4),
                    "true_place_in_candidates": round(float(np.mean(hits)), 4),
                }  # fmt: skip
                log(
                    f"  nprobe {nprobe}: {res['nprobe'][str(nprobe)]['query_ms']['median']} ms, recall {np.mean(recall):.3f}"
                )
            # streaming appends between retrains: one place at a time
            ivf.config = cfg.model_copy(update={"faiss_threads": config.filtering.faiss_threads})
            appends = Samples()
            for i in range(args.append_places):
                t0 = time.perf_counter()
                ivf.sync(n_places + i + 1, rows)
                appends.append((time.perf_counter() - t0) * 1e3)
            res["append_ms_per_place"] = stats(appends) if appends else None
            entry[key] = res
            ivf = None  # freed before the next size (the lambdas above ran already)
            gc.collect()
        if args.hnsw_ef:
            cfg = config.filtering.model_copy(update={"index": "hnsw", "faiss_threads": args.build_threads})
            hnsw = StageOneIndex(cfg, d, per)
            log(f"stage-I index P={n_places}: HNSW M={cfg.hnsw_m} efConstruction={cfg.hnsw_ef_construction} build")
            t0 = time.perf_counter()
            hnsw.sync(n_places, rows)
            res = {"build_s": round(time.perf_counter() - t0, 1), "build_threads": args.build_threads, "m": cfg.hnsw_m,
                   "ef_construction": cfg.hnsw_ef_construction, "ef_search": {}}  # fmt: skip
            for ef in _ints(args.hnsw_ef):
                hnsw.config = cfg.model_copy(
                    update={"hnsw_ef_search": ef, "faiss_threads": config.filtering.faiss_threads}
                )
                recall = [
                    len(np.intersect1d(run(hnsw, q).places, ref.places)) / max(1, len(ref.places))
                    for q, ref in zip(queries, truth)
                ]
                res["ef_search"][str(ef)] = {
                    "query_ms": stats(time_ms(lambda i: run(hnsw, queries[i]), repeats)),
                    "recall_at_n_mean": round(float(np.mean(recall)), 4), "recall_at_n_min": round(float(np.min(recall)), 4),
                }  # fmt: skip
                log(
                    f"  efSearch {ef}: {res['ef_search'][str(ef)]['query_ms']['median']} ms, recall {np.mean(recall):.3f}"
                )
            entry["hnsw"] = res
            hnsw = None  # freed before the next size (the lambdas above ran already)
        entry["loadavg_end"] = loadavg()
        out["sizes"][str(n_places)] = entry
        db = flat = None  # freed before the next size (the lambdas above ran already)
    return out


# ---- stage II: spatial matching --------------------------------------------------------------
def bench_spatial(args, config: VPRConfig, counts: list[int], repeats: int) -> dict:
    gh, gw, d = layout(config)["stage2"]
    dtype = np.dtype(DatabaseConfig().stage2_dtype)
    chunk = config.spatial.chunk_candidates
    rng = np.random.default_rng(2)
    n_store = max(args.store_places, max(counts))
    # Unnormalised stage-II codes (the default), stored in the database's stage-II dtype.
    store = rng.standard_normal((n_store, gh, gw, d), dtype=np.float32).astype(dtype)
    store32 = store.astype(np.float32)
    from loopclosure.database import QuantisedArray, code_weights, quantise

    weights = code_weights(random_codebooks(config, 8, 8).stage2)
    store8 = QuantisedArray(*quantise(store32, weights), weights)  # as int8 storage reads it: q * s * w
    out: dict = {
        "grid": [gh, gw, d],
        "stage2_dtype": str(dtype),
        "chunk_candidates": chunk,
        "store_places": n_store,
        "paper_ms": {str(n): PAPER_SPATIAL_MS[n] for n in counts if n in PAPER_SPATIAL_MS},
        "counts": {},
    }
    for n in counts:
        places_list = [np.sort(rng.choice(n_store, n, replace=False)) for _ in range(repeats + 2)]
        queries = [rng.standard_normal((gh, gw, d), dtype=np.float32) for _ in range(repeats + 2)]
        log(f"spatial N={n}: {repeats} repeats")
        # As TwoStageRanker.query: gather the candidates' grids, then score (conversion inside).
        total = time_ms(lambda i: spatial_scores(queries[i], store[places_list[i]], chunk), repeats)
        gather = time_ms(lambda i: store[places_list[i]], repeats)
        cands = [store[p] for p in places_list]
        score = time_ms(lambda i: spatial_scores(queries[i], cands[i], chunk), repeats)
        score32 = time_ms(lambda i: spatial_scores(queries[i], store32[places_list[i]], chunk), repeats)
        score8 = time_ms(lambda i: spatial_scores(queries[i], store8[places_list[i]], chunk), repeats)
        entry = {
            "gather_and_score": stats(total),
            "gather_only": stats(gather),
            "score_only": stats(score),
            "float32_storage_gather_and_score": stats(score32),
            "int8_storage_gather_and_score": stats(score8),
        }
        if n in PAPER_SPATIAL_MS:
            entry["speedup_vs_paper"] = round(PAPER_SPATIAL_MS[n] / max(entry["gather_and_score"]["median"], 1e-6), 1)
        # Where the time goes (same functions spatial_scores calls, one chunk).
        c = cands[0][:chunk]
        q = queries[0]
        conv = time_ms(lambda i: as_float32(c.reshape(-1, d)), repeats)
        conv_numpy = time_ms(lambda i: c.reshape(-1, d).astype(np.float32, copy=False), repeats)
        c32 = c.astype(np.float32)
        best_t = time_ms(lambda i: best_query_cells(q, c32), repeats)
        best = best_query_cells(q, c32)
        counts_t = time_ms(lambda i: consistency_counts(best), repeats)
        entry["breakdown_ms_median"] = {
            "to_float32": round(float(np.median(conv)), 3),
            "to_float32_numpy": round(float(np.median(conv_numpy)), 3),
            "best_query_cells_f32_input": round(float(np.median(best_t)), 3),
            "consistency_counts": round(float(np.median(counts_t)), 3),
        }
        out["counts"][str(n)] = entry
    return out


# ---- sequence matching -------------------------------------------------------------------------
def bench_sequence(args, config: VPRConfig, lengths: list[int], repeats: int) -> dict:
    from threadpoolctl import threadpool_limits

    from loopclosure.sequence_matcher import SequenceMatcher

    shape1 = layout(config)["stage1"]
    gh, gw, d = layout(config)["stage2"]
    n_places = args.store_places
    window = min(args.exclude_recent, n_places // 2)
    limit = n_places - window
    k, n_cand, chunk = config.filtering.k_neighbours, config.filtering.num_candidates, config.spatial.chunk_candidates
    rng = np.random.default_rng(5)
    db1 = synthetic_stage1(n_places, shape1, np.dtype(DatabaseConfig().stage1_dtype), seed=11)
    store = rng.standard_normal((n_places, gh, gw, d), dtype=np.float32).astype(DatabaseConfig().stage2_dtype)
    excluded = np.arange(limit, n_places)
    norm1 = max_row_norm(db1.reshape(-1, shape1[-1]))
    n_stream = repeats + max(lengths)
    first = int(rng.integers(0, max(1, limit - n_stream)))
    truth = [(first + t) % limit for t in range(n_stream)]
    q1 = [unit_rows(db1[p].astype(np.float32) + 0.3 * rng.standard_normal(shape1, dtype=np.float32)) for p in truth]
    q2 = [store[p].astype(np.float32) + 0.5 * rng.standard_normal((gh, gw, d), dtype=np.float32) for p in truth]

    def scorer(grid: np.ndarray, places: np.ndarray) -> np.ndarray:
        return spatial_scores(grid, store[places], chunk).scores

    default_k = SequenceMatchConfig().sequence_candidates  # vpr-eval's K
    detector_k = DetectorConfig().sequence.sequence_candidates  # the SLAM detector's K
    out: dict = {
        "store_places": n_places, "exclusion_window_places": window, "num_candidates": n_cand,
        "stream_queries": n_stream, "timed_queries": repeats, "blas_threads": 1,
        "default_sequence_candidates": default_k, "detector_sequence_candidates": detector_k, "settings": {},
    }  # fmt: skip
    for length in lengths:
        for direction in ("forward", "both"):
            for k_best in (None, default_k, detector_k):
                seq_cfg = SequenceMatchConfig(length=length, direction=direction, sequence_candidates=k_best)
                matcher = SequenceMatcher(seq_cfg, scorer)
                rows: dict[str, Samples] = {n: Samples() for n in ("filter", "spatial", "matcher", "total")}
                scored, found = [], 0
                log(f"sequence L={length} {direction} K={k_best or 'all'}: {n_stream} queries")
                with threadpool_limits(limits=1, user_api="blas"):
                    for t in range(n_stream):
                        c0, t0 = time.process_time(), time.perf_counter()
                        cands = vote(q1[t], db1, k, n_cand, excluded, norm1)
                        t1 = time.perf_counter()
                        extra = np.setdiff1d(matcher.continuations(limit), cands.places)
                        places = np.concatenate([cands.places, extra])
                        scores = scorer(q2[t], places)
                        t2 = time.perf_counter()
                        m = matcher.step(q2[t], cands.places, scores[: len(cands)], limit, extra, scores[len(cands) :])
                        t3 = time.perf_counter()
                        if t < n_stream - repeats:
                            continue  # the sequence warms up
                        for name, ms in (
                            ("filter", t1 - t0),
                            ("spatial", t2 - t1),
                            ("matcher", t3 - t2),
                            ("total", t3 - t0),
                        ):
                            rows[name].append(ms * 1e3)
                        rows["total"].cpu.append((time.process_time() - c0) * 1e3)
                        scored.append(len(places) + matcher.scored_last_step)
                        found += m.place == truth[t]
                out["settings"][f"L{length}_{direction}_K{k_best or 'all'}"] = {
                    "length": length, "direction": direction, "sequence_candidates": k_best,
                    **{f"{name}_ms": stats(v) for name, v in rows.items()},
                    "spatial_scores_per_query_median": float(np.median(scored)),
                    "true_place_found": f"{found}/{repeats}",
                }  # fmt: skip
    return out


# ---- BLAS threads A/B -------------------------------------------------------------------------
def bench_blas_ab(
    config: VPRConfig, n_places: int, n_candidates: int, repeats: int, window: int, store_places: int
) -> dict:
    """Filtering and spatial matching with BLAS threads as they are vs capped at 1, interleaved
    repeat by repeat so both see the same machine load."""
    shape = layout(config)["stage1"]
    gh, gw, d = layout(config)["stage2"]
    rng = np.random.default_rng(4)
    db = synthetic_stage1(n_places, shape, np.dtype(DatabaseConfig().stage1_dtype), seed=7)
    excluded = np.arange(max(0, n_places - window), n_places)
    norm = max_row_norm(db.reshape(-1, shape[-1]))
    store = rng.standard_normal((max(store_places, n_candidates), gh, gw, d), dtype=np.float32).astype(
        DatabaseConfig().stage2_dtype
    )
    k, n_cand = config.filtering.k_neighbours, config.filtering.num_candidates
    chunk = config.spatial.chunk_candidates
    out: dict = {}
    for name, fn in (
        (f"filtering_{n_places}_with_exclusion", lambda q, c: vote(q, db, k, n_cand, excluded, norm)),
        (f"spatial_{n_candidates}", lambda q, c: spatial_scores(q, store[c], chunk)),
    ):
        samples: dict[str, list[float]] = {"blas_default": [], "blas_1": []}
        for i in range(repeats + 1):
            q1 = unit_rows(rng.standard_normal(shape, dtype=np.float32))
            q2 = rng.standard_normal((gh, gw, d), dtype=np.float32)
            cands = np.sort(rng.choice(len(store), n_candidates, replace=False))
            q = q1 if name.startswith("filtering") else q2
            for label, limit in (("blas_default", None), ("blas_1", 1)):
                with blas_limit(limit):
                    t0 = time.perf_counter()
                    fn(q, cands)
                    if i:  # the first round is a warm-up
                        samples[label].append((time.perf_counter() - t0) * 1e3)
        out[name] = {k2: stats(v) for k2, v in samples.items()}
    return out


# ---- storage ---------------------------------------------------------------------------------
def bench_storage(config: VPRConfig) -> dict:
    shapes = layout(config)
    cb = random_codebooks(config, 8, 8)
    rng = np.random.default_rng(3)
    n = 16
    codes = PlaceCodes(
        unit_rows(rng.standard_normal((n, *shapes["stage1"]), dtype=np.float32)),
        rng.standard_normal((n, *shapes["stage2"]), dtype=np.float32),
    )
    out: dict = {"paper_bytes_per_place": PAPER_BYTES_PER_PLACE}
    for label, dbc in (
        ("default", DatabaseConfig()),
        ("float32", DatabaseConfig(stage1_dtype="float32", stage2_dtype="float32")),
        ("int8", DatabaseConfig(stage1_dtype="int8", stage2_dtype="int8")),
        ("stage2_int8", DatabaseConfig(stage2_dtype="int8")),
    ):
        db = PlaceDatabase(cb, dbc)
        db.add(codes)
        with tempfile.TemporaryDirectory() as tmp:
            folder = db.save(tmp)
            disk = sum(f.stat().st_size for f in folder.glob("stage*.npy"))
        out[label] = {
            "dtypes": [dbc.stage1_dtype, dbc.stage2_dtype],
            "bytes_per_place": db.bytes_per_place,
            "stage1_bytes": db._codes["stage1"].place_bytes(),
            "stage2_bytes": db._codes["stage2"].place_bytes(),
            "disk_npy_bytes_per_place": round(disk / n, 1),
            "fraction_of_paper": round(db.bytes_per_place / PAPER_BYTES_PER_PLACE, 3),
        }
    return out


def bench_mapped_map(config: VPRConfig, n_places: int, dtype: str, folder: Path) -> dict:
    """A saved map of n_places: open memory-mapped vs read into RAM, then appends in place
    (add + commit per place, as a checkpoint per keyframe would), with resident memory."""
    shapes = layout(config)
    cb = random_codebooks(config, 8, 8)
    dbc = DatabaseConfig(stage1_dtype=dtype, stage2_dtype=dtype if dtype != "float32" else "float16")
    rng = np.random.default_rng(9)
    db = PlaceDatabase(cb, dbc)
    t0 = time.perf_counter()
    for start in range(0, n_places, 5000):
        m = min(5000, n_places - start)
        db.add(PlaceCodes(unit_rows(rng.standard_normal((m, *shapes["stage1"]), dtype=np.float32)),
                          rng.standard_normal((m, *shapes["stage2"]), dtype=np.float32)))  # fmt: skip
    db.save(folder)
    write_s = time.perf_counter() - t0
    db = None  # freed before the next size (the lambdas above ran already)
    gc.collect()
    out: dict = {"places": n_places, "dtypes": [dbc.stage1_dtype, dbc.stage2_dtype], "write_s": round(write_s, 1),
                 "disk_mb": round(sum(f.stat().st_size for f in folder.iterdir()) / 2**20, 1)}  # fmt: skip
    peak0 = rss_mb()
    t0 = time.perf_counter()
    mapped = PlaceDatabase.load(folder, mmap=True)
    out["open_mapped_s"] = round(time.perf_counter() - t0, 3)
    out["open_mapped_rss_growth_mb"] = round(rss_mb() - peak0, 1)
    del mapped
    grow = PlaceDatabase.open(folder)
    one = PlaceCodes(unit_rows(rng.standard_normal((1, *shapes["stage1"]), dtype=np.float32)),
                     rng.standard_normal((1, *shapes["stage2"]), dtype=np.float32))  # fmt: skip
    adds, commits = Samples(), Samples()
    for _ in range(5):
        t0 = time.perf_counter()
        grow.add(one)
        t1 = time.perf_counter()
        grow.commit()
        adds.append((t1 - t0) * 1e3)
        commits.append((time.perf_counter() - t1) * 1e3)
    out["append_add_ms"], out["append_commit_ms"] = stats(adds), stats(commits)
    del grow
    gc.collect()
    t0 = time.perf_counter()
    peak0 = rss_mb()
    ram = PlaceDatabase.load(folder)
    out["load_in_ram_s"] = round(time.perf_counter() - t0, 3)
    out["load_in_ram_rss_growth_mb"] = round(rss_mb() - peak0, 1)
    del ram
    return out


# ---- main ------------------------------------------------------------------------------------
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None, help="VGG16 weights file, or 'random' (default: resolve, then shared)")
    ap.add_argument("--allow-download", action="store_true", help="let weight resolution download (off by default)")
    ap.add_argument("--images", default=str(DEFAULT_IMAGES), help="image folder for the CNN timing")
    ap.add_argument("--max-images", type=int, default=32, help="images read from --images")
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument(
        "--precision",
        choices=("auto", "fp32", "bf16", "int8"),
        default=None,
        help="backbone precision (default: the config's, auto)",
    )
    ap.add_argument("--sizes", default=None, help="database sizes for filtering (default 1000,10000,100000)")
    ap.add_argument("--candidates", default="5,15,50", help="N for spatial matching")
    ap.add_argument("--batch-sizes", default="1,8", help="CNN batch sizes")
    ap.add_argument("--repeats", type=int, default=None, help="repeats for filtering / spatial (default 15, quick 5)")
    ap.add_argument("--encode-repeats", type=int, default=None, help="timed batch-1 passes (default 5, quick 2)")
    ap.add_argument("--store-places", type=int, default=1000, help="stage-II store the candidates come from")
    ap.add_argument("--exclude-recent", type=int, default=100, help="exclusion window: most recent places excluded")
    ap.add_argument("--blas-threads", type=int, default=None, help="cap numpy BLAS threads for the whole run")
    ap.add_argument("--ab-repeats", type=int, default=None, help="repeats of the BLAS-threads A/B (0: skip)")
    ap.add_argument("--skip-encode", action="store_true", help="no CNN timing")
    ap.add_argument("--sequence-lengths", default="3,5", help="L for the sequence matcher timing ('' to skip)")
    ap.add_argument(
        "--index-sizes", default="", help="stage I exact vs IVF at these place counts, e.g. 10000,100000,1000000"
    )
    ap.add_argument("--nlists", default="", help="IVF lists for --index-sizes (default: auto, 4 sqrt(vectors))")
    ap.add_argument("--nprobes", default="8,16,32,64,128", help="IVF lists probed, swept")
    ap.add_argument("--exact-repeats", type=int, default=20, help="queries whose exact votes are the recall reference")
    ap.add_argument("--check-votes", type=int, default=0,
                    help="--index-sizes: compare this many queries' exact votes with numpy brute force")  # fmt: skip
    ap.add_argument("--exact-backend", choices=("faiss", "torch"), default="faiss",
                    help="--index-sizes: exact search in faiss or as torch matrix products (the GPU path)")  # fmt: skip
    ap.add_argument("--torch-device", choices=("auto", "cpu", "cuda"), default="auto",
                    help="--exact-backend torch: its device")  # fmt: skip
    ap.add_argument("--torch-block-rows", type=int, default=None,
                    help="--exact-backend torch: vectors per block (default: 256 MB of similarities, 1 GB on a GPU)")  # fmt: skip
    ap.add_argument("--torch-storage", choices=("auto", "float32", "float16"), default="auto",
                    help="--exact-backend torch: the device copy's precision (auto: float16 on a GPU)")  # fmt: skip
    ap.add_argument("--hnsw-ef", default="", help="also build HNSW and sweep these efSearch values (slow to build)")
    ap.add_argument("--ivf-codes", choices=("flat", "sq8"), default="flat", help="IVF list storage")
    ap.add_argument("--append-places", type=int, default=20, help="places appended one by one after the IVF build")
    ap.add_argument("--build-threads", type=int, default=2, help="faiss threads while training/adding")
    ap.add_argument("--query-cosine", type=float, default=0.71, help="query vector to its place (Corridor: 0.71)")
    ap.add_argument("--only-index", action="store_true", help="only the --index-sizes section (and machine info)")
    ap.add_argument(
        "--mapped-places", type=int, default=0, help="also time a saved map of this many places opened mapped"
    )
    ap.add_argument("--mapped-dtype", choices=("float32", "int8"), default="int8", help="codes of that map")
    ap.add_argument("--quick", action="store_true", help="~30 s: sizes 1000,10000 and few repeats")
    ap.add_argument("--output", default=None, help="also write the JSON to this file")
    return ap.parse_args(argv)


def _sequence_total(section: dict, names: tuple[str, ...]) -> float | None:
    """Worst median total (ms) among the named sequence settings, if all were measured at N = 50."""
    settings = section.get("settings", {})
    if section.get("num_candidates") != 50 or not all(n in settings for n in names):
        return None
    return max(settings[n]["total_ms"]["median"] for n in names)


def _ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    sizes = _ints(args.sizes) if args.sizes else ([1000, 10000] if args.quick else [1000, 10000, 100000])
    repeats = args.repeats or (5 if args.quick else 15)
    enc_reps = args.encode_repeats or (2 if args.quick else 5)
    if args.ab_repeats is None:
        args.ab_repeats = 3 if args.quick else 8
    counts = _ints(args.candidates)
    batch_sizes = _ints(args.batch_sizes)

    import torch

    from loopclosure.backbone import resolve_device

    if args.threads:
        torch.set_num_threads(args.threads)
    backbone_kw = {"precision": args.precision} if args.precision else {}
    config = VPRConfig(backbone=BackboneConfig(device=args.device, allow_download=args.allow_download, **backbone_kw))
    t_start = time.perf_counter()
    machine = machine_info(str(resolve_device(args.device)))
    result: dict = {"tool": "bench_vpr", "quick": bool(args.quick), "machine": machine}
    result["settings"] = {
        "sizes": sizes,
        "repeats": repeats,
        "encode_repeats": enc_reps,
        "ab_repeats": args.ab_repeats,
        "candidates": counts,
        "batch_sizes": batch_sizes,
        "blas_threads": args.blas_threads,
        "exclude_recent": args.exclude_recent,
        "precision": config.backbone.precision,
    }
    if args.only_index:
        result["stage1_index"] = bench_stage1_index(args, config, _ints(args.index_sizes), repeats)
        if args.mapped_places:
            with tempfile.TemporaryDirectory() as tmp:
                result["mapped_map"] = bench_mapped_map(
                    config, args.mapped_places, args.mapped_dtype, Path(tmp) / "map"
                )
        machine["loadavg_end"] = loadavg()
        return emit(result, t_start, args.output)
    with blas_limit(args.blas_threads):
        if args.index_sizes:
            result["stage1_index"] = bench_stage1_index(args, config, _ints(args.index_sizes), repeats)
        if args.skip_encode:
            result["cnn_encode"] = {"skipped": True}
        else:
            # Batch 8 costs ~8x batch 1: fewer timed batches keep the default run short.
            reps = {bs: max(1, enc_reps if bs == 1 else -(-enc_reps * 2 // bs)) for bs in batch_sizes}
            result["cnn_encode"] = bench_encode(args, config, reps)
        filt = result["filtering_query_ms"] = bench_filtering(args, config, sizes, repeats)
        spat = result["spatial_matching_ms"] = bench_spatial(args, config, counts, repeats)
        result["bytes_per_place"] = bench_storage(config)
        if args.mapped_places:
            with tempfile.TemporaryDirectory() as tmp:
                log(f"mapped map of {args.mapped_places} places")
                result["bytes_per_place"]["mapped_map"] = bench_mapped_map(
                    config, args.mapped_places, args.mapped_dtype, Path(tmp) / "map"
                )
        seq_lengths = _ints(args.sequence_lengths)
        result["sequence_query_ms"] = (
            bench_sequence(args, config, seq_lengths, repeats) if seq_lengths else {"skipped": True}
        )
        if args.ab_repeats:
            log(f"BLAS threads A/B: {args.ab_repeats} repeats")
            ab_size = 10000 if 10000 in sizes else sizes[-1]
            result["blas_threads_ab_ms"] = bench_blas_ab(
                config, ab_size, max(counts), args.ab_repeats, args.exclude_recent, args.store_places
            )

    f10k = filt["sizes"].get("10000")
    s50 = spat["counts"].get("50")
    measured = {
        # The worse of with/without exclusion at 10k (SLAM queries always carry a window).
        "filtering_10k_ms": max(f10k["no_exclusion"]["median"], f10k["with_exclusion"]["median"]) if f10k else None,
        # As TwoStageRanker.query pays it: gather the float16 grids, convert, score.
        "spatial_50_ms": s50["gather_and_score"]["median"] if s50 else None,
        # L = 5, N = 50 as configured by default (the best K candidates get sequence terms), the
        # worse of one direction and both
        "sequence_query_L5_N50_ms": _sequence_total(
            result["sequence_query_ms"],
            tuple(f"L5_{d}_K{SequenceMatchConfig().sequence_candidates}" for d in ("forward", "both")),
        ),
    }
    # not a target: every one of the N candidates scored along its sequence (L x N spatial scores)
    result["sequence_query_L5_N50_all_candidates_forward_ms"] = _sequence_total(
        result["sequence_query_ms"], ("L5_forward_Kall",)
    )
    result["targets"] = {
        "targets_ms": TARGETS,
        "measured_median_ms": measured,
        "pass": {k: (None if measured[k] is None else bool(measured[k] <= v)) for k, v in TARGETS.items()},
    }
    machine["loadavg_end"] = loadavg()
    load = [v[0] for v in (machine["loadavg_start"], machine["loadavg_end"]) if v]
    if load and max(load) > 0.75 * (os.cpu_count() or 1):
        machine["note"] = (
            f"busy machine: 1-min load average up to {max(load)} on {os.cpu_count()} CPUs; "
            "timings are inflated and noisy (medians over repeats reported)"
        )
    return emit(result, t_start, args.output)


if __name__ == "__main__":
    main()
