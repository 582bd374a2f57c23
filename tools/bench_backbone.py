"""Benchmark the VGG16 backbone per precision (fp32, bf16, int8): speed, agreement, physical limit.

Prints ONE JSON object to stdout (progress goes to stderr).

Usage:
  python tools/bench_backbone.py [--precisions fp32,bf16,int8] [--batch-sizes 1,8] [--repeats 7]
                                 [--weights PATH|random] [--images DIR] [--calibration DIR] [--quick]

What is measured (through `loopclosure.backbone.Backbone.__call__`, so preprocessing and the
float32 numpy maps it returns are included):
  ms_per_image        One pass to the stage-I layer (conv5_2) with the stage-II tap (conv4_2) on
                      real images (Corridor ref by default) at input_size 224. The precisions are
                      timed in turn within every repeat, so all of them see the same load.
  agreement           Cosine similarity and relative L2 error of each precision's conv maps against
                      torch fp32 (the reference) on the same images, per stage, worst image.
  gflop_per_image     Multiply-adds x 2 of the convolutions run (counted from the layer shapes).
  gemm_peak           What one large matrix product reaches in torch, fp32 and bf16, on all torch
                      threads: the practical ceiling of a convolution lowered to GEMM.
  isa_peak_gflops     The arithmetic peak of all usable cores: tools/peak_flops.c (register-only
                      512-bit FMA / VDPBF16PS / VPDPBUSD chains, thread CPU time) compiled with
                      `cc -O2 -march=native` and run on every core at once; without a C compiler
                      (or with --peak-gflops) the figures measured on this project's machine.
  physical_limit_ms   gflop_per_image / isa_peak_gflops: no kernel can beat it.
int8 is calibrated on --calibration (default: --images) through ONNX Runtime (extra "int8");
without the extra it is reported as skipped with the reason. The machine is shared: every time
is a median over repeats, beside the load average at the start, middle and end.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

TOOLS = Path(__file__).resolve().parent
sys.path.insert(0, str(TOOLS))

from bench_vpr import DEFAULT_IMAGES, emit, load_images, loadavg, log, machine_info, pick_weights, stats  # noqa: E402

from loopclosure.backbone import Backbone, cpu_has_fast_bf16  # noqa: E402
from loopclosure.config import BackboneConfig  # noqa: E402
from loopclosure.errors import LoopClosureInputError  # noqa: E402

# tools/peak_flops.c on both cores of this project's machine (AMD EPYC, family 26 = Zen 5, about
# 4.2 GHz; 2026-11-24): 265 GFLOP/s fp32, 530 bf16, 1055 GOP/s int8 per core, i.e. 64 / 128 / 256
# per cycle, the full-width 512-bit units.
DEFAULT_PEAK_GFLOPS = {"fp32": 530.0, "bf16": 1060.0, "int8": 2110.0}


def conv_gflop(backbone: Backbone, size: int) -> float:
    """GFLOP (2 x multiply-adds) of the convolutions one image runs through."""
    last = max(backbone._i1, backbone._i2)
    side, total = size, 0
    for index, layer in enumerate(backbone.net.features):
        if index > last:
            break
        if hasattr(layer, "kernel_size") and not hasattr(layer, "out_channels"):  # max-pool
            side //= 2
        elif hasattr(layer, "out_channels"):
            k = layer.kernel_size[0] * layer.kernel_size[1]
            total += 2 * layer.in_channels * layer.out_channels * k * side * side
    return total / 1e9


def isa_peak() -> dict | None:
    """Sum over all usable cores of tools/peak_flops.c run at once; None without a C compiler."""
    import shutil
    import subprocess
    import tempfile

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        exe = Path(tmp) / "peak_flops"
        built = subprocess.run([cc, "-O2", "-march=native", "-o", str(exe), str(TOOLS / "peak_flops.c")],
                               capture_output=True, text=True, check=False)  # fmt: skip
        if built.returncode != 0:
            log(f"peak_flops.c did not build ({built.stderr.strip()[:200]}); using the stored peak")
            return None
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        procs = [subprocess.Popen([str(exe)], stdout=subprocess.PIPE, text=True) for _ in range(cores)]
        per_core = [json.loads(p.communicate()[0]) for p in procs]
    total = {k: round(sum(c[k] for c in per_core), 1) for k in ("fp32", "bf16", "int8")}
    return {"cores": cores, "per_core": per_core, "total": total}


def gemm_peak(repeats: int, device: str = "cpu") -> dict[str, float]:
    """GFLOP/s of an n x n x n torch matmul, fp32 and bf16 (best of repeats; n = 2048 on the
    CPU, 8192 on a GPU, whose fp32 products run as TF32 only if torch was told so)."""
    import torch

    n = 8192 if device == "cuda" else 2048
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    out = {}
    for name, dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        a, b = torch.randn(n, n, device=device).to(dtype), torch.randn(n, n, device=device).to(dtype)
        torch.mm(a, b)
        sync()
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            torch.mm(a, b)
            sync()
            best = min(best, time.perf_counter() - t0)
        out[name] = round(2 * n**3 / best / 1e9, 1)
    return out


def agreement(ref: tuple[np.ndarray, np.ndarray], got: tuple[np.ndarray, np.ndarray]) -> dict:
    """Worst-image cosine similarity and relative L2 error per stage."""
    out = {}
    for stage, a, b in zip(("stage1", "stage2"), ref, got):
        a2, b2 = a.reshape(len(a), -1).astype(np.float64), b.reshape(len(b), -1).astype(np.float64)
        cos = (a2 * b2).sum(1) / (np.linalg.norm(a2, axis=1) * np.linalg.norm(b2, axis=1))
        rel = np.linalg.norm(a2 - b2, axis=1) / np.linalg.norm(a2, axis=1)
        out[stage] = {"cosine_min": round(float(cos.min()), 6), "rel_l2_max": round(float(rel.max()), 5)}
    return out


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precisions", default="fp32,bf16,int8", help="comma list of fp32, bf16, int8, auto")
    ap.add_argument("--batch-sizes", default="1,8")
    ap.add_argument(
        "--repeats", type=int, default=None, help="timed passes per precision and batch (default 7, quick 2)"
    )
    ap.add_argument("--weights", default=None, help="VGG16 weights file, or 'random' (default: resolve, then shared)")
    ap.add_argument("--images", default=str(DEFAULT_IMAGES), help="image folder timed on")
    ap.add_argument("--calibration", default=None, help="int8 calibration folder (default: --images)")
    ap.add_argument("--calibration-images", type=int, default=32)
    ap.add_argument("--input-size", type=int, default=224)
    ap.add_argument(
        "--device", choices=("cpu", "cuda"), default="cpu", help="cuda: torch precisions on the GPU (int8 is CPU-only)"
    )
    ap.add_argument("--threads", type=int, default=None, help="torch / ONNX Runtime threads (default: all cores)")
    ap.add_argument(
        "--peak-gflops",
        default=None,
        help="ISA peak of all cores, e.g. fp32=530,bf16=1060,int8=2110 (default: measure with tools/peak_flops.c)",
    )
    ap.add_argument("--no-gemm", action="store_true", help="skip the torch GEMM peak")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--output", default=None, help="also write the JSON to this file")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    import torch

    repeats = args.repeats or (2 if args.quick else 7)
    precisions = [p for p in args.precisions.split(",") if p]
    batch_sizes = [int(b) for b in args.batch_sizes.split(",") if b]
    peak, peak_source = dict(DEFAULT_PEAK_GFLOPS), "stored: tools/peak_flops.c on this project's machine"
    if args.peak_gflops:
        peak.update({k: float(v) for k, v in (item.split("=") for item in args.peak_gflops.split(","))})
        peak_source = "--peak-gflops"
    elif args.device == "cuda":  # the CPU's ISA peak says nothing of a GPU: achieved rates only
        peak, peak_source = {}, "none on cuda (see gflops_achieved)"
    elif not args.quick and (measured := isa_peak()) is not None:
        peak, peak_source = measured["total"], f"tools/peak_flops.c measured now: {measured['per_core']}"
    if args.threads:
        torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    result: dict = {"tool": "bench_backbone", "machine": machine_info(args.device)}
    result["machine"]["cpu_has_fast_bf16"] = cpu_has_fast_bf16()
    result["settings"] = {"precisions": precisions, "batch_sizes": batch_sizes, "repeats": repeats,
                          "input_size": args.input_size, "threads": args.threads}  # fmt: skip

    state, weights_info = pick_weights(args.weights, allow_download=False)
    images_list, images_info = load_images(Path(args.images), max(max(batch_sizes), 8), args.input_size)
    images = np.stack(images_list)
    result["weights"], result["images"] = weights_info, images_info
    base = BackboneConfig(weights="random" if state is None else "x", device=args.device, input_size=args.input_size,
                          num_threads=args.threads, int8_calibration=args.calibration or args.images,
                          int8_calibration_images=args.calibration_images)  # fmt: skip

    backbones: dict[str, Backbone] = {}
    sections: dict[str, dict] = {}
    for precision in ["fp32", *[p for p in precisions if p != "fp32"]]:
        t0 = time.perf_counter()
        try:
            backbones[precision] = Backbone(base.model_copy(update={"precision": precision}), state)
        except LoopClosureInputError as exc:  # int8 without its extra
            sections[precision] = {"skipped": str(exc)}
            log(f"{precision}: skipped ({exc})")
            continue
        sections[precision] = {
            "resolved": backbones[precision].precision,
            "build_s": round(time.perf_counter() - t0, 2),
        }
        log(f"{precision}: built in {sections[precision]['build_s']} s")
    del state

    if "fp32" not in backbones:  # the reference itself cannot run (a GPU that is not there)
        raise LoopClosureInputError(f"the fp32 reference cannot run: {sections['fp32']['skipped']}")
    ref = backbones["fp32"](images[:8])
    for precision, backbone in backbones.items():
        sections[precision]["agreement_with_fp32"] = agreement(ref, backbone(images[:8]))
        for bs in batch_sizes:  # warm-up of every batch shape
            backbone(images[:bs])
    gflop = conv_gflop(backbones["fp32"], args.input_size)
    timed = [p for p in precisions if p in backbones]

    samples: dict[tuple[str, int], list[float]] = {(p, bs): [] for p in timed for bs in batch_sizes}
    cpu: dict[tuple[str, int], list[float]] = {key: [] for key in samples}  # process CPU ms, all threads
    load_mid = None
    for r in range(repeats):
        if r == repeats // 2:
            load_mid = loadavg()
        for bs in batch_sizes:
            batch = images[(r * bs) % len(images) :][:bs]
            if len(batch) < bs:
                batch = images[:bs]
            for precision in timed:
                t0, c0 = time.perf_counter(), time.process_time()
                backbones[precision](batch)
                samples[precision, bs].append((time.perf_counter() - t0) * 1e3)
                cpu[precision, bs].append((time.process_time() - c0) * 1e3)
        log(f"repeat {r + 1}/{repeats}")

    for precision in timed:
        section = sections[precision]
        resolved = backbones[precision].precision
        kind = resolved if resolved in ("int8", "bf16") else "fp32"
        for bs in batch_sizes:
            s = stats(samples[precision, bs])
            per_image = s["median"] / bs
            section[f"batch_{bs}"] = {
                "ms_per_image": round(per_image, 2),
                "ms_per_batch": s,
                # core-ms an image costs: what it leaves the other stages of a SLAM run on these cores
                "cpu_ms_per_image": round(float(np.median(cpu[precision, bs])) / bs, 2),
                "gflops_achieved": round(gflop / (per_image / 1e3), 1),
            }
            if kind in peak:
                section[f"batch_{bs}"]["fraction_of_isa_peak"] = round(gflop / (per_image / 1e3) / peak[kind], 3)
        if kind in peak:
            section["physical_limit_ms_per_image"] = round(gflop / peak[kind] * 1e3, 1)
    result["gflop_per_image"] = round(gflop, 2)
    result["isa_peak_gflops"] = {**peak, "source": peak_source}
    result["precisions"] = sections
    if not args.no_gemm:
        result["gemm_peak_gflops_torch"] = gemm_peak(3 if args.quick else 5, args.device)
    result["targets_ms_per_image"] = {"bf16": 80.0, "int8": 45.0}  # the CPU's (issue 10)
    result["pass"] = (
        {}
        if args.device != "cpu"
        else {
            p: bool(min(sections[p][f"batch_{bs}"]["ms_per_image"] for bs in batch_sizes) <= target)
            for p, target in result["targets_ms_per_image"].items()
            if p in timed
        }
    )
    result["machine"]["loadavg_mid"] = load_mid
    result["machine"]["loadavg_end"] = loadavg()
    return emit(result, t_start, args.output)


if __name__ == "__main__":
    try:
        main()
    except LoopClosureInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
