"""Single frames vs sequence matching on a simulated camera stream (the demo's, or another).

Prints ONE JSON object to stdout (progress goes to stderr).

With the simulator's rear camera (on by default), the rear images are queried against the
forward camera's places as the detector does: their own sequences, an accept-score sweep,
and the detector's decision over both cameras (forward first, then rear).

Usage:
  python tools/bench_sequence_sim.py [--weights PATH] [--lengths 1,2,3,5] [--direction both]
                                     [--save-codes FILE | --codes FILE]
                                     [--sim-config SIM_YAML] [--frames N]
                                     [--route POSES_FILE [--poses-frame F]]

The demo traverse (`ssmvpr-slam demo --odometry logged`: drifting wheel odometry picks the
keyframes, camera only), or the one --sim-config / --route / --frames describe as in the other
simulator benches (e.g. another city: a YAML with `seed: 1` and the demo's `appearance_schedule:
[day, day, dusk]`), runs once through `SlamPipeline`; the detector's place database then holds
every keyframe's codes. From them, each keyframe after the PCA warm-up is queried again offline
exactly as the detector queries it (stage I over the places before it minus the exclusion
window, stage II, sequence matching with `match_sequences`, which equals the streaming matcher),
for each L. Scored like `metrics.json`'s stream PR-AUC: one best match per keyframe, correct
within `evaluation.loops.correct_radius` of a ground-truth revisit. Also reported: the same with
the reverse revisits left out (a forward camera sees the other side of the street there), the
recall at precision 1 of forward and reverse revisits apart, and the loops the detector's
calibrated decision accepts (`calibrated_decision`: the detector's default, `decide_stream`, with
the configured directions, the rear camera's reverse), the loops the absolute decision accepts at
the configured thresholds (`absolute_decision`: `accept_score`, `min_single_score`) and at others
(`absolute_accept_score_sweep`), beside the decision before sequence matching (single frame >= 0.5
and the top-1 gate, L = 3, ±2).
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _sim_options import add_simulation_options, simulation_config  # noqa: E402

if TYPE_CHECKING:
    from frontend.simulation import SimulationConfig


def log(msg: str) -> None:
    print(f"[bench_sequence_sim] {msg}", file=sys.stderr, flush=True)


def run_traverse(weights: str | None, simulation: SimulationConfig) -> dict[str, np.ndarray]:
    """The traverse (`simulation`, camera only) through the pipeline; the keyframes' codes and bookkeeping."""
    import sklearn.decomposition  # noqa: F401  (its BLAS must be loaded to be limited)
    from threadpoolctl import threadpool_limits

    from frontend.odometry import make_odometry
    from frontend.simulation.simulator import TraverseSimulator
    from loopclosure.backbone import load_backbone
    from ssmvpr_slam.app.pipeline import SlamPipeline
    from ssmvpr_slam.config.slam import load_config

    cfg = load_config()
    if weights:
        cfg.vpr.backbone.weights = weights
    cfg.simulation = simulation
    cfg.frontend.odometry.kind = "logged"
    cfg.pipeline.use_lidar_for_loops = False
    t0 = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        pipeline = SlamPipeline.build(cfg, make_odometry(cfg.frontend.odometry, cfg.frontend.pose_files),
                                load_backbone(cfg.vpr.backbone))  # fmt: skip
        pipeline.run(TraverseSimulator(cfg.simulation).frames())
    det = pipeline.detector
    log(f"{len(pipeline.state.keyframes)} keyframes in {time.perf_counter() - t0:.0f} s")
    out = {
        "stage1": np.asarray(det.database.stage1), "stage2": np.asarray(det.database.stage2),
        "travelled": np.asarray(det._session_travelled), "gt": np.array([k.gt_pose for k in pipeline.state.keyframes]),
        "warmup": np.array(cfg.detector.pca_warmup_keyframes),
    }  # fmt: skip
    if cfg.simulation.camera.rear:  # the rear images are queries only: encode them again, as the detector did
        simulator = TraverseSimulator(cfg.simulation)
        rear = [det.encoder.project(det.encoder.raw_cubes([det.encoder.prepare(simulator.render_image(k.frame_index, rear=True))]))
                for k in pipeline.state.keyframes]  # fmt: skip
        out["rear_stage1"] = np.concatenate([c.stage1 for c in rear])
        out["rear_stage2"] = np.concatenate([c.stage2 for c in rear])
        log(f"rear images encoded ({time.perf_counter() - t0:.0f} s)")
    return out


def queries(codes: dict[str, np.ndarray], exclusion_keyframes: int, exclusion_distance: float, n_cand: int,
            camera: str = ""):  # fmt: skip
    """Per keyframe after the warm-up, as LoopDetector sees it: the limit (first excluded
    place), the stage-I candidates and the stage-II scores against every earlier place.
    camera "rear_": the rear images' codes queried against the forward camera's places."""
    from threadpoolctl import threadpool_limits

    from loopclosure.filtering import vote
    from loopclosure.spatial import spatial_scores

    s1, s2, travelled, first = codes["stage1"], codes["stage2"], list(codes["travelled"]), int(codes["warmup"])
    n = len(s1)
    scores = np.zeros((n - first, n), np.float32)
    limits = np.zeros(n - first, np.int64)
    cands = []
    with threadpool_limits(limits=1, user_api="blas"):
        for i, q in enumerate(range(first, n)):
            first_recent = q - min(exclusion_keyframes, q)
            first_near = bisect.bisect_right(travelled[:q], travelled[q] - exclusion_distance)
            limits[i] = min(first_recent, first_near)
            scores[i, :q] = spatial_scores(codes[camera + "stage2"][q], s2[:q]).scores
            cands.append(vote(codes[camera + "stage1"][q], s1[:q], n_cand, n_cand, np.arange(limits[i], q)).places)
    return scores, limits, cands


def revisit_kinds(pos: np.ndarray, radius: float, gap: int) -> dict[int, str]:
    from ssmvpr_slam.evaluation.loop_metrics import find_revisits

    def heading(i: int) -> np.ndarray:
        v = pos[min(i + 1, len(pos) - 1)] - pos[max(i - 1, 0)]
        return v / max(float(np.linalg.norm(v)), 1e-9)

    out = {}
    for q in find_revisits(pos, radius, gap).tolist():
        m = int(np.argmin(np.linalg.norm(pos[: q - gap + 1] - pos[q], axis=1)))
        out[q] = "forward" if float(heading(q) @ heading(m)) > 0 else "reverse"
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=None, help="VGG16 weights (default: resolve, as the demo does)")
    ap.add_argument("--lengths", default="1,2,3,5", help="sequence lengths L")
    ap.add_argument("--direction", default="both", choices=("forward", "reverse", "both"))
    ap.add_argument("--save-codes", default=None, help="keep the traverse's codes in this .npz")
    ap.add_argument("--codes", default=None, help="use codes saved by --save-codes instead of simulating")
    add_simulation_options(ap)
    args = ap.parse_args(argv)
    if args.codes and (args.sim_config or args.route or args.frames is not None):
        ap.error("--codes replays saved codes: --sim-config, --route and --frames would be ignored")

    from loopclosure.metrics import pr_auc, precision_recall_curve
    from loopclosure.sequence_matcher import match_sequences
    from ssmvpr_slam.config.slam import load_config

    cfg = load_config()
    det, loops = cfg.detector, cfg.evaluation.loops
    codes = (
        dict(np.load(args.codes))
        if args.codes
        else run_traverse(args.weights, simulation_config(ap, args, lidar={"enabled": False}))
    )
    if args.save_codes:
        np.savez(args.save_codes, **codes)
    first = int(codes["warmup"])
    pos = codes["gt"][:, :3, 3]
    kinds = revisit_kinds(pos, loops.revisit_radius, loops.min_frame_gap)
    if not any(q >= first for q in kinds):  # recall and PR-AUC would be undefined
        ap.error(
            f"the traverse ({len(pos)} keyframes) has no ground-truth revisit after the {first}-keyframe "
            "warm-up: nothing to evaluate (a longer traverse, or one with loops, has)"
        )
    scores, limits, cands = queries(
        codes, det.exclusion_keyframes, det.exclusion_distance, cfg.vpr.filtering.num_candidates
    )
    qs = np.arange(first, len(pos))

    def calibrated(s: np.ndarray, c: list, lim: np.ndarray, direction: str, length: int) -> dict[int, int]:
        """{query: place} the calibrated decision accepts (`decide_stream`: the detector's rule,
        without the links of accepted loops between places)."""
        from loopclosure.calibration import decide_stream

        seq = det.sequence.model_copy(update={"length": length, "direction": direction})
        return {int(q): m.place for q, (m, v) in zip(qs, decide_stream(s, c, lim, seq, det.calibrated))
                if v is not None and v.accepted}  # fmt: skip

    def accepted(matches: list, threshold: float, min_single: float) -> dict[int, int]:
        """{query: place} of the sequence matches the detector's decision accepts at these thresholds."""
        return {int(q): m.place for q, m in zip(qs, matches)
                if m.place is not None and m.score >= threshold and m.single_score >= min_single}  # fmt: skip

    def decided(loops_by_query: dict[int, int]) -> dict:
        """Precision and recall (all / forward / reverse revisits) of accepted {query: place} loops."""
        ok = {q: float(np.linalg.norm(pos[q] - pos[p])) <= loops.correct_radius for q, p in loops_by_query.items()}
        hit = {q for q, o in ok.items() if o and q in kinds}
        out = {"accepted": len(ok), "precision": float(np.mean(list(ok.values()))) if ok else None,
               "recall": len(hit) / len(kinds) if kinds else None}  # fmt: skip
        for k in ("forward", "reverse"):
            n = sum(v == k for v in kinds.values())
            out[f"recall_{k}"] = sum(kinds[q] == k for q in hit) / n if n else None
        return out

    def evaluate(places: np.ndarray, values: np.ndarray) -> dict:
        ok = np.array([p >= 0 and np.linalg.norm(pos[q] - pos[p]) <= loops.correct_radius for q, p in zip(qs, places)])
        truth = np.array([q in kinds for q in qs])
        forward = np.array([kinds.get(q) != "reverse" for q in qs])
        wrong = (places >= 0) & ~ok
        top_wrong = float(values[wrong].max()) if wrong.any() else None
        accepted = (values > top_wrong) if top_wrong is not None else (places >= 0)
        recall = {k: float(np.mean([accepted[i] and ok[i] for i, q in enumerate(qs) if kinds.get(q) == k]))
                  for k in ("forward", "reverse") if any(v == k for v in kinds.values())}  # fmt: skip
        return {
            "stream_pr_auc": pr_auc(precision_recall_curve(values, ok & truth, truth)),
            "stream_pr_auc_forward_revisits": pr_auc(
                precision_recall_curve(values[forward], (ok & truth)[forward], truth[forward])
            ),
            "top_wrong_score": top_wrong,
            "recall_at_precision_1": recall,
        }

    out: dict = {
        "tool": "bench_sequence_sim", "keyframes": len(pos), "queries": len(qs),
        "revisits": {k: sum(v == k for v in kinds.values()) for k in ("forward", "reverse")},
        "direction": args.direction, "results": {},
    }  # fmt: skip
    rear = None
    if "rear_stage1" in codes and det.rear.enabled:
        rear = queries(
            codes, det.exclusion_keyframes, det.exclusion_distance, cfg.vpr.filtering.num_candidates, "rear_"
        )
        out["rear_thresholds"] = det.rear.model_dump()
    for length in [int(v) for v in args.lengths.split(",") if v.strip()]:
        seq_cfg = det.sequence.model_copy(update={"length": length, "direction": args.direction})
        matches = match_sequences(scores, seq_cfg, cands, limits)
        places = np.array([-1 if m.place is None else m.place for m in matches])
        values = np.array([-np.inf if m.place is None else m.score for m in matches])
        result = out["results"][str(length)] = evaluate(places, values)
        front = accepted(matches, det.accept_threshold, det.min_single_score)
        result["absolute_decision"] = decided(front)
        calibrated_front = calibrated(scores, cands, limits, det.sequence.direction, length)
        result["calibrated_decision"] = decided(calibrated_front)
        result["absolute_accept_score_sweep"] = {
            f"{threshold:g}": decided(accepted(matches, threshold, det.min_single_score))
            for threshold in sorted({0.40, 0.45, 0.50, 0.55, 0.60, det.accept_threshold})
        }
        if rear is not None:  # the rear images' own sequences, and the detector's choice of the two
            rear_matches = match_sequences(rear[0], seq_cfg, rear[2], rear[1])
            r_places = np.array([-1 if m.place is None else m.place for m in rear_matches])
            r_values = np.array([-np.inf if m.place is None else m.score for m in rear_matches])
            result["rear"] = evaluate(r_places, r_values)
            result["rear"]["absolute_accept_score_sweep"] = {
                f"{threshold:g}": decided(accepted(rear_matches, threshold, det.rear.min_single_score))
                for threshold in (0.24, 0.25, 0.26, 0.27, 0.28, 0.30, 0.32)
            }
            # forward first: the rear camera's loop only where the forward camera accepted none
            both = {**accepted(rear_matches, det.rear.accept_score, det.rear.min_single_score), **front}
            result["absolute_decision_front_and_rear"] = decided(both)
            rear_calibrated = calibrated(rear[0], rear[2], rear[1], det.rear.direction, length)
            result["calibrated_decision_front_and_rear"] = decided({**rear_calibrated, **calibrated_front})
        log(f"L={length}: {result}")
    # single frames as the recogniser alone ranks them (stage II over the stage-I candidates)
    single = np.array([c[np.argmax(scores[i, c])] if len(c) else -1 for i, c in enumerate(cands)])
    single_scores = np.array([scores[i, p] if p >= 0 else -np.inf for i, p in enumerate(single)])
    out["single_frame"] = evaluate(single, single_scores)
    from loopclosure.config import SequenceGateConfig
    from loopclosure.sequence_gate import SequenceGate

    gate, before = SequenceGate(SequenceGateConfig(length=3, tolerance=2, allow_reverse=True)), []
    for q, p, v in zip(qs.tolist(), single.tolist(), single_scores.tolist()):
        if v < 0.5:
            gate.observe(q, None)
            continue
        if gate.decide(q, p).accepted:
            before.append((q, p))
        gate.observe(q, p)
    out["single_frame"]["detector_decision_before"] = decided(dict(before))
    out["thresholds"] = {"accept_score": det.accept_threshold, "min_single_score": det.min_single_score}
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
