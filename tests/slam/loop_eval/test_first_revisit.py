"""Loops from the first revisit, at default settings: real short streams (the shared Gardens Point
half cut short, day then night), a simulated traverse whose first revisit comes as early as the
exclusion window allows, streams of look-alikes with no revisit, and streams too short to
decide anything, through `loop-eval` with the real ImageNet VGG16 weights.

The earlier start-up (40 keyframes of PCA warm-up, then 40 runner-ups before the first
decision, sequences zero-filled at a seam) is run on the same streams as a control: it accepts
nothing there, so these tests tell the two apart."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401

pytestmark = pytest.mark.slow

# the start-up before loops came from the first revisit, as a control
BLIND_START = """
detector:
  pca_warmup_keyframes: 40
  sequence: {length: 8, direction: forward, sequence_candidates: 20, missing: zero}
  calibrated: {min_history: 40, prior_runner_ups: 0, min_field: 1}
"""


def cut(source: Path, target: Path, first: int, count: int) -> Path:
    """`count` images of `source` from the `first`-th on, linked into `target`."""
    target.mkdir(parents=True)
    for path in sorted(source.iterdir())[first : first + count]:
        (target / path.name).symlink_to(path)
    return target


def loop_eval(*args: object, out: Path, config: Path | None = None) -> tuple[dict, str]:
    extra = ["-c", config] if config is not None else []
    result = invoke("loop-eval", *args, *extra, "--device", "cpu", "--out", out)
    assert result.exit_code == 0, result.output
    return json.loads((out / "latest" / "metrics.json").read_text()), result.output


@pytest.fixture(scope="module")
def gardens_half(shared_dir: Path) -> Path:
    return shared_dir / "data" / "gardens_point_half"


@pytest.fixture(scope="module")
def blind_start(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("config") / "blind_start.yaml"
    path.write_text(BLIND_START)
    return path


def test_a_revisit_at_keyframe_20_gets_right_loops_and_no_wrong_one(
    tmp_path: Path, gardens_half: Path, weights_path: Path, blind_start: Path, shared_backbone_passes: object
) -> None:
    """20 frames by day, then the same 20 by night: the night pass starts at keyframe 20."""
    day = cut(gardens_half / "day_right", tmp_path / "day", 0, 20)
    night = cut(gardens_half / "night_right", tmp_path / "night", 0, 20)
    metrics, _ = loop_eval(day, night, "--weights", weights_path, out=tmp_path / "now")
    loops = metrics["loops"]
    assert loops["with_truth"] == 20 and loops["accepted"] >= 10
    assert loops["precision"] == 1.0 and loops["recall"] >= 0.5
    assert metrics["keyframes_judged"] > 0 and metrics["too_short_to_decide"] is None
    rows = (tmp_path / "now" / "latest" / "loops.csv").read_text().splitlines()[1:]
    first_accepted = min(int(r.split(",")[0]) for r in rows if r.split(",")[11] == "1")
    assert first_accepted <= 24  # within the night pass's first five keyframes

    control, output = loop_eval(day, night, "--weights", weights_path, out=tmp_path / "blind", config=blind_start)
    assert control["loops"]["accepted"] == 0
    assert control["too_short_to_decide"] is not None and "too short to decide" in output


def test_look_alikes_without_a_revisit_accept_nothing_from_the_first_keyframe_on(
    tmp_path: Path, gardens_half: Path, weights_path: Path, shared_backbone_passes: object
) -> None:
    """The same campus by day, then other paths of it by night: paving, railings and trees alike,
    no place of the day pass again. Every frame is judged, from the night pass's first on."""
    day = cut(gardens_half / "day_right", tmp_path / "day", 0, 30)
    night = cut(gardens_half / "night_right", tmp_path / "night", 50, 30)
    pairs = tmp_path / "no_revisit.npy"  # a VPR-Bench ground truth: no night frame has a day place
    np.save(pairs, np.array([[q, []] for q in range(30)], dtype=object), allow_pickle=True)
    metrics, _ = loop_eval(day, night, "--gt", pairs, "--weights", weights_path, out=tmp_path / "out")
    assert metrics["loops"]["with_truth"] == 0
    assert metrics["keyframes_judged"] >= 30  # decisions were made, and refused
    assert metrics["loops"]["accepted"] == 0


@pytest.fixture(scope="module")
def small_block_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The quick start's city with 20 m blocks, a frame every 7 m or so, no LiDAR: the route is
    back at its start after about 45 keyframes, the first revisit the exclusion window (30
    keyframes, 15 m) allows there."""
    from rich.console import Console

    from ssmvpr_slam.app.runner import simulate_to_mcap
    from ssmvpr_slam.config.slam import load_config

    config = load_config("quick", {"simulation": {"frame_rate_hz": 1.6, "max_frames": 60,
                                                  "city": {"block_size_m": 20.0}, "lidar": {"enabled": False}}})  # fmt: skip
    return simulate_to_mcap(config, tmp_path_factory.mktemp("log") / "small_block.mcap", Console(quiet=True))


def test_a_simulated_first_revisit_is_closed_within_five_keyframes(
    tmp_path: Path, small_block_log: Path, weights_path: Path, blind_start: Path, shared_backbone_passes: object
) -> None:
    metrics, _ = loop_eval(small_block_log, "--weights", weights_path, out=tmp_path / "now")
    loops = metrics["loops"]
    assert loops["precision"] == 1.0 and loops["with_truth"] >= 10
    rows = [r.split(",") for r in (tmp_path / "now" / "latest" / "loops.csv").read_text().splitlines()[1:]]
    first_revisit = min(int(r[0]) for r in rows if r[13] != "")  # the first frame with a true place
    first_accepted = min(int(r[0]) for r in rows if r[11] == "1")
    assert first_revisit <= 50
    assert first_accepted - first_revisit <= 5, (first_revisit, first_accepted)

    control, _ = loop_eval(small_block_log, "--weights", weights_path, out=tmp_path / "blind", config=blind_start)
    assert control["loops"]["accepted"] == 0


def test_a_stream_too_short_to_decide_says_so(
    tmp_path: Path, gardens_half: Path, weights_path: Path, shared_backbone_passes: object
) -> None:
    day = cut(gardens_half / "day_right", tmp_path / "day", 0, 3)
    night = cut(gardens_half / "night_right", tmp_path / "night", 0, 3)
    metrics, output = loop_eval(day, night, "--weights", weights_path, out=tmp_path / "out")
    assert metrics["keyframes_judged"] == 0 and metrics["loops"]["recall"] == 0.0
    assert "recognition never started" in metrics["too_short_to_decide"]
    assert "too short to decide any loop" in output and "says nothing about the detector" in output
