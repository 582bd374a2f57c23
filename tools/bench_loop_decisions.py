"""Loop decisions on real two-pass sequences: the calibrated decision against the absolute one,
its accept level swept, and PCA fitted three ways, each through `loop-eval`'s stream and scoring.

Prints ONE JSON object to stdout (progress goes to stderr).

Usage:
  python tools/bench_loop_decisions.py --weights PATH [--shared ../shared] [--sets corridor,gp_half,nordland]
                                       [--accepts 4,5,6,7,8] [--pca warmup,references] [--pca-codebooks FILE]

Sets (../shared/data): corridor (ref then query), gp_half (Gardens Point day_right then
night_right), nordland (Nordland-64 summer then winter), gp_mini (10 + 10: too short for the
PCA warm-up, refused). For each set and PCA variant the pass pair streams through the detector a
run builds (default preset) twice: with `detector.decision: calibrated` (recording every
winner, so one stream gives every accept level) and with `absolute` (the simulator-tuned rule
it replaced, with its former sequence setting: L = 3, both directions, K = 10), and once more for
every other calibrated accept level (--accepts). Each backbone pass is remembered, so the variants
of a set cost one pass per image.

PCA variants: warmup (the default: fitted on the stream's first 40 keyframes), references (on
the whole first pass, as `fit-pca FIRST` would), codebooks (a `fit-pca` .npz, e.g. fitted on
rendered simulator frames: --pca-codebooks).

Per set: loops (every decision judged) and loops_across_passes (only decisions matching into the
other pass; Corridor revisits places within a pass that its ground truth does not list).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SETS = {
    "corridor": ("corridor/ref", "corridor/query"),
    "gp_half": ("gardens_point_half/day_right", "gardens_point_half/night_right"),
    "nordland": ("nordland64_half/summer", "nordland64_half/winter"),
    "gp_mini": ("gardens_point_mini/query", "gardens_point_mini/ref"),
}


def log(msg: str) -> None:
    print(f"[bench_loop_decisions] {msg}", file=sys.stderr, flush=True)


class MemoBackbone:
    """The real backbone, remembering each image's maps across the variants."""

    calibrates_on_stream = False

    def __init__(self, backbone: Any) -> None:
        self.backbone = backbone
        self.config = backbone.config
        self.device = torch.device("cpu")  # the remembered maps are numpy: codes by numpy wherever the net ran
        self._memo: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def stream_calibration(self) -> None:
        return None

    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = hashlib.sha1(np.ascontiguousarray(images).tobytes()).digest()
        if key not in self._memo:
            self._memo[key] = self.backbone(images)
        return self._memo[key]


def _brief(m: dict[str, Any]) -> dict[str, Any]:
    return {k: m[k] for k in ("accepted", "precision", "recall", "false_accepts")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", required=True)
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--sets", default="corridor,gp_half,nordland")
    ap.add_argument("--accepts", default="4,5,6,7,8")
    ap.add_argument("--pca", default="warmup,references", help="warmup, references, codebooks (comma separated)")
    ap.add_argument("--pca-codebooks", type=Path, default=None, help="a fit-pca .npz for the codebooks variant")
    args = ap.parse_args(argv)

    from loopclosure.backbone import load_backbone
    from loopclosure.backbone_input import list_images, read_image
    from loopclosure.encoder import Encoder
    from ssmvpr_slam.config.slam import load_config
    from ssmvpr_slam.loop_eval.runner import LoopEvalInputs, compute_metrics, prepare
    from ssmvpr_slam.loop_eval.stream import stream

    accepts = [float(a) for a in args.accepts.split(",")]
    variants = args.pca.split(",")
    if "codebooks" in variants and args.pca_codebooks is None:
        ap.error("--pca codebooks needs --pca-codebooks FILE")
    base = load_config()
    base.vpr.backbone.weights = args.weights
    backbone = MemoBackbone(load_backbone(base.vpr.backbone))
    result: dict[str, Any] = {"accepts": accepts, "sets": {}}
    for name in args.sets.split(","):
        if name not in SETS:
            ap.error(f"unknown set {name!r}; one of {', '.join(SETS)}")
        first, second = (args.shared / "data" / p for p in SETS[name])
        inputs = LoopEvalInputs((first, second))
        prepared = prepare(inputs, base)
        loop_truth = prepared.truth
        per_set: dict[str, Any] = {"frames": list(prepared.lengths)}
        for variant in variants:
            cfg = base.model_copy(deep=True)
            if variant == "references":
                path = Path(f"/tmp/bench_loop_decisions_{name}_codebooks.npz")
                encoder = Encoder(cfg.vpr, backbone)  # type: ignore[arg-type]
                encoder.fit_codebooks(encoder.prepare(read_image(p), str(p)) for p in list_images(first)).save(path)
                cfg.detector.codebooks = str(path)
            elif variant == "codebooks":
                cfg.detector.codebooks = str(args.pca_codebooks)
            default_accept = cfg.detector.calibrated.accept
            runs = [("calibrated", default_accept), ("absolute", None)]
            runs += [("calibrated", a) for a in accepts if a != default_accept]
            for decision, accept in runs:
                run = cfg.model_copy(deep=True)
                run.detector.decision = decision  # type: ignore[assignment]
                if decision == "absolute":  # the rule as it shipped: L = 3 both ways, K = 10
                    run.detector.sequence = run.detector.sequence.model_copy(
                        update={"length": 3, "direction": "both", "sequence_candidates": 10}
                    )
                else:
                    run.detector.calibrated = run.detector.calibrated.model_copy(update={"accept": accept})
                start = time.perf_counter()
                outcome = stream(run, backbone, [read() for read in prepared.passes], prepared.positions)  # type: ignore[arg-type]
                metrics = compute_metrics(outcome, loop_truth, run, 2)
                entry = {"loops": metrics["loops"], "loops_across_passes": metrics["loops_across_passes"]}
                if accept == default_accept or accept is None:
                    per_set[f"{variant}/{decision}"] = entry
                else:
                    per_set.setdefault(f"{variant}/calibrated_accept_sweep", {})[f"{accept:g}"] = {
                        view: _brief(entry[view]) for view in ("loops", "loops_across_passes")
                    }
                log(f"{name} {variant}/{decision} {accept}: {time.perf_counter() - start:.0f} s, "
                    f"P {metrics['loops']['precision']} R {metrics['loops']['recall']}")  # fmt: skip
        result["sets"][name] = per_set
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
