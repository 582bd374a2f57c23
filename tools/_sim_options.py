"""Traverse options shared by the simulator-driven benches: which simulation, route and length.

One place, so that `--route`, `--poses-frame`, the simulation YAML and `--frames` mean the same in
every bench. Without a YAML the base is the demo traverse (default_demo_config).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from frontend.errors import FrontendInputError
from frontend.simulation import SimulationConfig, default_demo_config

POSES_FRAMES = ("auto", "camera", "body")


def add_simulation_options(parser: argparse.ArgumentParser, config_flags: tuple[str, ...] = ("--sim-config",)) -> None:
    """--frames, --route, --poses-frame and the simulation YAML option(s) named `config_flags`."""
    parser.add_argument("--frames", type=int, default=None, help="stop after N frames (default: the whole traverse)")
    parser.add_argument(*config_flags, dest="sim_config", type=Path, default=None, metavar="FILE",
                        help="simulation YAML, a whole SimulationConfig (not merged over the demo's); default: the demo traverse")  # fmt: skip
    parser.add_argument("--route", type=Path, default=None, metavar="FILE",
                        help="TUM / KITTI poses file to drive (sets route.preset)")  # fmt: skip
    parser.add_argument("--poses-frame", choices=POSES_FRAMES, default=None,
                        help="convention of the --route poses (route.poses_frame); the simulator's default if not given")  # fmt: skip


def simulation_config(parser: argparse.ArgumentParser, args: argparse.Namespace, **overrides: Any) -> SimulationConfig:
    """The validated SimulationConfig the options ask for; `overrides` are top-level fields
    (sub-sections merge). A bad file or value ends the bench through parser.error (exit 2)."""
    try:
        base = SimulationConfig.from_yaml(args.sim_config) if args.sim_config else default_demo_config()
    except FrontendInputError as exc:
        parser.error(str(exc))
    data = base.model_dump()
    route: dict[str, Any] = {}
    if args.route is not None:
        route["preset"] = str(args.route)
    if args.poses_frame is not None:  # only when asked: older RouteConfigs have no such field
        route["poses_frame"] = args.poses_frame
    if route:
        overrides = {**overrides, "route": {**overrides.get("route", {}), **route}}
    if args.frames is not None:
        overrides = {**overrides, "max_frames": args.frames}
    for key, value in overrides.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) and isinstance(data.get(key), dict) else value
    try:
        return SimulationConfig.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"]) or "(top level)"
        hint = ""
        if first["loc"] == ("route", "poses_frame") and first["type"] == "extra_forbidden":
            hint = " (this simulator's RouteConfig has no poses_frame; leave out --poses-frame)"
        parser.error(f"simulation config: {where}: {first['msg']}{hint}")
