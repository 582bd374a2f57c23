"""`vpr-eval`: SSM-VPR on a reference/query benchmark, measured the way the paper does."""

from __future__ import annotations

import csv
import io
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from loopclosure.backbone import load_backbone
from loopclosure.backbone_input import list_images, read_image
from loopclosure.benchmark_truth import GroundTruth, correct_mask, load_ground_truth, truth_windows
from loopclosure.blas import one_blas_thread
from loopclosure.config import SequenceMatchConfig
from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.device_search import check_search_device
from loopclosure.encoder import Encoder, PlaceCodes
from loopclosure.frame_correlation import FrameCorrelationPrior
from loopclosure.metrics import precision_recall_curve, recall_at_n, summarize
from loopclosure.pca import Codebooks
from loopclosure.sampling import evenly_spaced
from loopclosure.sequence_matcher import SequenceMatcher
from loopclosure.spatial import spatial_scores
from loopclosure.two_stage import TwoStageRanker
from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_slam.config.slam import SlamConfig, dump_config
from ssmvpr_slam.prior_map import encoder_signature
from ssmvpr_slam.results.run_folder import staged_results_dir, write_json


@dataclass
class SequenceOutcome:
    """Per-query results of sequence matching with one length L."""

    length: int
    direction: str  # as configured: forward | reverse | both
    match: np.ndarray  # (Q,) best place of the best sequence, -1 if none
    score: np.ndarray  # (Q,) its sequence score
    match_direction: list[str]  # (Q,) forward | reverse | ""
    terms: np.ndarray  # (Q,) terms of the winning sequence that existed
    seconds: np.ndarray  # (Q,) the matcher's own time (earlier queries' spatial scores, aggregation)
    spatial_scores: np.ndarray  # (Q,) spatial scores the matcher computed itself


@dataclass
class QueryOutcome:
    """Per-query arrays, index-aligned with the query folder."""

    stage1_match: np.ndarray  # (Q,) best place by votes, -1 if none
    stage1_score: np.ndarray  # (Q,) normalised votes
    stage2_match: np.ndarray  # (Q,) best place after spatial matching
    stage2_score: np.ndarray  # (Q,) final score in [0, 1]
    candidates: np.ndarray  # (Q, N) stage-I candidate lists, -1 padded
    query_seconds: np.ndarray  # (Q,) filtering + spatial matching
    sequences: dict[int, SequenceOutcome] = field(default_factory=dict)  # by L


def _progress(console: Console) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False,
    )  # fmt: skip


def _prepared(encoder: Encoder, files: Sequence[Path]) -> Iterator[np.ndarray]:
    for path in files:
        yield encoder.prepare(read_image(path), str(path), strict=True)


def encode_folder(
    encoder: Encoder, files: Sequence[Path], progress: Progress, label: str, fit: bool
) -> tuple[PlaceCodes, float]:
    """Codes of a folder (fitting the codebooks on it first when asked) and seconds per image."""
    task = progress.add_task(label, total=len(files))
    advance = lambda n: progress.advance(task, n)  # noqa: E731
    start = time.perf_counter()
    if fit and len(evenly_spaced(len(files), encoder.config.spatial.pca.max_fit_images)) == len(files):
        _, codes = encoder.fit_and_encode(_prepared(encoder, files), advance)
    else:
        if fit:
            subset = [files[i] for i in evenly_spaced(len(files), encoder.config.spatial.pca.max_fit_images)]
            fit_task = progress.add_task(f"{label}: fitting PCA", total=len(subset))
            encoder.fit_codebooks(_prepared(encoder, subset), lambda n: progress.advance(fit_task, n))
        codes = PlaceCodes.concatenate(list(encoder.encode_stream(_prepared(encoder, files), advance)))
    return codes, (time.perf_counter() - start) / len(files)


def recognise_all(
    recognizer: TwoStageRanker,
    queries: PlaceCodes,
    sequential: bool,
    progress: Progress,
    sequence_lengths: Sequence[int] = (),
    sequence_config: SequenceMatchConfig | None = None,
) -> QueryOutcome:
    """Every query in folder order; the queries form one stream (prior and sequences use it)."""
    n = len(queries)
    n_cand = recognizer.config.filtering.num_candidates
    out = QueryOutcome(
        np.full(n, -1, np.int64), np.zeros(n, np.float32), np.full(n, -1, np.int64),
        np.full(n, -np.inf, np.float32), np.full((n, n_cand), -1, np.int64), np.zeros(n),
    )  # fmt: skip
    prior_config = recognizer.config.frame_correlation.model_copy(update={"enabled": sequential})
    prior = FrameCorrelationPrior(prior_config)
    database = recognizer.database
    chunk = recognizer.config.spatial.chunk_candidates

    def score(grid: np.ndarray, places: np.ndarray) -> np.ndarray:
        return spatial_scores(grid, database.stage2[places], chunk).scores

    base = sequence_config or SequenceMatchConfig()
    matchers = {L: SequenceMatcher(base.model_copy(update={"length": L}), score) for L in sequence_lengths}
    for L, matcher in matchers.items():
        out.sequences[L] = SequenceOutcome(
            L, matcher.config.direction, np.full(n, -1, np.int64), np.full(n, -np.inf), [""] * n,
            np.zeros(n, np.int64), np.zeros(n), np.zeros(n, np.int64),
        )  # fmt: skip
    limit = len(database)
    task = progress.add_task("matching queries", total=n)
    for q in range(n):
        start = time.perf_counter()
        rec = recognizer.query(queries[q], boosted=prior.boosted())
        out.query_seconds[q] = time.perf_counter() - start
        prior.update(rec.best_place, rec.won_without_boost)
        cands = rec.candidates
        if len(cands):
            out.stage1_match[q] = cands.places[0]
            out.stage1_score[q] = cands.scores[0]
            out.candidates[q, : len(cands)] = cands.places[:n_cand]
        if rec.best_place is not None:
            out.stage2_match[q] = rec.best_place
            out.stage2_score[q] = rec.best_score
        spatial = dict(zip(rec.ranked_places.tolist(), rec.spatial_scores.tolist()))
        for L, matcher in matchers.items():
            start = time.perf_counter()
            continued = matcher.continuations(limit)
            new = [p for p in continued.tolist() if p not in spatial]
            if new:  # the continued places stage I did not propose
                spatial.update(zip(new, score(queries.stage2[q], np.asarray(new, np.int64)).tolist()))
            match = matcher.step(
                queries.stage2[q], cands.places, np.array([spatial[p] for p in cands.places.tolist()], np.float32),
                limit, continued, np.array([spatial[p] for p in continued.tolist()], np.float32),
            )  # fmt: skip
            seq = out.sequences[L]
            seq.seconds[q] = time.perf_counter() - start
            seq.spatial_scores[q] = matcher.scored_last_step + len(new)
            if match.place is not None:
                seq.match[q], seq.score[q] = match.place, match.score
                seq.match_direction[q], seq.terms[q] = match.direction or "", match.terms
        progress.advance(task)
    return out


def window_warning(gt: GroundTruth, tolerance: int) -> str | None:
    """One line when the tolerance widens a file's own windows (Corridor's ±2 plus ±2 counts ±4)."""
    windows = truth_windows(gt)
    if not windows.windowed or tolerance == 0:
        return None
    return (
        f"ground truth {gt.source} already lists a window of consecutive references per query "
        f"({windows.queries} of {windows.with_truth} queries, median {windows.median_refs:g} references); "
        f"tolerance {tolerance} widens each window by ±{tolerance} frames; --tolerance 0 uses the file as it is"
    )


def windows_record(gt: GroundTruth, tolerance: int) -> dict[str, Any] | None:
    """metrics.json's account of a windowed truth, so a reader sees what the tolerance was added to."""
    windows = truth_windows(gt)
    if not windows.windowed:
        return None
    return {
        "queries": windows.queries,
        "of": windows.with_truth,
        "median_refs": windows.median_refs,
        "widened_by": tolerance,
    }


def compute_metrics(outcome: QueryOutcome, gt: GroundTruth, config: SlamConfig) -> dict[str, Any]:
    tol = config.vpr_eval.tolerance
    n_cand = outcome.candidates.shape[1]
    ns = sorted({n for n in config.vpr_eval.recall_ns if n <= n_cand} | {n_cand})
    stage2 = summarize(outcome.stage2_score, outcome.stage2_match, gt, tol)
    stage1 = summarize(outcome.stage1_score, outcome.stage1_match, gt, tol, outcome.candidates, ns)
    metrics: dict[str, Any] = {
        "tolerance": tol,
        "ground_truth_windows": windows_record(gt, tol),  # null: one reference (or scattered ones) per query
        "n_query": gt.n_query,
        "n_ref": gt.n_ref,
        "pr_auc": stage2["pr_auc"],
        "precision_at_full_recall": stage2["precision_at_full_recall"],
        "recall_at_full_precision": stage2["recall_at_full_precision"],
        "top1_accuracy_stage1": stage1["top1_accuracy"],
        "top1_accuracy_stage2": stage2["top1_accuracy"],
        "filtering_recall_at_n": stage1["recall_at_n"],
        "stage1": stage1,
        "stage2": stage2,
    }
    if outcome.sequences:
        # single frames (stage II) and each sequence length side by side, same truth and tolerance
        metrics["single_frame"] = {"pr_auc": stage2["pr_auc"], "top1_accuracy": stage2["top1_accuracy"]}
        single_auc = float(stage2["pr_auc"])  # type: ignore[arg-type]
        metrics["sequence"] = {
            str(L): _sequence_metrics(seq, gt, tol, single_auc) for L, seq in outcome.sequences.items()
        }
    return metrics


def _sequence_metrics(seq: SequenceOutcome, gt: GroundTruth, tol: int, single_auc: float) -> dict[str, Any]:
    summary = summarize(seq.score, seq.match, gt, tol)
    return {
        "length": seq.length,
        "direction": seq.direction,
        "pr_auc": summary["pr_auc"],
        "pr_auc_minus_single_frame": float(summary["pr_auc"]) - single_auc,  # type: ignore[arg-type]
        "top1_accuracy": summary["top1_accuracy"],
        "precision_at_full_recall": summary["precision_at_full_recall"],
        "recall_at_full_precision": summary["recall_at_full_precision"],
        "reverse_matches": sum(d == "reverse" for d in seq.match_direction),
        "matcher_ms_median": 1000 * float(np.median(seq.seconds)),
        "matcher_spatial_scores_median": float(np.median(seq.spatial_scores)),
    }


def write_matches_csv(
    path: Path, outcome: QueryOutcome, gt: GroundTruth, tol: int, ref_files: Sequence[Path], query_files: Sequence[Path]
) -> None:
    correct = correct_mask(gt, outcome.stage2_match, tol)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    sequences = list(outcome.sequences.values())
    seq_correct = {seq.length: correct_mask(gt, seq.match, tol) for seq in sequences}
    writer.writerow(["query_index", "query_file", "ref_index", "ref_file", "score", "correct",
                     "stage1_ref_index", "stage1_score", "true_ref_indices", "query_ms"]
                    + [f"seq{seq.length}_{c}" for seq in sequences
                       for c in ("ref_index", "score", "correct", "direction", "terms", "ms")])  # fmt: skip
    for q, query_file in enumerate(query_files):
        m = int(outcome.stage2_match[q])
        writer.writerow([
            q, query_file.name, m, ref_files[m].name if m >= 0 else "", f"{outcome.stage2_score[q]:.6f}",
            int(correct[q]), int(outcome.stage1_match[q]), f"{outcome.stage1_score[q]:.6f}",
            " ".join(map(str, gt.refs[q])), f"{1000 * outcome.query_seconds[q]:.3f}",
        ] + [v for seq in sequences for v in (
            int(seq.match[q]), f"{seq.score[q]:.6f}", int(seq_correct[seq.length][q]), seq.match_direction[q],
            int(seq.terms[q]), f"{1000 * seq.seconds[q]:.3f}",
        )])  # fmt: skip
    atomic_write_text(path, buffer.getvalue())


def write_plots(
    folder: Path, outcome: QueryOutcome, gt: GroundTruth, metrics: dict[str, Any], config: SlamConfig
) -> None:
    from ssmvpr_slam.vpr.plots import plot_pr_curves, plot_recall_at_n

    def curve(scores: np.ndarray, matches: np.ndarray, tol: int):  # noqa: ANN202
        return precision_recall_curve(scores, correct_mask(gt, matches, tol), gt.has_truth)

    tol = config.vpr_eval.tolerance
    by_tol = {
        f"±{t} frames": curve(outcome.stage2_score, outcome.stage2_match, t) for t in config.vpr_eval.plot_tolerances
    }
    plot_pr_curves(by_tol, folder / "pr_tolerances.png", "SSM-VPR precision-recall by frame tolerance")
    by_stage = {
        "stage I (filtering)": curve(outcome.stage1_score, outcome.stage1_match, tol),
        "stage II (spatial matching)": curve(outcome.stage2_score, outcome.stage2_match, tol),
    }
    for L, seq in outcome.sequences.items():
        by_stage[f"sequence L={L} ({seq.direction})"] = curve(seq.score, seq.match, tol)
    title = "Stage I vs stage II" + (" vs sequences" if outcome.sequences else "")
    plot_pr_curves(by_stage, folder / "pr_stages.png", f"{title} (±{tol} frames)")
    if outcome.sequences:
        single_vs_sequence = {"single frame (stage II)": by_stage["stage II (spatial matching)"]}
        single_vs_sequence.update({k: v for k, v in by_stage.items() if k.startswith("sequence")})
        plot_pr_curves(single_vs_sequence, folder / "pr_sequence.png", f"Single frames vs sequences (±{tol} frames)")
    n_cand = outcome.candidates.shape[1]
    recall = recall_at_n(outcome.candidates, gt, tol, list(range(1, n_cand + 1)))
    plot_recall_at_n({"filtering stage": recall}, folder / "recall_at_n.png", f"Filtering recall@N (±{tol} frames)")


def summary_table(metrics: dict[str, Any]) -> Table:
    table = Table(title="SSM-VPR recognition", show_header=True)
    table.add_column("metric")
    table.add_column("value", justify="right")
    rows = [
        ("PR-AUC (stage II)", metrics["pr_auc"]),
        ("recall @ 100% precision", metrics["recall_at_full_precision"]),
        ("top-1 accuracy, stage I", metrics["top1_accuracy_stage1"]),
        ("top-1 accuracy, stage II", metrics["top1_accuracy_stage2"]),
    ]
    rows += [(f"filtering recall@{n}", v) for n, v in metrics["filtering_recall_at_n"].items()]
    for L, seq in metrics.get("sequence", {}).items():
        rows.append((f"PR-AUC, sequence L={L} ({seq['direction']})", seq["pr_auc"]))
        rows.append((f"top-1 accuracy, sequence L={L}", seq["top1_accuracy"]))
    for name, value in rows:
        table.add_row(name, f"{value:.3f}")
    timing = metrics["timing"]
    table.add_row("encode per image", f"{1000 * timing['encode_s_per_image']:.0f} ms")
    table.add_row("query per image (median)", f"{1000 * timing['query_s_median']:.1f} ms")
    for L, seq in metrics.get("sequence", {}).items():
        table.add_row(f"sequence matcher L={L}, per query (median)", f"{seq['matcher_ms_median']:.1f} ms")
    return table


def run_vpr_eval(
    ref_dir: Path,
    query_dir: Path,
    config: SlamConfig,
    ground_truth: Path | None = None,
    sequential: bool = False,
    codebooks_path: Path | None = None,
    console: Console | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Encode both folders, recognise every query, write metrics/matches/plots; returns (folder, metrics).

    Sequence matching runs for each of `config.vpr_eval.sequence_lengths` beside single frames."""
    console = console or Console()
    check_search_device(config.vpr.filtering)  # before minutes of encoding
    ref_files, query_files = list_images(ref_dir), list_images(query_dir)
    gt = load_ground_truth(ground_truth, ref_files, query_files)
    warning = window_warning(gt, config.vpr_eval.tolerance)
    if warning is not None:  # before minutes of encoding, so the user can stop and rerun
        console.print(f"[bold yellow]warning:[/bold yellow] {escape(warning)}", highlight=False, soft_wrap=True)
    encoder = Encoder(config.vpr, load_backbone(config.vpr.backbone, progress=True))
    if codebooks_path is not None:
        encoder.codebooks = Codebooks.load(codebooks_path)
    with _progress(console) as progress:
        ref_codes, ref_s = encode_folder(
            encoder, ref_files, progress, "encoding references", fit=codebooks_path is None
        )
        query_codes, query_s = encode_folder(encoder, query_files, progress, "encoding queries", fit=False)
        assert encoder.codebooks is not None  # fitted on the references, or loaded
        database = PlaceDatabase(encoder.codebooks, config.vpr.database)
        database.add(ref_codes, [PlaceInfo(frame_id=i, name=p.name) for i, p in enumerate(ref_files)])
        # one BLAS thread for the many small stage-II products (two contend on a shared 2-core CPU)
        with one_blas_thread():
            outcome = recognise_all(TwoStageRanker(config.vpr, database), query_codes, sequential, progress,
                                    config.vpr_eval.sequence_lengths, config.vpr_eval.sequence)  # fmt: skip

    metrics = compute_metrics(outcome, gt, config)
    metrics["sequential"] = sequential
    metrics["timing"] = {
        "encode_s_per_image": (ref_s * len(ref_files) + query_s * len(query_files))
        / (len(ref_files) + len(query_files)),
        "query_s_median": float(np.median(outcome.query_seconds)),
        "query_s_mean": float(np.mean(outcome.query_seconds)),
        "device": str(encoder.backbone.device),
    }
    metrics["bytes_per_place"] = database.bytes_per_place
    metrics["inputs"] = {"ref_dir": str(ref_dir), "query_dir": str(query_dir),
                         "ground_truth": str(ground_truth) if ground_truth else "frame-aligned"}  # fmt: skip

    with staged_results_dir(config.results.out_dir, "vpr_eval") as staged:  # `latest` moves once complete
        folder = staged.path
        write_json(folder / "metrics.json", metrics)
        write_matches_csv(folder / "matches.csv", outcome, gt, config.vpr_eval.tolerance, ref_files, query_files)
        atomic_write_text(folder / "config.yaml", dump_config(config))
        if config.results.save_database:  # signed like a run's database, so --map can check it
            database.save(folder / "database", extra={"encoder": encoder_signature(config.vpr)})
        if config.results.plots:
            write_plots(folder, outcome, gt, metrics, config)
    assert staged.final is not None  # set when the block above completed
    folder = staged.final
    console.print(summary_table(metrics))
    console.print(f"results in [bold]{escape(str(folder))}[/bold]")
    return folder, metrics
