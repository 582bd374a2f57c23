"""tools/bench_vpr.py's stage-I index and mapped-map sections run at tiny settings and report
exact vs IVF timings, recall, build and append times, int8 bytes per place."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "bench_vpr.py"


def test_stage1_index_and_mapped_map_sections() -> None:
    args = ["--only-index", "--index-sizes", "600", "--repeats", "2", "--exact-repeats", "3", "--nprobes", "4,1024",
            "--append-places", "2", "--exclude-recent", "10", "--mapped-places", "30"]  # fmt: skip
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    size = out["stage1_index"]["sizes"]["600"]
    assert size["exact_query_ms"]["median"] > 0 and size["exact_build_s"] >= 0
    (ivf,) = [v for k, v in size.items() if k.startswith("ivf_nlist_")]
    assert ivf["build_s"] >= 0 and ivf["append_ms_per_place"]["n"] == 2
    assert ivf["nprobe"]["1024"]["recall_at_n_mean"] == 1.0  # every list probed: the exact candidates
    assert 0 <= ivf["nprobe"]["4"]["recall_at_n_min"] <= ivf["nprobe"]["4"]["recall_at_n_mean"] <= 1
    mapped = out["mapped_map"]
    assert mapped["places"] == 30 and mapped["dtypes"] == ["int8", "int8"]
    assert mapped["open_mapped_s"] >= 0 and mapped["append_commit_ms"]["n"] == 5


def test_stage1_index_through_the_torch_exact_backend() -> None:
    """The GPU path's timing, here on the CPU device: its votes are the recall reference IVF meets."""
    args = ["--only-index", "--index-sizes", "400", "--repeats", "2", "--exact-repeats", "3", "--nprobes", "1024",
            "--append-places", "1", "--exclude-recent", "10", "--exact-backend", "torch", "--torch-device", "cpu"]  # fmt: skip
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, check=False
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    size = json.loads(proc.stdout)["stage1_index"]["sizes"]["400"]
    assert size["exact_search"] == {"backend": "torch", "device": "cpu", "storage": "float32"}
    assert size["exact_query_ms"]["median"] > 0
    (ivf,) = [v for k, v in size.items() if k.startswith("ivf_nlist_")]
    assert ivf["nprobe"]["1024"]["recall_at_n_mean"] == 1.0


def test_storage_rows_include_int8() -> None:
    sys.path.insert(0, str(SCRIPT.parent))
    import bench_vpr

    from loopclosure.config import VPRConfig

    storage = bench_vpr.bench_storage(VPRConfig())
    assert storage["int8"]["bytes_per_place"] == 16 * 100 + 16 * 4 + 13 * 13 * 100 + 13 * 13 * 4 <= 20_000
    assert storage["stage2_int8"]["bytes_per_place"] == 16 * 100 * 4 + 13 * 13 * 100 + 13 * 13 * 4


def test_the_device_search_breakdown_runs_on_the_cpu() -> None:
    """tools/bench_device_search.py (a GPU's stage-I breakdown) at a tiny size on the CPU device:
    every part timed, the forced chunk selection equal to torch.topk, at least k candidates."""
    script = SCRIPT.parent / "bench_device_search.py"
    proc = subprocess.run(
        [sys.executable, str(script), "--vectors", "20000", "--repeats", "1", "--device", "cpu"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["device"] == "cpu" and out["selection_equals_topk"] is True
    assert set(out["selection_ms"]) == {"torch_topk", "chunks_1024", "chunks_4096", "chunks_16384"}
    assert set(out["proposal_ms"]) == {"float32_torch_topk", "float32_default", "float16_torch_topk", "float16_default"}
    assert all(p["ms"] > 0 and p["candidates_per_row"] >= out["k"] for p in out["proposal_ms"].values())
    too_few = subprocess.run(
        [sys.executable, str(script), "--vectors", "100"], capture_output=True, text=True, check=False
    )
    assert too_few.returncode == 2 and "--vectors: at least 1616" in too_few.stderr
