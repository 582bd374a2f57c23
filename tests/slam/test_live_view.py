"""The live view (`run --viewer`): its server publishes the trajectory, the loop edges and the
keyframes, read here by a websocket client speaking viser's wire format; and the page, opened
in a real browser (the system's Chromium through Playwright), draws them."""

from __future__ import annotations

import json
import os
import shutil
import socket
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401
from small_logs import small_camera_log

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.run_result import Keyframe, LoopRecord
from ssmvpr_slam.run_state import RunState

viser = pytest.importorskip("viser", reason="the live view needs the `viewer` extra (pip install -e '.[viewer]')")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loop_of_two_laps(n: int = 40) -> tuple[RunState, SimpleNamespace]:
    """A square driven twice, keyframes with thumbnails, loops from the second lap onto the
    first in the graph; the graph's estimate is the odometry nudged."""
    state = RunState()
    side = n // 4
    corners = np.array([[0, 0], [30, 0], [30, 30], [0, 30]], float)
    for k in range(2 * n):
        lap = k % n
        a, b = corners[lap // side], corners[(lap // side + 1) % 4]
        xy = a + (b - a) * (lap % side) / side
        pose = np.eye(4)
        pose[:2, 3] = xy + 0.05 * (k // n)  # the second lap drifted a little
        thumb = cv2.imencode(".jpg", np.full((24, 32, 3), (k * 3) % 255, np.uint8))[1].tobytes()
        state.keyframes.append(Keyframe(k, 2 * k, float(k), pose, None, None, None, thumbnail=thumb))
    for k in range(n, 2 * n):
        proposal = LoopProposal(k, k - n, k - n, 0.6, 0.2, 0, 0.0, True, "accepted")
        registration = LoopRegistration(np.eye(4), True, "icp", 0.9, 0.1, method="icp")
        state.loops.append(LoopRecord(proposal, registration, factor_handle=k - n))
    state.frames_seen = 4 * n
    graph = SimpleNamespace(optimized_poses=lambda: {k.id: k.odom_pose for k in state.keyframes})
    return state, graph


def read_published(port: int, seconds: float = 3.0) -> list[dict[str, Any]]:
    """Every message the server sends a new client within `seconds`, decoded (viser's wire
    format: the sizes, then zstd-compressed msgpack, then the raw buffers)."""
    import msgspec
    import zstandard
    from websockets.sync.client import connect

    messages: list[dict[str, Any]] = []
    version = viser.__version__
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{version}"], open_timeout=10) as ws:  # type: ignore[list-item]
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                raw = ws.recv(timeout=max(0.05, deadline - time.monotonic()))
            except TimeoutError:
                break
            assert isinstance(raw, bytes)
            size = int.from_bytes(raw[:8], "little")
            compressed = int.from_bytes(raw[8:16], "little")
            inner = zstandard.ZstdDecompressor().decompress(raw[16 : 16 + compressed], max_output_size=size)
            messages.extend(msgspec.msgpack.decode(inner)["messages"])
    return messages


def test_the_server_publishes_the_trajectories_the_loops_and_the_keyframes() -> None:
    from ssmvpr_slam.app.live_view import LiveView

    state, graph = loop_of_two_laps()
    view = LiveView(port=free_port(), min_interval_s=0.0)
    try:
        assert view.update(state, graph) is True
        assert view.update(state, graph) is False  # nothing new since: not redrawn
        messages = read_published(view.port)
    finally:
        view.close()
    types: dict[str, set[str]] = {}
    for m in messages:
        if isinstance(m, dict) and "name" in m:
            types.setdefault(m["name"], set()).add(m["type"])
    for name in ("/slam/odometry", "/slam/optimised", "/slam/loops"):
        assert "LineSegmentsMessage" in types.get(name, set()), sorted(types)
    for name in ("/slam/keyframe", "/slam/match"):
        assert "FrameMessage" in types.get(name, set()), sorted(types)
        assert "CameraFrustumMessage" in types.get(f"{name}/camera", set()), sorted(types)
    loops = next(m for m in messages if isinstance(m, dict) and m.get("name") == "/slam/loops"
                 and m["type"] == "LineSegmentsMessage")  # fmt: skip
    assert "props" in loops  # the segments travel as a binary buffer beside the message
    markdown = [m for m in messages if isinstance(m, dict) and m.get("type") == "GuiMarkdownMessage"]
    text = " ".join(str(m) for m in markdown)
    assert "80 keyframes" in text and "40 in the graph" in text


def test_a_port_taken_is_one_error_naming_it() -> None:
    from ssmvpr_slam.app.live_view import LiveView, LiveViewError

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        try:
            view = LiveView(port=port)
        except LiveViewError as exc:
            assert str(port) in str(exc)
        else:  # viser moved on to the next free port itself: the view says where it is
            assert view.port != port and str(view.port) in view.url
            view.close()


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _chromium_or_skip() -> str:
    if CHROMIUM is None:
        message = "no Chromium on this machine (apt-get install chromium); .ci/run installs it"
        if os.environ.get("SSMVPR_REQUIRE_BROWSER") == "1":
            pytest.fail(message)
        pytest.skip(message)
    return CHROMIUM


def _served_port(port: int, runner: threading.Thread, wait_s: float = 180.0) -> int:
    """The port the run's view answers HTTP on: `port`, or one of the next few when viser moved on
    because `port` was taken. The server starts once the backbone is loaded, so this polls; a run
    that ends first fails here with its output (a plain socket probe, so a slow browser cannot make
    the run outlast the wait)."""
    import urllib.request

    deadline = time.monotonic() + wait_s
    while True:
        for candidate in range(port, port + 4):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{candidate}", timeout=2):
                    return candidate
            except OSError:
                continue
        assert runner.is_alive() and time.monotonic() < deadline, (
            "the run ended (or timed out) before its view answered"
        )
        time.sleep(0.2)


@pytest.mark.slow
def test_run_viewer_serves_a_page_a_browser_draws(tmp_path: Path, weights_path: Path) -> None:
    """`run --viewer` on a short simulated log (two laps of a small block): the run's page,
    opened by the system's Chromium while the run's view is up, shows the drawn scene (a
    screenshot with the trajectory's and the loops' colours) and the panel's counts."""
    chromium = _chromium_or_skip()
    from playwright.sync_api import sync_playwright

    small = small_camera_log(
        tmp_path, "detector: {pca_warmup_keyframes: 10, exclusion_keyframes: 5, exclusion_distance: 0.0}\n"
        "results: {plots: false}\n", "two_laps", frame_rate_hz=2.0, city={"block_size_m": 10.0},
        route={"preset": "block_grid", "laps": 2}, max_frames=40,
    )  # fmt: skip
    log, config = small.log, small.config
    port = free_port()
    done: dict[str, Any] = {}

    def run() -> None:
        done["result"] = invoke("run", log, "-c", config, "--weights", weights_path, "--out", tmp_path / "out",
                                "--viewer", "--viewer-port", str(port), "--realtime", "--rate", "1")  # fmt: skip

    runner = threading.Thread(target=run)
    runner.start()
    shot = tmp_path / "view.png"
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=chromium,
            args=["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--disable-background-networking", "--disable-component-update", "--no-first-run"],
        )  # fmt: skip
        page = browser.new_page(viewport={"width": 1000, "height": 700})
        served = _served_port(port, runner)
        # the page's scripts load slowly on a busy machine: wait for the answer, not for every asset
        page.goto(f"http://127.0.0.1:{served}", wait_until="commit", timeout=120000)
        page.wait_for_selector("text=keyframes", timeout=60000)
        time.sleep(5)  # a few keyframes more, drawn
        page.screenshot(path=str(shot))
        text = page.inner_text("body")
        browser.close()
    runner.join(timeout=300)
    result = done["result"]
    assert result.exit_code == 0, result.output
    assert f"http://127.0.0.1:{served}" in result.output  # the run says where its view really is
    assert "keyframes" in text and "loops:" in text
    image = cv2.imread(str(shot))
    assert image is not None and image.shape[:2] == (700, 1000)
    # the odometry's grey and the estimate's blue lines are on the page (not a blank canvas)
    b, g, r = (image[..., i].astype(int) for i in range(3))
    blue = (b > 150) & (r < 90) & (g > 60) & (g < 150)
    assert blue.sum() > 50, "no trajectory drawn"
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["keyframes"] > 10
