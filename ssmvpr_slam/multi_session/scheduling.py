"""`map`'s work on Ray, each step cancellable: the shared codebooks, the sessions, the
cross-session matching. Every wait is bounded (half a second) so a stop request is seen
promptly; a stop kills the workers in flight (a session half done is run again by the next
call) and cancels the matching tasks.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.multi_session.cross_loops import CrossLoop, find_cross_loops, views_verifier
from ssmvpr_slam.multi_session.session_map import SessionMap
from ssmvpr_slam.multi_session.stop import MapStop
from ssmvpr_slam.multi_session.workers import SessionOutcome, remote_worker

_POLL_S = 0.5


def fit_codebooks(config: SlamConfig, logs: list[Path], out: Path, stop: MapStop) -> bool:
    """The shared PCA codebooks fitted on every log, into `out`; False when stopped first."""
    import ray

    fitter = remote_worker(config)
    try:
        future = fitter.fit_codebooks.remote([str(p) for p in logs], str(out))
        while not ray.wait([future], timeout=_POLL_S)[0]:
            if stop.requested:
                return False
        ray.get(future)
        return True
    finally:
        ray.kill(fitter)


def run_sessions(
    config: SlamConfig,
    jobs: list[tuple[int, str, str]],
    codebooks: Path,
    out_dir: Path,
    console: Console,
    stop: MapStop,
    finished: Callable[[SessionOutcome], None],
) -> list[SessionOutcome]:
    """Every (index, name, log) as a session on the workers, each worker taking the next when
    free; `finished` is called as each ends. A worker that died for good is replaced and its
    session reported failed; on a stop, the workers in flight are killed and the sessions
    done so far returned."""
    import ray
    from ray.exceptions import RayActorError, RayTaskError

    workers = [remote_worker(config) for _ in range(min(config.map.workers, len(jobs)))]
    pending = deque(jobs)
    running: dict[Any, tuple[int, tuple[int, str, str]]] = {}

    def submit(w: int) -> None:
        job = pending.popleft()
        running[workers[w].run_session.remote(*job, str(codebooks), str(out_dir))] = (w, job)

    for w in range(len(workers)):
        if pending:
            submit(w)
    outcomes = []
    try:
        while running and not stop.requested:
            done, _ = ray.wait(list(running), num_returns=1, timeout=_POLL_S)
            if not done:
                continue
            w, (index, name, log) = running.pop(done[0])
            try:
                outcome = ray.get(done[0])
            except RayActorError as exc:  # killed beyond its retries: a fresh worker takes the next session
                outcome = SessionOutcome(index, name, log, error=f"its worker died ({type(exc).__name__})")
                workers[w] = remote_worker(config)
            except RayTaskError as exc:
                cause = exc.cause if exc.cause is not None else exc
                outcome = SessionOutcome(index, name, log, error=f"{type(cause).__name__}: {cause}")
            outcomes.append(outcome)
            finished(outcome)
            if outcome.error is None:
                console.print(f"session {escape(name)}: {outcome.keyframes} keyframes in {outcome.seconds:.0f} s")
            else:
                console.print(f"[red]session {escape(name)} ({escape(log)}) failed:[/red] {escape(outcome.error)}")
            if pending:
                submit(w)
    finally:
        for worker in workers:
            ray.kill(worker, no_restart=True)
    return sorted(outcomes, key=lambda o: o.index)


def _cross_loops_task(query: int, folders: list[tuple[str, str, str]], config: SlamConfig) -> list[CrossLoop]:
    """One session's cross loops; the backbone is loaded (once per worker process) only where
    camera-only sessions need two views verified."""
    sessions = [SessionMap.load(name, log, Path(folder), config.vpr) for name, log, folder in folders]
    return find_cross_loops(query, sessions, config, views_verifier(query, sessions, config))


def all_cross_loops(sessions: list[SessionMap], config: SlamConfig, stop: MapStop) -> list[CrossLoop] | None:
    """Every session's keyframes against the others' places, one Ray task per session; None
    when stopped (the tasks are cancelled)."""
    import ray

    folders = [(s.name, s.log, str(s.folder)) for s in sessions]
    task = ray.remote(_cross_loops_task).options(num_cpus=1)
    futures = [task.remote(k, folders, config) for k in range(len(sessions))]
    while len(ray.wait(futures, num_returns=len(futures), timeout=_POLL_S)[0]) < len(futures):
        if stop.requested:
            for future in futures:
                ray.cancel(future, force=True)
            return None
    return [loop for part in ray.get(futures) for loop in part]
