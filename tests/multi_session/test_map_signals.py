"""`map` under signals, on a real local Ray, as an operator meets them: SIGINT once the first of
two sessions has finished, SIGTERM and then SIGKILL while the second runs, and a last call that
finishes the map. Each stop keeps the finished session and says so in one line; SIGINT and
SIGTERM leave no process of the call running; every later call on the same `--out` adopts the
left-over map and reuses the finished session instead of running it again; the finished map
holds both sessions and nothing is left behind.

Two simulated sessions of one city (45 frames each, both cameras, the quick preset), one Ray
worker so the sessions run one after the other.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from map_sessions import linked_session_logs
from processes import all_pids, command_line, process_stat, session_workers

pytestmark = pytest.mark.slow

FRAMES = 45


def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.upper().startswith("SSMVPR_")}


def _finished(out: Path) -> int:
    for record in out.glob(".map_*.partial/finished_sessions.json"):
        try:
            return len(json.loads(record.read_text()))
        except (OSError, ValueError):
            return 0
    return 0


def _session_running(sid: int, since: dict[int, float], seconds: float) -> bool:
    """True once a Ray worker of the map call whose process session is `sid` has been running a
    session for `seconds` (another test's Ray, running beside this one, is not this call's)."""
    for pid in session_workers():
        stat = process_stat(pid)
        if (
            stat is not None
            and stat.session == sid
            and time.monotonic() - since.setdefault(pid, time.monotonic()) > seconds
        ):
            return True
    return False


def _processes_of_session(sid: int) -> list[str]:
    """Processes still alive in the process session `sid` (the map call's, with its Ray)."""
    alive = []
    for pid in all_pids():
        stat = process_stat(pid)
        if stat is not None and stat.session == sid and stat.state != "Z":
            alive.append(command_line(pid)[:80])
    return alive


class MapCall:
    """One `ssmvpr-slam map` in a process session of its own, its output in a file."""

    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self.handle = open(log, "wb")  # noqa: SIM115 (closed in `wait`)
        command = [sys.executable, "-c", "from ssmvpr_slam.cli import app; app()", "map", *args]
        self.process = subprocess.Popen(command, stdout=self.handle, stderr=subprocess.STDOUT, env=_env(),
                                        start_new_session=True)  # fmt: skip
        self.started = time.monotonic()

    def until(self, condition, what: str, limit_s: float = 400) -> None:  # noqa: ANN001
        while not condition():
            assert self.process.poll() is None, f"map ended before {what}:\n{self.output()}"
            assert time.monotonic() - self.started < limit_s, f"no {what} within {limit_s} s:\n{self.output()}"
            time.sleep(0.2)

    def wait(self, limit_s: float) -> int:
        try:
            return self.process.wait(limit_s)
        finally:
            if self.process.poll() is None:
                os.killpg(self.process.pid, signal.SIGKILL)
            self.handle.close()

    def output(self) -> str:
        return self.log.read_text(errors="replace")


@pytest.fixture(scope="module")
def calls(weights_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    base = tmp_path_factory.mktemp("map_signals")
    logs = linked_session_logs(weights_path, base, FRAMES, (0, 4))
    config = base / "map.yaml"
    config.write_text("preset: quick\nresults:\n  mcap: false\n  plots: false\nmap:\n  workers: 1\n"
                      "  codebook_images_per_session: 12\n")  # fmt: skip
    out = base / "out"
    args = [*map(str, logs), "-c", str(config), "--weights", str(weights_path), "--out", str(out)]
    seen: dict[str, object] = {"out": out}

    # SIGINT once the first session has finished
    call = MapCall(args, base / "sigint.log")
    call.until(lambda: _finished(out) == 1, "a finished session")
    finished_at = time.monotonic() - call.started
    call.process.send_signal(signal.SIGINT)
    stopped = time.monotonic()
    seen["sigint"] = (call.wait(120), time.monotonic() - stopped, call.output())
    seen["sigint_published"] = list(out.glob("map_*"))
    time.sleep(3)
    seen["sigint_left"] = _processes_of_session(call.process.pid)
    seen["first_session_s"] = finished_at

    # SIGTERM while the second session runs (the first reused)
    call = MapCall(args, base / "sigterm.log")
    since: dict[int, float] = {}
    call.until(lambda: _session_running(call.process.pid, since, 5.0), "a running session")
    call.process.send_signal(signal.SIGTERM)
    stopped = time.monotonic()
    seen["sigterm"] = (call.wait(120), time.monotonic() - stopped, call.output())
    time.sleep(3)
    seen["sigterm_left"] = _processes_of_session(call.process.pid)

    # SIGKILL of the map process while the second session runs (a scheduler's kill, an OOM)
    call = MapCall(args, base / "sigkill.log")
    since = {}
    call.until(lambda: _session_running(call.process.pid, since, 5.0), "a running session")
    call.process.send_signal(signal.SIGKILL)
    seen["sigkill"] = (call.wait(60), call.output())
    seen["after_kill"] = sorted(p.name for p in out.glob(".map_*"))

    # the last call finishes the map
    call = MapCall(args, base / "last.log")
    seen["last"] = (call.wait(600), call.output())
    seen["last_s"] = time.monotonic() - call.started
    return seen


def test_sigint_stops_map_promptly_keeping_the_finished_session(calls):
    code, took, output = calls["sigint"]
    assert code == 128 + signal.SIGINT, output
    assert took < 30, took
    assert "map stopped on SIGINT: 1 of 2 session(s) finished, kept in" in output, output
    assert "run the same command again" in output and "Traceback" not in output
    assert calls["sigint_published"] == []  # no map was published
    assert calls["sigint_left"] == [], calls["sigint_left"]  # Ray shut down with it


def test_sigterm_stops_map_with_one_line_of_ours_and_no_stack_dump(calls):
    code, took, output = calls["sigterm"]
    assert "reusing 1 session(s) a stopped `map` finished" in output, output
    assert code == 128 + signal.SIGTERM, output
    assert took < 30, took
    assert "map stopped on SIGTERM: 1 of 2 session(s) finished" in output, output
    assert "*** SIGTERM received" not in output and "Traceback" not in output
    assert calls["sigterm_left"] == [], calls["sigterm_left"]


def test_after_sigkill_the_staging_is_there_for_the_next_call(calls):
    code, output = calls["sigkill"]
    assert code == -signal.SIGKILL
    assert len(calls["after_kill"]) == 1 and calls["after_kill"][0].endswith(".partial")


def test_the_next_call_reuses_the_finished_session_and_publishes_the_whole_map(calls):
    code, output = calls["last"]
    assert code == 0, output
    assert "reusing 1 session(s) a stopped `map` finished" in output, output
    [folder] = calls["out"].glob("map_*")
    metrics = json.loads((folder / "metrics.json").read_text())
    assert [r["name"] for r in metrics["session_results"]] == ["s0_session0", "s1_session4"]
    assert all(r["error"] is None for r in metrics["session_results"])
    assert len(list((folder / "sessions").glob("s*_20*"))) == 2
    assert not (folder / "plan.json").exists() and not (folder / "finished_sessions.json").exists()
    assert not list(calls["out"].glob(".map_*"))  # nothing left behind
    reused = metrics["session_results"][0]["seconds"]
    print(f"\nthe reused session took {reused:.0f} s when it ran; the last call {calls['last_s']:.0f} s in all")
    for name in ("sigint", "sigterm", "sigkill", "last"):  # what an operator saw (pytest -s)
        print(f"--- {name}\n{calls[name][-1]}")
