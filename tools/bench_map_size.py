"""Per-keyframe recognition time as the map grows: the detector a run builds, recognising real
keyframes against a place database of 1k, 10k and 100k places. Prints ONE JSON object (progress
on stderr).

Usage:
  python tools/bench_map_size.py --log LOG [--sizes 1000,10000,100000] [--keyframes 40]
                                 [--config PRESET_OR_YAML] [--weights PATH] [--device auto]

The keyframes are the log's first `--keyframes` camera frames (every `--stride`-th). The map is
the codes of the log's own first places (encoded once), replicated to each size with a little
noise on every copy (no two places alike), given to the detector as a prior map: so every query
searches all of them (stage I as configured: exact up to `vpr.filtering.ann_threshold_places`,
IVF beyond), scores its candidates (stage II), matches sequences and decides, as in a run whose
map has grown that far. Reported per size: the keyframe's detector time (median, p90, mean) and
by stage, the database's build time, and `growth`: the median at the largest size over the
median at the smallest.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def log(msg: str) -> None:
    print(f"[bench_map_size] {msg}", file=sys.stderr, flush=True)


def _images(log_path: Path, config: Any, count: int, stride: int) -> list[np.ndarray]:
    from frontend.sources import open_source

    images = []
    for k, frame in enumerate(open_source(log_path, config.frontend.source, config.frontend.pose_files)):
        if frame.image is not None and k % stride == 0:
            images.append(frame.image)
        if len(images) == count:
            break
    return images


def _map(encoder: Any, base: Any, size: int, config: Any, rng: np.random.Generator) -> Any:
    """`size` places: the base codes tiled, each copy with noise at 5 % of the codes' spread."""
    from loopclosure.database import PlaceDatabase, PlaceInfo
    from loopclosure.encoder import PlaceCodes

    database = PlaceDatabase(encoder.codebooks, config.vpr.database)
    spread1, spread2 = float(base.stage1.std()), float(base.stage2.std())
    n = len(base)
    for start in range(0, size, n):
        take = min(n, size - start)
        stage1 = base.stage1[:take] + rng.normal(0, 0.05 * spread1, base.stage1[:take].shape).astype(np.float32)
        stage2 = base.stage2[:take] + rng.normal(0, 0.05 * spread2, base.stage2[:take].shape).astype(np.float32)
        infos = [PlaceInfo(frame_id=start + i) for i in range(take)]
        database.add(PlaceCodes(stage1, stage2), infos)
    return database


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", type=Path, required=True)
    ap.add_argument("--sizes", default="1000,10000,100000")
    ap.add_argument("--keyframes", type=int, default=40, help="keyframes timed against each map")
    ap.add_argument("--stride", type=int, default=2, help="every this many frames of the log is a keyframe")
    ap.add_argument("--base-places", type=int, default=200, help="places of the log encoded for the map")
    ap.add_argument("--config", default=None)
    ap.add_argument("--weights", default=None)
    ap.add_argument("--device", default=None)
    args = ap.parse_args(argv)

    from loopclosure.backbone import load_backbone
    from loopclosure.detector import LoopDetector
    from loopclosure.encoder import Encoder
    from ssmvpr_slam.config.slam import load_config

    config = load_config(args.config)
    if args.weights:
        config.vpr.backbone.weights = args.weights
    if args.device:
        config.vpr.backbone.device = args.device
    sizes = [int(s) for s in args.sizes.split(",")]
    backbone = load_backbone(config.vpr.backbone)
    encoder = Encoder(config.vpr, backbone)
    start = time.perf_counter()
    base_images = _images(args.log, config, args.base_places, 1)
    prepared = [encoder.prepare(image) for image in base_images]
    encoder.codebooks, base = encoder.fit_and_encode(prepared)
    log(f"{len(base)} base places encoded in {time.perf_counter() - start:.0f} s")
    queries = _images(args.log, config, args.keyframes, args.stride)
    rng = np.random.default_rng(0)
    result: dict[str, Any] = {"log": str(args.log), "keyframes": len(queries), "sizes": {}}
    for size in sizes:
        start = time.perf_counter()
        database = _map(encoder, base, size, config, rng)
        build = time.perf_counter() - start
        detector = LoopDetector(config.vpr, config.detector, Encoder(config.vpr, backbone, encoder.codebooks), database)
        rows = []
        for k, image in enumerate(queries):
            start = time.perf_counter()
            detector.process(image, k)
            total = time.perf_counter() - start
            t = detector.timings
            rows.append({"total": total, "backbone": t.backbone, "stage1": t.database_query,
                         "stage2": t.spatial_matching, "sequence": t.sequence_matching, "decision": t.gate})  # fmt: skip
        steady = rows[2:]  # the first queries build the index and warm the caches
        per = {key: {"median_ms": 1000 * float(np.median([r[key] for r in steady])),
                     "p90_ms": 1000 * float(np.percentile([r[key] for r in steady], 90)),
                     "mean_ms": 1000 * float(np.mean([r[key] for r in steady]))} for key in rows[0]}  # fmt: skip
        index = database.search_index()
        result["sizes"][str(size)] = {"per_keyframe": per, "build_s": build, "first_query_ms": 1000 * rows[0]["total"],
                                      "stage1_index": index.kind, "bytes_per_place": database.bytes_per_place}  # fmt: skip
        log(f"{size} places: {per['total']['median_ms']:.0f} ms a keyframe (stage I {per['stage1']['median_ms']:.1f} "
            f"ms, {index.kind}), built in {build:.0f} s")  # fmt: skip
        del detector, database
    first, last = (result["sizes"][str(s)]["per_keyframe"]["total"]["median_ms"] for s in (sizes[0], sizes[-1]))
    result["growth"] = last / first
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
