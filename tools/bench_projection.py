"""A keyframe's images to codes, the maps cut and projected on the host (numpy) against on the
backbone's device (torch, `vpr.backbone.projection`): time and agreement.

Prints ONE JSON object to stdout (progress goes to stderr).

Usage:
  python tools/bench_projection.py [--device auto|cpu|cuda] [--precision fp32|auto] [--batch 2]
                                   [--repeats 20] [--weights PATH|random] [--images DIR] [--quick]

What is measured, per batch of `--batch` prepared images (2: a keyframe's front and rear):
  backbone_ms     `Backbone.maps` alone, the device synchronised (the maps left where they are).
  numpy_ms        `Encoder.codes(batch)` with projection numpy: the pass, the maps to the host,
                  cubes and PCA there (the reference).
  torch_ms        `Encoder.codes(batch)` with projection torch: the pass, cubes and PCA on the
                  device, the codes to the host.
  agreement       the largest difference between the two paths' codes, over each stage's
                  largest code magnitude, on every image timed.
PCA is fitted on the host from `--fit-images` images first, as a stream fits it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

TOOLS = Path(__file__).resolve().parent
sys.path.insert(0, str(TOOLS))

from bench_vpr import DEFAULT_IMAGES, emit, load_images, log, machine_info, pick_weights, stats  # noqa: E402

from loopclosure.backbone import Backbone  # noqa: E402
from loopclosure.config import BackboneConfig, VPRConfig  # noqa: E402
from loopclosure.encoder import Encoder  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--precision", default="fp32", choices=["fp32", "auto"])
    ap.add_argument("--batch", type=int, default=2, help="images per pass (2: a keyframe's front and rear)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--fit-images", type=int, default=16)
    ap.add_argument("--weights", default=None, help="VGG16 weights file, or 'random' (default: resolve, then shared)")
    ap.add_argument("--images", default=str(DEFAULT_IMAGES), help="image folder (synthetic images without one)")
    ap.add_argument("--input-size", type=int, default=224)
    ap.add_argument("--pca-dim", type=int, default=100, help="both stages' code dimensions (the paper's 100)")
    ap.add_argument("--quick", action="store_true", help="3 repeats, 8 fitting images, 112 px input, 4 dimensions")
    ap.add_argument("--output", default=None, help="also write the JSON to this file")
    args = ap.parse_args(argv)
    if args.quick:
        args.repeats, args.fit_images, args.input_size, args.pca_dim = 3, 8, 112, 4
    if args.batch < 1 or args.repeats < 1 or args.fit_images < 2:
        ap.error("--batch and --repeats must be 1 or more, --fit-images 2 or more")
    return args


def main(argv: list[str] | None = None) -> dict:
    import torch

    t_start = time.perf_counter()
    args = parse_args(argv)
    state_dict, weights_info = pick_weights(args.weights, allow_download=False)
    backbone_config = BackboneConfig(device=args.device, precision=args.precision, input_size=args.input_size,
                                     weights="random" if state_dict is None else None)  # fmt: skip
    backbone = Backbone(backbone_config, state_dict)
    need = args.fit_images + args.batch * args.repeats
    images, _ = load_images(Path(args.images), need, args.input_size)
    images = [images[i % len(images)] for i in range(need)]
    fit, timed = images[: args.fit_images], images[args.fit_images :]
    pca = {"pca": {"dim": args.pca_dim}}
    configs = {
        name: VPRConfig.model_validate({"backbone": backbone_config.model_copy(update={"projection": name}).model_dump(),
                                        "filtering": pca, "spatial": pca})
        for name in ("numpy", "torch")
    }  # fmt: skip
    encoders = {name: Encoder(config, backbone) for name, config in configs.items()}
    log(f"fitting PCA on {len(fit)} images ({backbone.precision} on {backbone.device})")
    codebooks = encoders["numpy"].fit_codebooks(fit)
    encoders["torch"].codebooks = codebooks

    synchronise = torch.cuda.synchronize if backbone.device.type == "cuda" else (lambda: None)

    def maps_only(batch: list[np.ndarray]) -> None:
        backbone.maps(np.stack(batch))
        synchronise()

    timings: dict[str, list[float]] = {"backbone_ms": [], "numpy_ms": [], "torch_ms": []}
    worst = {"stage1": 0.0, "stage2": 0.0}
    batches = [timed[i : i + args.batch] for i in range(0, len(timed), args.batch)]
    for step in ("warm-up", *range(len(batches))):
        batch = batches[0 if step == "warm-up" else step]
        runs = {
            "backbone_ms": lambda b=batch: maps_only(b),
            "numpy_ms": lambda b=batch: encoders["numpy"].codes(b),
            "torch_ms": lambda b=batch: encoders["torch"].codes(b),
        }
        got = {}
        for name, run in runs.items():
            synchronise()
            start = time.perf_counter()
            got[name] = run()
            seconds = time.perf_counter() - start
            if step != "warm-up":
                timings[name].append(seconds * 1000.0)
        for stage in worst:
            reference, device_codes = getattr(got["numpy_ms"], stage), getattr(got["torch_ms"], stage)
            worst[stage] = max(worst[stage], float(np.abs(device_codes - reference).max() / np.abs(reference).max()))
    result = {
        "tool": "bench_projection",
        "machine": machine_info(str(backbone.device)),
        "weights": weights_info,
        "device": str(backbone.device),
        "precision": backbone.precision,
        "batch": args.batch,
        "input_size": args.input_size,
        "repeats": len(batches),
        **{name: stats(samples) for name, samples in timings.items()},
        "host_projection_ms": round(float(np.median(timings["numpy_ms"]) - np.median(timings["backbone_ms"])), 3),
        "device_projection_ms": round(float(np.median(timings["torch_ms"]) - np.median(timings["backbone_ms"])), 3),
        "speedup": round(float(np.median(timings["numpy_ms"]) / np.median(timings["torch_ms"])), 3),
        "agreement": {f"{stage}_max_relative_difference": float(f"{value:.3g}") for stage, value in worst.items()},
    }
    return emit(result, t_start, args.output)


if __name__ == "__main__":
    main()
