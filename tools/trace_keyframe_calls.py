"""Follow one keyframe's calls through `SlamSystem.process`: which of the project's modules it
enters, in what order, and how often it returns to a module it already left (a reader following
the code goes back and forth that often). The keyframe is the first whose proposal is accepted
(`--accepted N`: the Nth; or `--keyframe K`); its loop is registered inline, so the trace holds the whole of it.

    python tools/trace_keyframe_calls.py --log quick.mcap --config quick --weights $W

Two passes over the log, the same each time (loops registered inline, no stage overlap): the
first finds the keyframe, the second profiles only the `process` call of its frame. Prints JSON:
module visits (consecutive calls inside one module are one visit), distinct modules, returns to
a module already left, and the visits in order.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PACKAGES = ("ssmvpr_slam.", "loopclosure.", "frontend.", "ssmvpr_common.")


def _frames(args: argparse.Namespace, config: Any) -> Iterator[Any]:
    """The log's frames, its odometry resolved into `config` as `run` resolves it."""
    from ssmvpr_slam.app.runner import open_camera_source

    source, odometry = open_camera_source(Path(args.log), config)
    config.frontend.odometry = odometry
    yield from source


class _Run:
    """A fresh system over the log's frames (built at the first frame, once the odometry is known)."""

    def __init__(self, args: argparse.Namespace, config: Any, backbone: Any) -> None:
        self.frames = _frames(args, config)
        first = next(self.frames)
        from ssmvpr_slam.app.runner import build_odometry
        from ssmvpr_slam.system import SlamSystem

        self.system = SlamSystem(config, build_odometry(config), backbone)
        self.first = first

    def __iter__(self) -> Iterator[Any]:
        yield self.first
        yield from self.frames


def _target(args: argparse.Namespace, config: Any, backbone: Any) -> tuple[int, int]:
    """(frame index, keyframe id) of the keyframe to trace."""
    run = _Run(args, config, backbone)
    system = run.system
    accepted = 0
    for index, frame in enumerate(run):
        loops, keyframes = len(system.state.loops), len(system.state.keyframes)
        system.process(frame)
        if len(system.state.keyframes) == keyframes:
            continue  # not a keyframe
        kf = keyframes
        accepted += any(r.proposal.accepted for r in system.state.loops[loops:])
        if kf == args.keyframe or (args.keyframe is None and accepted == args.accepted):
            return index, kf
    raise SystemExit("no keyframe to trace: no proposal was accepted (give --keyframe K)")


def _trace(args: argparse.Namespace, config: Any, backbone: Any, frame_index: int) -> list[str]:
    """The module of the innermost project frame at every call and return of that frame's process."""
    run = _Run(args, config, backbone)
    system = run.system
    events: list[str] = []

    def profile(frame: Any, event: str, _arg: Any) -> None:
        if event not in ("call", "return"):
            return
        while frame is not None:
            name = frame.f_globals.get("__name__", "")
            if name.startswith(PACKAGES):
                events.append(name)
                return
            frame = frame.f_back

    for index, frame in enumerate(run):
        if index < frame_index:
            system.process(frame)
            continue
        sys.setprofile(profile)
        try:
            system.process(frame)
        finally:
            sys.setprofile(None)
        break
    return events


def summarise(events: list[str]) -> dict[str, Any]:
    """Visits (runs of one module), distinct modules, and returns to a module already left."""
    visits: list[str] = []
    for module in events:
        if not visits or visits[-1] != module:
            visits.append(module)
    seen: set[str] = set()
    returns = 0
    for module in visits:
        returns += module in seen
        seen.add(module)
    return {"visits": len(visits), "modules": len(seen), "returns": returns, "order": visits}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--log", required=True)
    parser.add_argument("--config", default=None, help="a preset or YAML file")
    parser.add_argument("--weights", required=True)
    parser.add_argument("--accepted", type=int, default=1, help="trace the keyframe of the Nth accepted proposal")
    parser.add_argument("--keyframe", type=int, default=None, help="trace this keyframe instead")
    args = parser.parse_args()

    from loopclosure.backbone import load_backbone
    from ssmvpr_slam.config.slam import load_config

    overrides = {"vpr": {"backbone": {"weights": args.weights}},
                 "pipeline": {"overlap": False, "registration_worker": False}}  # fmt: skip
    config = load_config(args.config, overrides)
    backbone = load_backbone(config.vpr.backbone)
    frame_index, keyframe = _target(args, config, backbone)
    events = _trace(args, config, backbone, frame_index)
    summary = summarise(events)
    print(json.dumps({"log": args.log, "frame": frame_index, "keyframe": keyframe,
                      "loop_acceptance": summarise(acceptance(events)), **summary}, indent=1))  # fmt: skip


def acceptance(events: list[str]) -> list[str]:
    """The part of the trace that decides the keyframe's loop: from the registrations' queue to
    the factor (what a reader of one loop's acceptance follows), without the recognition before."""
    inside = [k for k, module in enumerate(events) if module == "ssmvpr_slam.loop_registrations"]
    return events[inside[0] : inside[-1] + 1] if inside else []


if __name__ == "__main__":
    main()
