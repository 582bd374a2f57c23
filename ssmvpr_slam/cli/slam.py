"""`run`, `demo` and `simulate`: SLAM on a log, the simulated quick start, and the simulator's
logs. The work is in `runner` (a run), `resume` (what `--resume` keeps) and `simulated_logs`
(the demo's cached log); a command here parses its options and calls them."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape

from ssmvpr_slam.cli.common import (
    ConfigOpt,
    DeviceOpt,
    OutOpt,
    WeightsOpt,
    app,
    console,
    examples,
    make_config,
    odometry_kind,
    out_option,
    validated_update,
)
from ssmvpr_slam.cli.errors import friendly_errors


@app.command(
    "run",
    epilog=examples(
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
    from ssmvpr_slam.app.runner import run_log
    from ssmvpr_slam.results.run_folder import output_dir

    if resume is not None:
        from ssmvpr_slam.checkpoint.resume import prepare_resume

        options = {"--config": config, "--odometry": odometry, "--map": map_dir, "--no-lidar-loops": no_lidar_loops,
                   "--out": out, "--frames": frames, "--pose-role": pose_role, "--realtime": realtime,
                   "--rate": rate}  # fmt: skip
        resumed = prepare_resume(resume, options, weights, device)  # refuses the options that change settings
        run_log(log, resumed.config, resumed.prior_map, console, name=resumed.name, resume=resumed.checkpoint)
        return
    if rate is not None and not realtime:
        from ssmvpr_slam.errors import OptionError

        raise OptionError("--rate sets the pace of --realtime; add --realtime")
    cfg = make_config(config, weights, device, out)
    if frames is not None:
        cfg.pipeline = validated_update(cfg.pipeline, {"max_frames": frames})
    if realtime:
        live = {"realtime": True} if rate is None else {"realtime": True, "realtime_rate": rate}
        cfg.pipeline = validated_update(cfg.pipeline, live)
    if odometry is not None:
        cfg.frontend.odometry.kind = odometry_kind(odometry)  # type: ignore[assignment]
    if pose_role is not None:
        cfg.frontend.source.folder = validated_update(cfg.frontend.source.folder, {"pose_role": pose_role})
    if no_lidar_loops:
        cfg.pipeline.use_lidar_for_loops = False
    with output_dir(cfg.results.out_dir, out_option(out)), _live_view(viewer, viewer_port, console) as view:
        run_log(log, cfg, map_dir, console, view=view)


@contextlib.contextmanager
def _live_view(enabled: bool, port: int, console: Console) -> Iterator[Any]:
    """`run --viewer`: the view served for the run; when the run ends in a terminal, it stays up
    (the final state drawn) until Enter or Ctrl-C."""
    if not enabled:
        yield None
        return
    from ssmvpr_slam.app.live_view import LiveView

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


@app.command(
    "demo",
    epilog=examples(
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
    from ssmvpr_slam.app.runner import run_log
    from ssmvpr_slam.app.simulated_logs import demo_log, with_demo_odometry
    from ssmvpr_slam.config.slam import resolve_weights_first
    from ssmvpr_slam.results.run_folder import output_dir

    cfg = make_config(config, weights, device, out)
    if frames is not None:
        cfg.simulation = validated_update(cfg.simulation, {"max_frames": frames})
    cfg = with_demo_odometry(cfg, odometry_kind(odometry))
    resolve_weights_first(cfg)
    with output_dir(cfg.results.out_dir, out_option(out)):
        log = demo_log(cfg, console)  # in the user cache, reused by the next demo with the same settings
        run_log(log, cfg, console=console, name="demo")


@app.command(
    "simulate",
    epilog=examples(
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
    from ssmvpr_slam.app.runner import simulate_sessions, simulate_to_mcap
    from ssmvpr_slam.results.run_folder import output_dir, output_file

    cfg = make_config(config)
    if sim_config is not None:
        cfg.simulation = SimulationConfig.from_yaml(sim_config)
    updates = {k: v for k, v in {"max_frames": frames, "seed": seed}.items() if v is not None}
    cfg.simulation = validated_update(cfg.simulation, updates)
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
