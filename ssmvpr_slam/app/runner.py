"""`run` and `demo`: the thin runner around `SlamSystem` that owns the files, progress and signals.

`run_log` reads top to bottom as the steps of a run: open the log, load the prior map, build
the system (or restore it from a checkpoint), stream the frames with progress and
checkpoints, finish, evaluate, publish the results folder, print the summary.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from frontend.config import OdometryConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry import Odometry, choose_odometry, make_odometry
from frontend.sources import Source, open_source
from loopclosure.backbone import Backbone, load_backbone
from ssmvpr_common.disk_full import DiskFullError, is_disk_full
from ssmvpr_slam.app.checkpoint_replay import restore_from_checkpoint
from ssmvpr_slam.app.pipeline import SlamPipeline
from ssmvpr_slam.app.realtime import SensorClock
from ssmvpr_slam.checkpoint.saving import (
    Checkpoint,
    Checkpointer,
    CheckpointError,
    CheckpointMeta,
    carry_checkpoint,
    check_log,
    find_checkpoint,
    log_fingerprint,
)
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.evaluation.run_report import RunReport, evaluate
from ssmvpr_slam.kept_keyframe import kept_voxel
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.results.metrics import ResumedFrom, RunInputs, RunMetrics
from ssmvpr_slam.results.run_folder import RunFolder, staged_results_dir
from ssmvpr_slam.results.summary import summary_table
from ssmvpr_slam.results.writers import write_results
from ssmvpr_slam.run_result import RealtimeStats, RunResult
from ssmvpr_slam.run_state import RunState
from ssmvpr_slam.system import SlamSystem

if TYPE_CHECKING:
    from ssmvpr_slam.app.live_view import LiveView


def run_log(
    log: Path,
    config: SlamConfig,
    prior_map: Path | None = None,
    console: Console | None = None,
    name: str = "run",
    resume: Checkpoint | None = None,
    backbone: Backbone | None = None,
    view: LiveView | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Stream `log` through SLAM (from `resume`'s checkpoint if given); returns the results
    folder and its metrics. backbone: one already loaded (a `map` worker runs many logs with it).
    view: a live view (`run --viewer`) redrawn as keyframes come."""
    console = console or Console()
    source, odometry = open_camera_source(log, config, resume)
    config = config.model_copy(deep=True)  # resolved for this log; the caller's config stays as given
    config.frontend.odometry = odometry
    use_calibration(config, source)
    prior = PriorMap.load(prior_map, config.vpr) if prior_map is not None else None  # before the slow part
    pipeline = SlamPipeline(build_system(config, prior, backbone))
    if config.pipeline.realtime:
        pipeline.clock = SensorClock(config.pipeline.realtime_rate, config.pipeline.realtime_max_lag_s)
    frames = islice(source, config.pipeline.max_frames)  # a resume's replay counts towards the limit
    if resume is not None:
        restore_from_checkpoint(pipeline, resume, log, frames, console)
    run_folder = RunFolder(config.results.out_dir, name, resume.run_folder if resume else None)
    meta = CheckpointMeta(str(log), log_fingerprint(log), None if prior_map is None else str(prior_map), name)
    checkpoints = Checkpointer(run_folder, config, meta, pipeline.system, pipeline.ending.seconds)
    stream_frames(pipeline, frames, source, checkpoints, console, view)
    stopped = pipeline.ending.interrupted and checkpoints.write() is not None  # resumable where it stopped
    result = pipeline.finish()
    report = evaluate(result, config.evaluation)
    inputs = run_description(log, source, config, prior_map, resume)
    with resumable_on_disk_full(run_folder, log, name):
        folder, metrics = publish_results(run_folder, result, report, config, inputs, name, keep_checkpoint=stopped)
    print_summary(console, metrics, result, folder, name)
    if stopped:
        console.print(f"resume it with: ssmvpr-slam run {escape(str(log))} --resume {escape(str(folder))}")
    if result.realtime is not None and not result.realtime.kept_up:
        warn_fell_behind(console, result.realtime)
    if result.too_short_to_decide is not None:
        warn_too_short_to_decide(console, result.too_short_to_decide)
    raise_if_failed(pipeline, folder)
    return folder, metrics.to_json_dict()


def open_camera_source(
    log: Path, config: SlamConfig, resume: Checkpoint | None = None
) -> tuple[Source, OdometryConfig]:
    """The log's source, refused without camera images (or, for a resume, when it is not the
    checkpoint's log), and the odometry to run on it (`auto` resolved by its streams)."""
    source = open_source(log, config.frontend.source, config.frontend.pose_files)
    topics = source.topics
    if "camera" not in topics:  # places are recognised in images: a run without them finds no loop
        streams = ", ".join(sorted(topics)) or "none"
        raise FrontendInputError(f"{log}: no camera images to recognise places in (streams: {streams})")
    if not {"lidar", "logged_pose", "gt_pose"} & set(topics):  # nothing to drive with, nothing to judge by
        raise FrontendInputError(
            f"{log}: images only (no LiDAR scans, no poses): `run` needs odometry; give the folder a poses file "
            "(poses.txt, TUM or KITTI) and --pose-role logged, or measure recognition alone with "
            "`ssmvpr-slam loop-eval` (loop closures) or `ssmvpr-slam vpr-eval` (two passes)"
        )
    if resume is not None:
        check_log(resume, log)
    return source, choose_odometry(config.frontend.odometry, topics, str(log))


def use_calibration(config: SlamConfig, source: Source) -> None:
    """Two-view registration takes the forward camera's calibration from the log (CameraInfo,
    KITTI's calib.txt) where the config gives no fx: a guessed field of view bends every rotation
    the essential matrix gives. The rear camera is taken to be the same model (one K serves both).
    The run's config.yaml then records the K it used."""
    two_view = config.backend.registration.two_view
    camera = source.intrinsics.get("camera")
    if camera is None or two_view.fx is not None:
        return
    k = camera.k
    update = {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2])}
    config.backend.registration.two_view = two_view.model_copy(update=update)


def build_system(config: SlamConfig, prior: PriorMap | None, backbone: Backbone | None = None) -> SlamSystem:
    """The core with its odometry and backbone (the slow part: the weights load here, unless given)."""
    if backbone is None:
        backbone = load_backbone(config.vpr.backbone, progress=True)
    return SlamSystem(config, build_odometry(config), backbone, prior)


def build_odometry(config: SlamConfig) -> Odometry:
    """The configured odometry; kiss-icp with the stages overlapped runs in a process of its own,
    because it holds the GIL while it registers a scan and would stall the backbone's thread."""
    odometry = config.frontend.odometry
    own_process = config.pipeline.overlapped and odometry.kind == "kiss_icp"
    return make_odometry(odometry, config.frontend.pose_files, own_process=own_process, kept_voxel=kept_voxel(config))


def stream_frames(pipeline: SlamPipeline, frames: Iterator[Frame], source: Source, checkpoints: Checkpointer,
                  console: Console, view: LiveView | None = None) -> None:  # fmt: skip
    """Every frame through the pipeline, with a progress bar, a checkpoint when one is due and
    the live view redrawn."""
    with progress_bar(console, source, pipeline.config.pipeline.max_frames) as show:

        def after_frame(state: RunState) -> None:
            show(state)
            checkpoints.maybe()
            if view is not None:
                view.update(state, pipeline.graph)

        pipeline.run(frames, after_frame)
        if view is not None:
            view.update(pipeline.state, pipeline.graph, force=True)


@contextmanager
def progress_bar(console: Console, source: Source, limit: int | None = None) -> Iterator[Callable[[RunState], None]]:
    """A rich progress bar; yields the per-frame update."""
    total = getattr(source, "length", None)
    if limit is not None:
        total = limit if total is None else min(total, limit)
    columns = [TextColumn("[bold]SLAM"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("{task.fields[status]}")]  # fmt: skip
    with Progress(*columns, console=console) as progress:
        task = progress.add_task("frames", total=total, status="", completed=0)

        def show(state: RunState) -> None:
            fps = state.frames_seen / max(progress.tasks[task].elapsed or 1e-9, 1e-9)
            proposed = len(state.loops)
            in_graph = sum(r.in_graph for r in state.loops)
            progress.update(task, completed=state.frames_seen, status=f"kf {len(state.keyframes)} | loops "
                            f"{proposed} proposed, {in_graph} in graph | {fps:.1f} fps")  # fmt: skip

        yield show


def run_description(log: Path, source: Source, config: SlamConfig, prior_map: Path | None,
                    resume: Checkpoint | None) -> RunInputs:  # fmt: skip
    """What metrics.json says about the run's inputs."""
    resumed = None
    if resume is not None:
        resumed = ResumedFrom(checkpoint=resume.folder.name, frames=resume.result.frames_seen,
                              keyframes=len(resume.result.keyframes))  # fmt: skip
    return RunInputs(log=str(log), source=source.description, source_stats=_stats(source),
                     odometry_kind=config.frontend.odometry.kind, prior_map=str(prior_map) if prior_map else None,
                     resumed_from=resumed)  # fmt: skip


def publish_results(run_folder: RunFolder, result: RunResult, report: RunReport, config: SlamConfig,
                    inputs: RunInputs, name: str, keep_checkpoint: bool = False) -> tuple[Path, RunMetrics]:  # fmt: skip
    """Write every result into a staging folder and move it into place as one unit (over the
    run's checkpoints, if it wrote any); `latest` moves once it is complete. keep_checkpoint (a
    stopped run): the last checkpoint goes with the partial results, for `--resume`."""
    with staged_results_dir(run_folder.base, name, run_folder.path) as staged:
        metrics = write_results(staged.path, result, report, config, inputs)
        if keep_checkpoint:
            carry_checkpoint(run_folder.path, staged.path)
    assert staged.final is not None
    return staged.final, metrics


@contextmanager
def resumable_on_disk_full(run_folder: RunFolder, log: Path, name: str) -> Iterator[None]:
    """A disk that fills while the results are written drops only the staged results: the run's
    folder keeps its last checkpoint, so the error says how to resume from it rather than to run
    the whole log again (`map` sessions have their own recovery and are left to say theirs)."""
    try:
        yield
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        full = exc if isinstance(exc, DiskFullError) else DiskFullError.of(exc.filename, exc)
        folder = run_folder.path
        if full.advice is None and folder is not None and name in ("run", "demo") and _has_checkpoint(folder):
            full.advice = (f"free space, then resume from the last checkpoint, kept in {folder}: "
                           f"ssmvpr-slam run {log} --resume {folder}")  # fmt: skip
        if full is exc:
            raise
        raise full from exc


def _has_checkpoint(folder: Path) -> bool:
    try:
        find_checkpoint(folder)
    except CheckpointError:
        return False
    return True


def print_summary(console: Console, metrics: RunMetrics, result: RunResult, folder: Path, name: str = "run") -> None:
    console.print(summary_table(metrics, f"ssmvpr-slam {name}"))
    if result.ending.interrupted:
        console.print("[yellow]stopped early on request: results cover the frames processed so far[/yellow]")
    console.print(f"results in [bold]{escape(str(folder))}[/bold]")


def warn_fell_behind(console: Console, live: RealtimeStats) -> None:
    """A real-time run that left keyframes out: how many, and what to do about it."""
    console.print(
        f"[yellow]warning: the run fell behind its log played at x{live.rate:g}: {live.keyframes_skipped} of "
        f"{live.keyframes} keyframes came more than {live.max_lag_s:g} s late and skipped recognition (lag p99 "
        f"{live.lag_p99_s:.1f} s); play it slower (--rate), use a lighter preset (-c fast), or allow more lag "
        "(pipeline.realtime_max_lag_s)[/yellow]"
    )


def warn_too_short_to_decide(console: Console, why: str) -> None:
    """A run too short to decide anything looks like one that found no loop; say which it was."""
    console.print(
        f"[yellow]warning: too short to decide any loop: {escape(why)}; its recall says nothing about "
        "the detector (for a run this short, fit codebooks first with ssmvpr-slam fit-pca and pass them as "
        "detector.codebooks, or close loops against a map with --map)[/yellow]"
    )


def raise_if_failed(pipeline: SlamPipeline, folder: Path) -> None:
    """A run that failed midway still wrote its results above; it then reports the failure."""
    if pipeline.step_error is not None:
        raise pipeline.step_error
    source_error = pipeline.ending.source_error
    if source_error is not None:  # the frames before the fault are processed and written
        raise FrontendInputError(f"{source_error} (results up to there are in {folder})")


def _stats(source: object) -> dict[str, Any]:
    stats = getattr(source, "stats", None)
    if stats is None:
        return {}
    return {"frames_yielded": stats.frames_yielded, "skipped": dict(stats.skipped), "notes": dict(stats.notes)}


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

        write_frames(frames(), out, config.frontend.writer, simulator.intrinsics)
    return out


def simulate_sessions(config: SlamConfig, folder: Path, count: int, first: int, console: Console) -> list[Path]:
    """`count` sessions of the configured city (`frontend.simulation.sessions`) as
    `folder/session<k>.mcap`, numbered from `first`."""
    from frontend.simulation.sessions import city_sessions

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for k, simulation in enumerate(city_sessions(config.simulation, count, first), start=first):
        session = config.model_copy(update={"simulation": simulation})
        written.append(simulate_to_mcap(session, folder / f"session{k}.mcap", console))
    return written


__all__ = ["run_log", "simulate_sessions", "simulate_to_mcap"]
