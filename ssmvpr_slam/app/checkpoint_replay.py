"""Resuming a run from its checkpoint: the system's state put back from plain data, then the
odometry re-derived by replaying the frames the checkpoint had seen.

The odometry's state is not serialisable (kiss-icp's voxel map lives in C++), so a resume reads
the log again from its start, feeding the frames before the checkpoint to the odometry only;
everything else (keyframes, loops, the detector, the pose graph) comes back from the files
`ssmvpr_slam.checkpoint.saving` wrote."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from loopclosure.errors import LoopClosureInputError
from ssmvpr_slam.app.pipeline import SlamPipeline
from ssmvpr_slam.checkpoint.saving import Checkpoint, CheckpointError
from ssmvpr_slam.run_result import LoopRecord, RunResult, StageTimes, StreamEnd
from ssmvpr_slam.run_state import FrontCounts, RunState
from ssmvpr_slam.system import SlamSystem


def restore_system(system: SlamSystem, partial: RunResult, detector_state: dict[str, np.ndarray]) -> None:
    """Continue a fresh `system` from a checkpoint (`checkpoint.partial_result` and the detector's state arrays).

    The pose graph is rebuilt by repeating the original calls in their order (each keyframe,
    the loop factors that fell due at it, one iSAM2 step), so it is the graph the run had; the
    loops registered but not yet due go back to the registration queue; the odometry comes
    back by `replay_frames`."""
    if system.state.frames_seen or system.state.keyframes or system.finished:
        raise RuntimeError("restore_system: only a fresh system can be restored")
    if partial.database is None:
        raise ValueError("restore: the checkpoint holds no place database")
    system.detector.load_state_arrays(detector_state, partial.database)
    rows = [dict(r) for r in partial.timings]
    system.state = RunState([], [], partial.frames_seen, Counter(partial.frames_skipped), partial.rear_keyframes,
                            StageTimes(rows))  # fmt: skip
    system.front_counts = FrontCounts(partial.frames_seen, Counter(partial.frames_skipped), len(partial.keyframes))
    lag = system.registrations.lag
    made: dict[int, list[LoopRecord]] = {}  # by the keyframe that proposed them
    due: dict[int, list[LoopRecord]] = {}  # factors, by the keyframe whose step added them
    for record in partial.loops:
        made.setdefault(record.proposal.query_id, []).append(record)
        if record.factor_handle is not None:
            due.setdefault(record.proposal.query_id + lag, []).append(record)
    for kf in partial.keyframes:
        system.state.keyframes.append(kf)
        system.graph.add_keyframe(kf.id, kf.odom_pose)
        system.state.loops.extend(made.get(kf.id, []))
        for record in due.get(kf.id, []):
            restored = system.add_loop_factor(replace(record, factor_handle=None))
            if restored.factor_handle != record.factor_handle:
                raise ValueError(f"restore: keyframe {kf.id}'s loop factor came back as handle "
                                 f"{restored.factor_handle}, the checkpoint says {record.factor_handle}")  # fmt: skip
        system.graph.update()
    system.registrations.restore(system.state.loops, partial.unapplied_registrations)
    system.recoveries_told = len(system.graph.recoveries)  # warned about when the run first met them


def resume_keyframe_selection(system: SlamSystem) -> None:
    """After the replay: the next keyframe is chosen relative to the checkpoint's last one."""
    system.selector.reset()
    keyframes = system.state.keyframes
    if keyframes:
        system.selector.select(keyframes[-1].odom_pose, keyframes[-1].timestamp)
        system.selector.count = len(keyframes)
    system.front_counts.keyframes = len(keyframes)


def restore_from_checkpoint(pipeline: SlamPipeline, checkpoint: Checkpoint, log: Path, frames: Iterator[Frame],
                            console: Console) -> None:  # fmt: skip
    """Put the pipeline back where the checkpoint left it: the state from the files, then the
    odometry by replaying the frames the checkpoint had seen (with a progress bar)."""
    system = pipeline.system
    try:
        restore_system(system, checkpoint.result, checkpoint.detector_state)
    except (LoopClosureInputError, KeyError) as exc:  # a state this build or these settings cannot take
        what = f"lacks {exc}" if isinstance(exc, KeyError) else str(exc)
        raise CheckpointError(f"{checkpoint.folder / 'detector.npz'}: {what}") from None
    seen = checkpoint.result.frames_seen
    with Progress(TextColumn("[bold]replaying odometry"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console) as progress:  # fmt: skip
        task = progress.add_task("frames", total=seen)
        for _ in range(seen):
            frame = next(frames, None)
            if frame is None:
                raise FrontendInputError(f"{log}: ended after {progress.tasks[task].completed:.0f} frames; "
                                         f"the checkpoint had seen {seen}")  # fmt: skip
            system.odometry.update(frame)  # the odometry only: the rest came back from the files
            progress.advance(task)
    resume_keyframe_selection(system)
    pipeline.ending = StreamEnd(seconds=checkpoint.result.ending.seconds)  # the run's time carries on
    console.print(f"resumed from [bold]{escape(str(checkpoint.folder))}[/bold]: {len(checkpoint.result.keyframes)} "
                  f"keyframes, {seen} frames")  # fmt: skip
