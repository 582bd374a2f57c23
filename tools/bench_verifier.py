"""Two-view verification on deep features (loopclosure/pair_verifier.py) on real pairs across
light and season. Prints ONE JSON object (progress on stderr).

Usage:
  python tools/bench_verifier.py --weights PATH [--shared ../shared] [--sets gp,nordland]
                                 [--set NAME=FOLDER:REF:QUERY ...] [--queries N] [--every K] [--width W]
                                 [--min-image-width PX]

For every query frame of a set: its true pair (the reference frame of the same index) and its
wrong pairs (every stage-I candidate of the default recogniser at least 5 frames from the truth,
as issue #44 defines them). Reported per set: the share of true pairs verified, the share of
wrong pairs verified (all, and those 8 or more frames from the truth, which share no view), the
inlier ratios of both, what a sweep of `min_inlier_ratio` would give, and the time per pair
(features of both images, then the geometry) on this machine.

Sets: gp = Gardens Point half, night_right queries against day_right; nordland = Nordland-64
half, winter against summer (64x32 pixels, upscaled to the verifier's width). --set adds a
folder of the same layout (held-out data): NAME=FOLDER:REF_SUBDIR:QUERY_SUBDIR.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from loopclosure.backbone_input import list_images, read_image  # noqa: E402
from loopclosure.config import VerifierConfig  # noqa: E402
from loopclosure.pair_verifier import PairVerifier  # noqa: E402
from loopclosure.place_recognizer import PlaceRecognizer  # noqa: E402

SETS = {"gp": ("gardens_point_half", "day_right", "night_right"), "nordland": ("nordland64_half", "summer", "winter")}
MIN_WRONG_OFFSET = 5
NO_SHARED_VIEW = 8
SWEEP = (0.3, 0.35, 0.4, 0.41, 0.45, 0.5)


def log(msg: str) -> None:
    print(f"[bench_verifier] {msg}", file=sys.stderr, flush=True)


def share(flags: list[bool]) -> float | None:
    return round(float(np.mean(flags)), 4) if flags else None


def run_set(
    name: str, ref_dir: Path, query_dir: Path, weights: str, config: VerifierConfig, limit: int | None, every: int
) -> dict:
    refs, queries = list_images(ref_dir), list_images(query_dir)
    if limit is not None:
        refs, queries = refs[:limit], queries[:limit]
    n = min(len(refs), len(queries))
    recognizer = PlaceRecognizer.from_config(weights=weights, device="cpu")
    recognizer.add_references([read_image(p) for p in refs])
    verifier = PairVerifier(recognizer.encoder.backbone, config)
    features: dict[Path, object] = {}
    feature_s: list[float] = []

    def feats(path: Path) -> object:
        if path not in features:
            start = time.perf_counter()
            features[path] = verifier.features(read_image(path), str(path))
            feature_s.append(time.perf_counter() - start)
        return features[path]

    rows = []
    verify_s: list[float] = []
    for q in range(0, n, every):
        candidates = [int(c) for c in recognizer.query(read_image(queries[q])).candidates.places]
        pairs = [(q, True)] + [(c, False) for c in candidates if abs(c - q) >= MIN_WRONG_OFFSET]
        for r, true in pairs:
            fq, fr = feats(queries[q]), feats(refs[r])
            start = time.perf_counter()
            verdict = verifier.verify(fq, fr)  # type: ignore[arg-type]
            verify_s.append(time.perf_counter() - start)
            rows.append(
                (true, abs(r - q), verdict.accepted, verdict.inlier_ratio, verdict.n_inliers, verdict.verifiable)
            )
        if q % 20 == 0:
            log(f"{name}: query {q}/{n}")
    true_rows = [r for r in rows if r[0]]
    wrong_rows = [r for r in rows if not r[0]]
    sweep = {}
    for ratio in SWEEP:
        ok = [r[4] >= config.min_inliers and r[3] >= ratio for r in rows]
        sweep[str(ratio)] = {
            "true_verified": share([o for o, r in zip(ok, rows) if r[0]]),
            "wrong_verified": share([o for o, r in zip(ok, rows) if not r[0]]),
        }
    return {
        "queries": len(range(0, n, every)),
        "true_pairs": len(true_rows),
        "wrong_pairs": len(wrong_rows),
        "true_verified": share([r[2] for r in true_rows]),
        "wrong_verified": share([r[2] for r in wrong_rows]),
        "unverifiable": share([not r[5] for r in rows]),  # images too small to judge (VerifierConfig.min_image_width)
        "wrong_verified_no_shared_view": share([r[2] for r in wrong_rows if r[1] >= NO_SHARED_VIEW]),
        "wrong_verified_offsets": sorted({r[1] for r in wrong_rows if r[2]}),
        "inlier_ratio_true_p10_p50": [round(float(np.quantile([r[3] for r in true_rows], p)), 3) for p in (0.1, 0.5)],
        "inlier_ratio_wrong_p50_p99": [
            round(float(np.quantile([r[3] for r in wrong_rows], p)), 3) for p in (0.5, 0.99)
        ],
        "sweep_min_inlier_ratio": sweep,
        "features_ms_per_image_median": round(1000 * float(np.median(feature_s)), 1),
        "verify_ms_per_pair_median": round(1000 * float(np.median(verify_s)), 1),
        "ms_per_loop_median": round(1000 * (2 * float(np.median(feature_s)) + float(np.median(verify_s))), 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", required=True)
    parser.add_argument("--shared", default=str(ROOT.parent / "shared"))
    parser.add_argument("--sets", default="gp,nordland")
    parser.add_argument("--set", action="append", default=[], help="NAME=FOLDER:REF:QUERY (held-out data)")
    parser.add_argument("--queries", type=int, default=None, help="the first N frames of each set only")
    parser.add_argument("--every", type=int, default=1, help="every K-th query frame only (all references)")
    parser.add_argument("--width", type=int, default=None, help="override VerifierConfig.width")
    parser.add_argument("--min-image-width", type=int, default=None, help="override VerifierConfig.min_image_width")
    args = parser.parse_args()
    overrides = {"width": args.width, "min_image_width": args.min_image_width}
    config = VerifierConfig(**{k: v for k, v in overrides.items() if v is not None})
    jobs = {}
    for name in [s for s in args.sets.split(",") if s]:
        folder, ref, query = SETS[name]
        jobs[name] = (Path(args.shared) / "data" / folder / ref, Path(args.shared) / "data" / folder / query)
    for spec in args.set:
        name, _, rest = spec.partition("=")
        folder, ref, query = rest.split(":")
        jobs[name] = (Path(folder) / ref, Path(folder) / query)
    out: dict[str, object] = {"config": config.model_dump()}
    for name, (ref_dir, query_dir) in jobs.items():
        log(f"{name}: {query_dir} against {ref_dir}")
        out[name] = run_set(name, ref_dir, query_dir, args.weights, config, args.queries, args.every)
        log(f"{name}: {json.dumps(out[name])}")  # each set's figures as soon as it is done
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
