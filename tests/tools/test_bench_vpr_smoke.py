"""tools/bench_vpr.py runs end to end at tiny settings and prints one parseable JSON object."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "bench_vpr.py"
TINY = [
    "--sizes", "300", "--repeats", "2", "--candidates", "5,50",
    "--ab-repeats", "1", "--exclude-recent", "10", "--store-places", "100",
]  # fmt: skip


def _run(*extra: str) -> dict:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), *TINY, *extra], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)  # stdout is exactly one JSON object


def _check_common(out: dict) -> None:
    for key in (
        "machine",
        "settings",
        "cnn_encode",
        "filtering_query_ms",
        "spatial_matching_ms",
        "bytes_per_place",
        "targets",
        "blas_threads_ab_ms",
        "sequence_query_ms",
    ):
        assert key in out, key
    machine = out["machine"]
    for key in ("cpu_count", "torch", "torch_threads", "device", "cuda_device"):
        assert key in machine, key

    size = out["filtering_query_ms"]["sizes"]["300"]
    for label in ("no_exclusion", "with_exclusion"):
        assert size[label]["n"] == 2 and size[label]["median"] > 0 and size[label]["p90"] >= size[label]["median"]
    assert out["filtering_query_ms"]["stage1_shape"] == [16, 100]

    spatial = out["spatial_matching_ms"]
    assert spatial["grid"] == [13, 13, 100] and spatial["stage2_dtype"] == "float16"
    assert set(spatial["counts"]) == {"5", "50"}
    assert spatial["counts"]["50"]["gather_and_score"]["median"] > 0

    storage = out["bytes_per_place"]
    assert storage["default"]["bytes_per_place"] == 16 * 100 * 4 + 13 * 13 * 100 * 2
    assert storage["float32"]["bytes_per_place"] == 16 * 100 * 4 + 13 * 13 * 100 * 4
    assert storage["paper_bytes_per_place"] == 175_000

    sequence = out["sequence_query_ms"]
    assert sequence["num_candidates"] == 50 and sequence["timed_queries"] == 2
    assert set(sequence["settings"]) == {
        f"L{L}_{d}_K{k}" for L in (3, 5) for d in ("forward", "both") for k in ("all", 10, 20)
    }
    full = sequence["settings"]["L5_forward_Kall"]
    assert full["total_ms"]["median"] >= full["matcher_ms"]["median"] > 0
    assert full["total_ms"]["n"] == 2 and "cpu_median" in full["total_ms"]
    # the store is small here (100 places, 10 excluded), so N = 50 is most of it
    assert 50 <= full["spatial_scores_per_query_median"] <= 5 * (50 + 3)

    targets = out["targets"]
    assert set(targets["targets_ms"]) == {"spatial_50_ms", "filtering_10k_ms", "sequence_query_L5_N50_ms"}
    assert targets["measured_median_ms"]["filtering_10k_ms"] is None  # no 10k size at these settings
    assert isinstance(targets["pass"]["spatial_50_ms"], bool)
    assert isinstance(targets["pass"]["sequence_query_L5_N50_ms"], bool)


def test_bench_vpr_tiny_json() -> None:
    out = _run("--skip-encode")
    _check_common(out)
    assert out["cnn_encode"] == {"skipped": True}


@pytest.mark.slow
def test_bench_vpr_encode_random_weights() -> None:
    out = _run("--weights", "random", "--batch-sizes", "1", "--encode-repeats", "1", "--max-images", "2")
    _check_common(out)
    enc = out["cnn_encode"]
    assert enc["weights"]["random_weights"] is True
    assert enc["matches_encoder_encode"] is True
    assert enc["code_shapes"] == {"stage1": [16, 100], "stage2": [13, 13, 100]}
    assert enc["batch_1"]["images_per_s"] > 0
    assert set(enc["batch_1"]["breakdown_ms_per_batch_median"]) == {"backbone", "cubes", "pca", "total"}
