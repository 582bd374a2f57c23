"""`ssmvpr-slam loop-eval`: inputs checked, the stream run with a progress bar, results written."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from frontend.errors import FrontendInputError
from frontend.poses_io import read_poses
from frontend.sources import detect_kind
from loopclosure.backbone import load_backbone
from loopclosure.backbone_input import list_images
from loopclosure.pair_verifier import PairVerdict
from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_slam.config.slam import SlamConfig, dump_config
from ssmvpr_slam.loop_eval import revisit_truth as truth
from ssmvpr_slam.loop_eval import score
from ssmvpr_slam.loop_eval.log_frames import images_of_log, keyframes_of
from ssmvpr_slam.loop_eval.revisit_truth import LoopTruth, LoopTruthError
from ssmvpr_slam.loop_eval.stream import ImagePair, StreamOutcome, images_of, path_positions, stream, travelled
from ssmvpr_slam.loop_eval.verification import Verification, verify_accepted
from ssmvpr_slam.results.run_folder import staged_results_dir, write_json


@dataclass(frozen=True)
class LoopEvalInputs:
    """What the command line named: one or two image folders and one kind of ground truth."""

    sequences: tuple[Path, ...]
    ground_truth: Path | None = None  # two passes: a vpr-eval pairs file (default: frame-aligned)
    gt_poses: Path | None = None  # one sequence: TUM / KITTI poses, one per image
    gt_matrix: Path | None = None  # one sequence: a square 0/1 loop matrix
    tolerance: int = 2
    radius: float = 10.0
    spacing: float = 1.0
    rear: tuple[Path, ...] = ()  # a rear camera's folder per sequence, in the same order
    gt_threshold: float | None = None  # --gt-matrix values >= this are loops (a similarity matrix); None: 0/1 only


def _images(folder: Path, what: str) -> list[Path]:
    if not folder.is_dir():
        raise LoopTruthError(f"{folder}: no such {what} folder")
    return list_images(folder)  # an empty folder is an error naming it


@dataclass(frozen=True)
class Prepared:
    """What is streamed and how it is judged, checked before the backbone loads."""

    passes: tuple[Callable[[], Iterable[ImagePair]], ...]  # each call reads its pass afresh
    lengths: tuple[int, ...]
    names: tuple[str, ...]  # one per frame: a file name, or LOG#frame
    positions: np.ndarray  # (N, 3) metres, for the exclusion window
    truth: LoopTruth
    from_log: bool = False  # one log, judged by its own ground-truth poses


def is_log(path: Path) -> bool:
    """An MCAP, a ROS bag or a KITTI sequence (what `run` reads), not an image folder."""
    try:
        return detect_kind(path) != "folder"
    except FrontendInputError:
        return False


def prepare(inputs: LoopEvalInputs, config: SlamConfig) -> Prepared:
    """The passes, positions and ground truth, checked before the backbone loads: a wrong count or
    a missing file is one line, at once."""
    if not 1 <= len(inputs.sequences) <= 2:
        raise LoopTruthError(f"loop-eval takes one sequence or two passes, got {len(inputs.sequences)} folders")
    if inputs.tolerance < 0:
        raise LoopTruthError(f"--tolerance must be 0 or more frames, got {inputs.tolerance}")
    if not inputs.spacing > 0:
        raise LoopTruthError(f"--spacing must be positive metres per frame, got {inputs.spacing}")
    if inputs.gt_threshold is not None and inputs.gt_matrix is None:
        raise LoopTruthError("--gt-threshold reads a --gt-matrix of similarities; give the matrix, or leave it out")
    if len(inputs.sequences) == 1 and is_log(inputs.sequences[0]):
        return _prepare_log(inputs, config)
    for sequence in inputs.sequences:
        if is_log(sequence):
            raise LoopTruthError(f"{sequence}: a log is one sequence judged by its own ground truth; "
                                 "two passes are image folders")  # fmt: skip
    files = [_images(folder, "image") for folder in inputs.sequences]
    rear = None
    if inputs.rear:
        if len(inputs.rear) != len(files):
            raise LoopTruthError(f"--rear: one rear-camera folder per sequence ({len(files)}), got {len(inputs.rear)}")
        rear = [_images(folder, "rear camera") for folder in inputs.rear]
        for front, back, folder in zip(files, rear, inputs.rear):
            if len(front) != len(back):
                raise LoopTruthError(f"{folder}: {len(back)} rear images for {len(front)} forward images")
    passes = tuple(partial(images_of, f, None if rear is None else rear[k]) for k, f in enumerate(files))
    lengths = tuple(len(f) for f in files)
    names = tuple(path.name for f in files for path in f)
    positions, loop_truth = _folder_truth(inputs, config, files)
    return Prepared(passes, lengths, names, positions, loop_truth)


def _folder_truth(inputs: LoopEvalInputs, config: SlamConfig, files: list[list[Path]]) -> tuple[np.ndarray, LoopTruth]:
    n = sum(len(f) for f in files)
    det = config.detector
    if len(files) == 2:
        if inputs.gt_poses is not None or inputs.gt_matrix is not None:
            raise LoopTruthError("two passes are judged frame by frame (or by --gt); --gt-poses and --gt-matrix "
                                 "are for one sequence")  # fmt: skip
        loop_truth, _ = truth.two_passes(files[0], files[1], inputs.ground_truth, inputs.tolerance)
        return path_positions(n, inputs.spacing), loop_truth
    if inputs.ground_truth is not None:
        raise LoopTruthError("--gt pairs a second pass with the first; one sequence needs --gt-poses or --gt-matrix")
    if (inputs.gt_poses is None) == (inputs.gt_matrix is None):
        raise LoopTruthError("one sequence needs its ground truth: --gt-poses POSES or --gt-matrix FILE (one of them)")
    if inputs.gt_poses is not None:
        poses = read_poses(inputs.gt_poses).poses
        if len(poses) != n:
            raise LoopTruthError(f"{inputs.gt_poses}: {len(poses)} poses for {n} images")
        positions = poses[:, :3, 3]
        return positions, _truth_from_positions(positions, inputs, config)
    assert inputs.gt_matrix is not None
    positions = path_positions(n, inputs.spacing)
    loop_truth = truth.from_matrix(inputs.gt_matrix, n, inputs.tolerance, travelled(positions),
                                   det.exclusion_keyframes, det.exclusion_distance, inputs.gt_threshold)  # fmt: skip
    return positions, loop_truth


def _truth_from_positions(positions: np.ndarray, inputs: LoopEvalInputs, config: SlamConfig) -> LoopTruth:
    det = config.detector
    return truth.from_poses(positions, inputs.radius, travelled(positions), det.exclusion_keyframes,
                            det.exclusion_distance)  # fmt: skip


def _prepare_log(inputs: LoopEvalInputs, config: SlamConfig) -> Prepared:
    """One log (MCAP, bag, KITTI): a keyframe every `frontend.keyframes` step of its own ground
    truth, a revisit an earlier keyframe within --radius (`log_frames`)."""
    log = inputs.sequences[0]
    given = [name for name, value in (("--gt", inputs.ground_truth), ("--gt-poses", inputs.gt_poses),
                                      ("--gt-matrix", inputs.gt_matrix)) if value is not None]  # fmt: skip
    if given or inputs.rear:
        raise LoopTruthError(f"{log}: a log is judged by its own ground-truth poses and streams its own rear "
                             f"camera; {', '.join(given + (['--rear'] if inputs.rear else []))} is for image folders")  # fmt: skip
    keyframes = keyframes_of(log, config)
    positions = keyframes.poses[:, :3, 3]
    passes = (partial(images_of_log, keyframes, config),)
    return Prepared(passes, (len(positions),), tuple(keyframes.names()), positions,
                    _truth_from_positions(positions, inputs, config), from_log=True)  # fmt: skip


def compute_metrics(
    outcome: StreamOutcome,
    loop_truth: LoopTruth,
    config: SlamConfig,
    n_passes: int,
    verification: Verification | None = None,
) -> dict[str, Any]:
    judged = score.judge(outcome.proposals, loop_truth)
    det = config.detector
    metrics: dict[str, Any] = {
        "decision": det.decision,
        "accept": det.calibrated.accept if det.decision == "calibrated" else det.accept_threshold,
        "loops": score.loop_metrics(judged, n_passes),
        # a stream too short to decide anything has recall 0 that says nothing about the detector
        "keyframes_judged": outcome.keyframes_judged,
        "too_short_to_decide": outcome.too_short_to_decide,
    }
    if n_passes > 1:
        metrics["loops_across_passes"] = score.loop_metrics(score.only_across(judged), passes=1)  # none within
    metrics["timing"] = {
        "s_per_frame_median": float(np.median(outcome.seconds)) if len(outcome.seconds) else None,
        "s_per_frame_mean": float(np.mean(outcome.seconds)) if len(outcome.seconds) else None,
    }
    if verification is not None:
        metrics["verify"] = _verify_metrics(judged, verification, n_passes)
    return metrics


def _verify_metrics(judged: score.Judged, verification: Verification, n_passes: int) -> dict[str, Any]:
    """The loops again with only those a run would let in accepted (verified by the views, too
    small to judge, or refused but vouched for by earlier verified loops), the views' verdicts
    alone beside them, and what was refused."""
    n = len(judged.match)
    verified = verification.verified(n)
    unjudged = verification.unverifiable(n)  # too small to tell: kept as decided
    agreed = verification.kept_by_agreement(n)
    stands = verification.standing(n)
    kept = replace(judged, accepted=judged.accepted & stands)
    views_alone = replace(judged, accepted=judged.accepted & (verified | unjudged))
    refused = judged.accepted & ~stands
    seconds = verification.seconds
    out: dict[str, Any] = {
        "checked": len(verification.verdicts),
        "verified": int((judged.accepted & verified).sum()),
        "unverifiable": int((judged.accepted & unjudged).sum()),
        "kept_by_agreement": int((judged.accepted & agreed).sum()),
        "kept_by_agreement_wrong": int((judged.accepted & agreed & ~judged.correct).sum()),
        "refused_right_loops": int((refused & judged.correct).sum()),
        "refused_wrong_loops": int((refused & ~judged.correct).sum()),
        "loops": _at_the_decision(score.loop_metrics(kept, n_passes)),
        "views_alone": _at_the_decision(score.loop_metrics(views_alone, n_passes)),
        "ms_per_loop_median": 1000.0 * float(np.median(seconds)) if seconds else None,
    }
    if n_passes > 1:
        out["loops_across_passes"] = _at_the_decision(score.loop_metrics(score.only_across(kept), passes=1))
    return out


def _at_the_decision(loops: dict[str, Any]) -> dict[str, Any]:
    """Only accepted loops are verified: the curve over every winner's score is not the
    verified detector's, so its figures are left out (null) rather than repeated."""
    return loops | {"max_recall_at_full_precision": None, "pr_auc": None}


LOOP_COLUMNS = ["frame", "pass", "image", "match_frame", "match_image", "decision_score", "sequence_score",
                "single_score", "runner_up", "direction", "camera", "accepted", "correct", "true_frame", "reason",
                "verified", "verification", "kept"]  # fmt: skip


def write_loops_csv(
    path: Path,
    outcome: StreamOutcome,
    loop_truth: LoopTruth,
    names: Sequence[str],
    verification: Verification | None = None,
) -> None:
    """One row per frame that had a winner; under --verify, for the accepted loops, `verified`
    (the views' verdict: 1/0), their words, and `kept` (1: the loop stands: verified, too small
    to judge, or vouched for by earlier verified loops); empty otherwise."""
    verdicts = verification.verdicts if verification is not None else {}
    agreed = verification.agreed if verification is not None else {}
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(LOOP_COLUMNS)
    for q, p in enumerate(outcome.proposals):
        if p is None:
            continue
        true = loop_truth.matches[q]
        writer.writerow([
            q, int(loop_truth.passes[q]), names[q], p.match_id, names[p.match_id],
            f"{score.decision_score(p):.4f}", "" if p.sequence_score is None else f"{p.sequence_score:.4f}",
            f"{p.score:.4f}", "" if p.runner_up_score is None else f"{p.runner_up_score:.4f}", p.direction or "",
            p.camera, int(p.accepted), int(bool(loop_truth.has_truth[q]) and loop_truth.correct(q, p.match_id)),
            "" if not len(true) else int(true[np.argmin(np.abs(true - p.match_id))]), p.reason,
            _verified_cell(verdicts.get(q)), _verification_words(verdicts.get(q), agreed.get(q)),
            "" if verification is None or q not in verdicts else int(verification.stands(q)),
        ])  # fmt: skip
    atomic_write_text(path, buffer.getvalue())


def _verified_cell(verdict: PairVerdict | None) -> int | str:
    """1 or 0; empty for a loop not checked, `unverifiable` where its images were too small."""
    if verdict is None:
        return ""
    return int(verdict.accepted) if verdict.verifiable else "unverifiable"


def _verification_words(verdict: PairVerdict | None, agreeing: int | None) -> str:
    if verdict is None:
        return ""
    if agreeing is None:
        return verdict.reason
    return f"{verdict.reason}; kept: {agreeing} earlier verified loops of the revisit agree along the path"


def write_pr_plot(path: Path, outcome: StreamOutcome, loop_truth: LoopTruth, n_passes: int, title: str) -> None:
    from matplotlib.figure import Figure

    from ssmvpr_slam.evaluation.plots import save_figure

    judged = score.judge(outcome.proposals, loop_truth)
    views = {"all decisions": judged}
    if n_passes > 1:
        views["across passes only"] = score.only_across(judged)
    fig = Figure(figsize=(6.0, 5.0))
    ax = fig.add_subplot()
    for label, view in views.items():
        pr = score.curve(view)
        if pr is None:
            continue
        ax.plot(pr.recall, pr.precision, linewidth=2, label=f"{label} (AUC {score.pr_auc(pr):.3f})")
        accepted = int(view.accepted.sum())
        if accepted:
            right = int((view.accepted & view.correct).sum())
            ax.plot([right / int(view.has_truth.sum())], [right / accepted], "o", markersize=8,
                    label=f"{label}: the detector's decision")  # fmt: skip
    ax.set(xlim=(0.0, 1.02), ylim=(0.0, 1.02), xlabel="Recall", ylabel="Precision", title=title)
    ax.grid(True, linestyle=":")
    ax.legend(loc="lower left", fontsize=8)
    save_figure(fig, path)


def summary_table(metrics: dict[str, Any]) -> Table:
    table = Table(title="loop-eval", show_header=True)
    table.add_column("judged on")
    for name in ("accepted", "precision", "recall", "max recall @ P=1", "PR-AUC"):
        table.add_column(name, justify="right")
    views = [("all decisions", metrics["loops"])]
    if "loops_across_passes" in metrics:
        views.append(("across passes only", metrics["loops_across_passes"]))
    if "verify" in metrics:
        views.append(("verified by two views alone", metrics["verify"]["views_alone"]))
        views.append(("verified, or earlier verified loops agree", metrics["verify"]["loops"]))
        if "loops_across_passes" in metrics["verify"]:
            views.append(("verified, across passes", metrics["verify"]["loops_across_passes"]))

    def num(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f}"

    for label, m in views:
        table.add_row(label, str(m["accepted"]), num(m["precision"]), num(m["recall"]),
                      num(m["max_recall_at_full_precision"]), num(m["pr_auc"]))  # fmt: skip
    return table


def run_loop_eval(
    inputs: LoopEvalInputs, config: SlamConfig, console: Console | None = None, verify: bool = False
) -> tuple[Path, dict[str, Any]]:
    """Stream, judge, write metrics.json, loops.csv, pr.png and config.yaml; returns (folder, metrics).
    verify: check every accepted loop by two views too (`loop_eval.verification`)."""
    console = console or Console()
    prepared = prepare(inputs, config)
    loop_truth = prepared.truth
    if not loop_truth.has_truth.any():
        console.print("[bold yellow]warning:[/bold yellow] no frame has a true revisit under this ground truth: "
                      "recall and the PR curve are undefined", highlight=False)  # fmt: skip
    backbone = load_backbone(config.vpr.backbone, progress=True)
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TimeRemainingColumn(), console=console, transient=False) as progress:  # fmt: skip
        task = progress.add_task("streaming", total=sum(prepared.lengths))
        passes = [read() for read in prepared.passes]
        outcome = stream(config, backbone, passes, prepared.positions, lambda: progress.advance(task))
        verification = None
        if verify:
            n_accepted = sum(1 for p in outcome.proposals if p is not None and p.accepted)
            checking = progress.add_task("verifying", total=n_accepted)
            verification = verify_accepted(outcome, prepared.passes, prepared.positions, config, backbone,
                                           lambda: progress.advance(checking))  # fmt: skip
    metrics = compute_metrics(outcome, loop_truth, config, len(passes), verification)
    from_log = prepared.from_log
    by_poses = from_log or inputs.gt_poses is not None
    metrics["inputs"] = {
        "sequences": [str(s) for s in inputs.sequences],
        "frames": list(prepared.lengths),
        "ground_truth": "the log's ground-truth poses"
        if from_log
        else str(inputs.gt_poses or inputs.gt_matrix or inputs.ground_truth or "frame-aligned"),
        "gt_threshold": inputs.gt_threshold,
        "tolerance": inputs.tolerance,
        "radius_m": inputs.radius if by_poses else None,
        "spacing_m": inputs.spacing if not by_poses else None,
        "rear": [str(r) for r in inputs.rear],
    }
    with staged_results_dir(config.results.out_dir, "loop_eval") as staged:
        folder = staged.path
        write_json(folder / "metrics.json", metrics)
        write_loops_csv(folder / "loops.csv", outcome, loop_truth, prepared.names, verification)
        atomic_write_text(folder / "config.yaml", dump_config(config))
        if config.results.plots and loop_truth.has_truth.any():
            name = " then ".join(s.name for s in inputs.sequences)
            write_pr_plot(folder / "pr.png", outcome, loop_truth, len(passes), f"Loop closures: {name}")
    assert staged.final is not None
    console.print(summary_table(metrics))
    if outcome.too_short_to_decide is not None:
        console.print(f"[bold yellow]warning:[/bold yellow] too short to decide any loop: "
                      f"{escape(outcome.too_short_to_decide)}; recall 0 here says nothing about the detector",
                      highlight=False)  # fmt: skip
    console.print(f"results in [bold]{escape(str(staged.final))}[/bold]")
    return staged.final, metrics
