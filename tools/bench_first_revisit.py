"""Loops from the first revisit: the detector's start-up rules on real and simulated streams,
short and long, through `loop-eval`'s stream and scoring. Prints ONE JSON object (progress on
stderr).

Usage:
  python tools/bench_first_revisit.py --weights PATH [--shared ../shared] [--sets short,full,sim]
                                      [--variants default,blind,...] [--sim-dir DIR]

Sets (--sets picks groups or single names):
  short  Gardens Point half cut to 30 + 30 frames (day_right then night_right) from frames 0, 20,
         40, 60 and 70, and Nordland-64 half cut to 50 + 50 (summer then winter) from frames 0,
         50, ..., 300: gp30@0 ... nl50@300. The first of each kind is the issue's cut; the others
         are other short streams of the same kinds.
  full   the whole shared halves and Corridor (ref then query).
  sim    simulated logs judged by their ground truth (loop-eval LOG): the quick start's traverse,
         a small-block traverse whose first revisit comes after about 45 keyframes, and a
         first lap of the quick city with no revisit at all (look-alike streets only). The logs
         are simulated into --sim-dir once.

Variants (--variants):
  default     the shipped rule (docs/loop_decisions.md).
  blind       the start-up before it: 40 keyframes of PCA warm-up, 40 runner-ups before the first
              decision, no prior, sequences zero-filled where a line is cut short.
  low         blind with the two settings lowered by hand (warm-up 15, 10 runner-ups).
  no_prior    the shipped rule without the prior: the stream's own runner-ups from 5 on.
  zero_fill   the shipped rule with lines cut short filled with zeros (missing: zero).
  iqr         the shipped rule with the interquartile range as the runner-ups' spread.
  linear      the shipped rule with the prior fading linearly, gone after prior_runner_ups.

Per set and variant: accepted, precision and recall at the decision, the maximum recall at full
precision, keyframes judged, the first revisit and the first right loop accepted (stream frames).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_loop_decisions import MemoBackbone  # noqa: E402  (tools/ is the script's folder)

SHORT = {f"gp30@{s}": ("gardens_point_half", "day_right", "night_right", s, 30) for s in (0, 20, 40, 60, 70)}
SHORT |= {f"nl50@{s}": ("nordland64_half", "summer", "winter", s, 50) for s in range(0, 301, 50)}
FULL = {
    "gp_half": ("gardens_point_half", "day_right", "night_right", 0, None),
    "nordland_half": ("nordland64_half", "summer", "winter", 0, None),
    "corridor": ("corridor", "ref", "query", 0, None),
}
SIMS = {
    "sim_quick": {},
    "sim_small_block": {"frame_rate_hz": 1.6, "max_frames": 60, "city": {"block_size_m": 20.0}},
    "sim_no_revisit": {"max_frames": 90},  # the first lap of the quick city stops before its start
}
VARIANTS = ("default", "blind", "low", "no_prior", "zero_fill", "iqr", "linear")


def log(msg: str) -> None:
    print(f"[bench_first_revisit] {msg}", file=sys.stderr, flush=True)


def variant_config(base: Any, variant: str) -> Any:
    """The SlamConfig of a config-level variant (the code-level ones patch the model instead)."""
    cfg = base.model_copy(deep=True)
    det = cfg.detector
    if variant in ("blind", "low"):
        det.pca_warmup_keyframes = 40 if variant == "blind" else 15
        det.sequence = det.sequence.model_copy(update={"missing": "zero"})
        det.calibrated = det.calibrated.model_copy(
            update={"min_history": 40 if variant == "blind" else 10, "prior_runner_ups": 0, "min_field": 1}
        )
    elif variant == "no_prior":
        det.calibrated = det.calibrated.model_copy(update={"prior_runner_ups": 0})
    elif variant == "zero_fill":
        det.sequence = det.sequence.model_copy(update={"missing": "zero"})
    return cfg


@contextmanager
def model_patched(variant: str) -> Iterator[None]:
    """The code-level variants: the runner-ups' spread, the prior's fade."""
    from loopclosure import calibration

    saved_own, saved_weight = calibration.RunnerUpModel._own, calibration.RunnerUpModel._prior_weight

    def iqr_own(self: Any) -> tuple[float, float] | None:
        if len(self._recent) < self.config.min_history:
            return None
        values = np.fromiter(self._recent, np.float64, len(self._recent))
        q1, median, q3 = np.percentile(values, [25.0, 50.0, 75.0])
        return float(median), max(float(q3 - q1), 1e-7)

    def linear_weight(self: Any) -> float:
        if not self._fields or self.config.prior_runner_ups == 0:
            return 0.0
        return max(0.0, 1.0 - len(self._recent) / self.config.prior_runner_ups)

    try:
        if variant == "iqr":
            calibration.RunnerUpModel._own = iqr_own  # type: ignore[method-assign]
        if variant == "linear":
            calibration.RunnerUpModel._prior_weight = linear_weight  # type: ignore[method-assign]
        yield
    finally:
        calibration.RunnerUpModel._own = saved_own  # type: ignore[method-assign]
        calibration.RunnerUpModel._prior_weight = saved_weight  # type: ignore[method-assign]


def cut_folders(shared: Path, spec: tuple[str, str, str, int, int | None], work: Path, name: str) -> tuple[Path, Path]:
    """The two passes of a set, cut to `count` frames from `start` (linked into `work`)."""
    root, first, second, start, count = spec
    if count is None:
        return shared / "data" / root / first, shared / "data" / root / second
    out = []
    for sub in (first, second):
        folder = work / name.replace("@", "_") / sub
        folder.mkdir(parents=True, exist_ok=True)
        for path in sorted((shared / "data" / root / sub).iterdir())[start : start + count]:
            if not (folder / path.name).exists():
                (folder / path.name).symlink_to(path.resolve())
        out.append(folder)
    return out[0], out[1]


def simulated_log(name: str, sim_dir: Path) -> Path:
    from rich.console import Console

    from ssmvpr_slam.app.runner import simulate_to_mcap
    from ssmvpr_slam.config.slam import load_config

    path = sim_dir / f"{name}.mcap"
    if not path.exists():
        overrides = {"simulation": {**SIMS[name], "lidar": {"enabled": False}}}
        simulate_to_mcap(load_config("quick", overrides), path, Console(stderr=True))
    return path


def summary(outcome: Any, truth: Any, metrics: dict[str, Any]) -> dict[str, Any]:
    from ssmvpr_slam.loop_eval import score

    judged = score.judge(outcome.proposals, truth)
    revisits = np.flatnonzero(judged.has_truth)
    right = np.flatnonzero(judged.accepted & judged.correct)
    loops = metrics["loops"]
    return {
        "accepted": loops["accepted"],
        "precision": loops["precision"],
        "recall": loops["recall"],
        "max_recall_at_full_precision": loops["max_recall_at_full_precision"],
        "keyframes_judged": metrics["keyframes_judged"],
        "first_revisit": int(revisits[0]) if len(revisits) else None,
        "first_right_accepted": int(right[0]) if len(right) else None,
        "too_short_to_decide": metrics["too_short_to_decide"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", required=True)
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--sets", default="short,full,sim")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--sim-dir", type=Path, default=Path("/tmp/bench_first_revisit"))
    args = ap.parse_args(argv)

    from loopclosure.backbone import load_backbone
    from ssmvpr_slam.config.slam import load_config
    from ssmvpr_slam.loop_eval.runner import LoopEvalInputs, compute_metrics, prepare
    from ssmvpr_slam.loop_eval.stream import stream

    groups = {"short": SHORT, "full": FULL, "sim": SIMS}
    names: list[str] = []
    for item in args.sets.split(","):
        names += list(groups[item]) if item in groups else [item]
    for name in names:
        if not any(name in g for g in groups.values()):
            ap.error(f"unknown set {name!r}")
    variants = args.variants.split(",")
    for v in variants:
        if v not in VARIANTS:
            ap.error(f"unknown variant {v!r}; one of {', '.join(VARIANTS)}")
    args.sim_dir.mkdir(parents=True, exist_ok=True)
    base = load_config()
    base.vpr.backbone.weights = args.weights
    real_backbone = load_backbone(base.vpr.backbone)
    result: dict[str, Any] = {"variants": variants, "sets": {}}
    for name in names:
        backbone = MemoBackbone(real_backbone)
        if name in SIMS:
            inputs = LoopEvalInputs((simulated_log(name, args.sim_dir),))
        else:
            spec = SHORT.get(name) or FULL[name]
            inputs = LoopEvalInputs(cut_folders(args.shared, spec, args.sim_dir / "cuts", name))
        prepared = prepare(inputs, base)
        per_set: dict[str, Any] = {"frames": list(prepared.lengths)}
        for variant in variants:
            cfg = variant_config(base, variant)
            start = time.perf_counter()
            with model_patched(variant):
                outcome = stream(cfg, backbone, [read() for read in prepared.passes], prepared.positions)  # type: ignore[arg-type]
            metrics = compute_metrics(outcome, prepared.truth, cfg, len(prepared.lengths))
            per_set[variant] = summary(outcome, prepared.truth, metrics)
            entry = per_set[variant]
            log(f"{name} {variant}: {time.perf_counter() - start:.0f} s, accepted {entry['accepted']} "
                f"P {entry['precision']} R {entry['recall']} first {entry['first_right_accepted']}")  # fmt: skip
        result["sets"][name] = per_set
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
