"""`map`: many logs, one map. The work is in `multi_session.runner` (which checks the logs given
and finds the weights before Ray starts); the command parses its options and calls it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from ssmvpr_slam.cli.common import (
    ConfigOpt,
    DeviceOpt,
    OutOpt,
    WeightsOpt,
    app,
    console,
    err_console,
    examples,
    make_config,
    out_option,
    validated_update,
)
from ssmvpr_slam.cli.errors import friendly_errors


@app.command(
    "map",
    epilog=examples(
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
    from ssmvpr_slam.multi_session.runner import map_logs
    from ssmvpr_slam.multi_session.stop import MapStopped
    from ssmvpr_slam.results.run_folder import output_dir

    every = [*(logs or []), *(add or [])]
    if add and map_dir is None:
        raise OptionError("--add needs --map: the map folder the sessions join")
    if not every:
        raise OptionError("no logs: give the logs to map (or --map DIR --add LOG)")
    cfg = make_config(config, weights, device, out)
    if workers is not None:
        cfg.map = validated_update(cfg.map, {"workers": workers})
    with output_dir(cfg.results.out_dir, out_option(out)):
        try:
            map_logs(every, cfg, console, add_to=map_dir, ray_address=ray_address, resume=resume)
        except MapStopped as stopped:  # finished sessions kept: the exit status says which signal
            err_console.print(f"[yellow]{escape(str(stopped))}[/yellow]", highlight=False, soft_wrap=True)
            raise typer.Exit(128 + stopped.signum) from None
