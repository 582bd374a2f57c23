"""`run` and `demo`: wire a source, odometry, weights and a prior map into the pipeline."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from frontend.errors import FrontendInputError
from frontend.odometry import choose_odometry, make_odometry
from frontend.sources import open_source
from loopclosure.backbone import load_backbone
from ssmvpr_slam.config import SlamConfig
from ssmvpr_slam.pipeline import RunState, SlamPipeline
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.results import staged_results_dir
from ssmvpr_slam.run_results import write_run_results


def run_log(
    log: Path,
    config: SlamConfig,
    prior_map: Path | None = None,
    inject_wrong_loops: float = 0.0,
    console: Console | None = None,
    name: str = "run",
) -> tuple[Path, dict[str, Any]]:
    """Stream `log` through the pipeline; returns the results folder and its metrics."""
    console = console or Console()
    source = open_source(log, config.frontend.source, config.frontend.pose_files)
    topics = source.topics
    if "camera" not in topics:  # places are recognised in images: a run without them finds no loop
        streams = ", ".join(sorted(topics)) or "none"
        raise FrontendInputError(f"{log}: no camera images to recognise places in (streams: {streams})")
    config.frontend.odometry = choose_odometry(config.frontend.odometry, topics, str(log))
    odometry = make_odometry(config.frontend.odometry, config.frontend.pose_files)
    database = PriorMap.load(prior_map, config.vpr) if prior_map is not None else None  # before the slow part
    backbone = load_backbone(config.vpr.backbone, progress=True)
    pipeline = SlamPipeline(config, odometry, backbone, database, inject_wrong_loops)
    frames = iter(source)

    total = getattr(source, "length", None)
    columns = [TextColumn("[bold]SLAM"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("{task.fields[status]}")]  # fmt: skip
    with Progress(*columns, console=console) as progress:
        task = progress.add_task("frames", total=total, status="")

        def on_frame(state: RunState) -> None:
            fps = state.frames_seen / max(progress.tasks[task].elapsed or 1e-9, 1e-9)
            proposed = len(state.loops)
            in_graph = sum(r.in_graph for r in state.loops)
            progress.update(task, advance=1, status=f"kf {len(state.keyframes)} | loops {proposed} proposed, "
                            f"{in_graph} in graph | {fps:.1f} fps")  # fmt: skip

        pipeline.run(frames, on_frame)
    extra = {"log": str(log), "source": source.description, "source_stats": _stats(source),
             "odometry_kind": config.frontend.odometry.kind, "prior_map": str(prior_map) if prior_map else None,
             "injected_wrong_loop_rate": inject_wrong_loops}  # fmt: skip
    with staged_results_dir(config.results.out_dir, name) as staged:  # `latest` moves once complete
        metrics = write_run_results(staged.path, pipeline, config, extra)
    folder = staged.final
    console.print(summary_table(metrics))
    if pipeline.state.interrupted:
        console.print("[yellow]stopped early on request: results cover the frames processed so far[/yellow]")
    console.print(f"results in [bold]{escape(str(folder))}[/bold]")
    if pipeline.state.step_error is not None:
        raise pipeline.state.step_error  # results up to the failing frame are written above
    if pipeline.state.source_error is not None:
        # the frames before the fault are processed and written; the run still reports failure
        raise FrontendInputError(f"{pipeline.state.source_error} (results up to there are in {folder})")
    return folder, metrics


def _stats(source: object) -> dict[str, Any]:
    stats = getattr(source, "stats", None)
    if stats is None:
        return {}
    return {"frames_yielded": stats.frames_yielded, "skipped": dict(stats.skipped), "notes": dict(stats.notes)}


def summary_table(metrics: dict[str, Any]) -> Table:
    table = Table(title="ssmvpr-slam run")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_row("frames / keyframes", f"{metrics['frames']} / {metrics['keyframes']}")
    loops = metrics.get("loops", {})
    if loops:
        table.add_row("loops proposed / gate-accepted / in graph",
                      f"{loops['proposed']} / {loops['gate_accepted']} / {loops['in_graph']}")  # fmt: skip
        fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
        table.add_row("loop precision / recall", f"{fmt(loops['precision'])} / {fmt(loops['recall'])}")
        if "recall_visible" in loops:  # what a camera could see: reverse revisits show the far side
            fwd, rev = loops["by_direction"]["forward"], loops["by_direction"]["reverse"]
            table.add_row("recall of visible / forward / reverse revisits",
                          f"{fmt(loops['recall_visible'])} / {fmt(fwd['recall'])} / {fmt(rev['recall'])}")  # fmt: skip
        if loops.get("rear_camera_keyframes"):  # the rear camera is what recognises reverse revisits
            by_camera = loops["in_graph_by_camera"]
            table.add_row("loops in graph: front / rear camera", f"{by_camera['front']} / {by_camera['rear']}")
    if "ground_truth_coverage" in metrics:  # evaluated on the keyframes with ground truth only
        covered, total = metrics["ground_truth_keyframes"], metrics["keyframes"]
        table.add_row("ground truth coverage", f"{covered} / {total} keyframes ({100 * metrics['ground_truth_coverage']:.0f}%)")
    if "ate_odometry" in metrics:
        table.add_row("ATE RMSE odometry", f"{metrics['ate_odometry']['rmse']:.2f} m")
        table.add_row("ATE RMSE optimised", f"{metrics['ate_optimised']['rmse']:.2f} m")
        table.add_row("optimised / odometry", f"{metrics['ate_ratio']:.3f}")
    if "stream_pr_auc" in metrics:
        table.add_row("stream PR-AUC", f"{metrics['stream_pr_auc']:.3f}")
    latency = metrics.get("latency_per_keyframe", {}).get("total")
    if latency:
        table.add_row("latency per keyframe (median)", f"{1000 * latency['median_s']:.0f} ms")
    return table


def simulate_to_mcap(config: SlamConfig, out: Path, console: Console) -> Path:
    from frontend.simulation.simulator import TraverseSimulator
    from frontend.sources import write_frames

    simulator = TraverseSimulator(config.simulation)
    with Progress(TextColumn("[bold]simulating"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console) as progress:  # fmt: skip
        task = progress.add_task("frames", total=len(simulator))

        def frames():  # noqa: ANN202
            for frame in simulator.frames():
                yield frame
                progress.advance(task)

        write_frames(frames(), out, config.frontend.writer)
    return out


def demo_frames_config(config: SlamConfig) -> SlamConfig:
    """The demo's traverse: the simulator's default loopy city drive."""
    from frontend.simulation.simulator import default_demo_config

    if config.simulation == type(config.simulation)():
        config.simulation = default_demo_config()
    return config


__all__ = ["run_log", "simulate_to_mcap", "demo_frames_config"]
