"""`run --realtime`: frames at their recorded rate, keyframes that come too late handled by
odometry alone, the lag and what was skipped reported. The clock is faked where the rule is
checked (deterministic); the command runs for real on a short simulated log."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401
from small_logs import EVERY_FRAME, small_camera_log

from frontend.frame import Frame
from ssmvpr_slam.app.pipeline import SlamPipeline
from ssmvpr_slam.app.realtime import SensorClock
from ssmvpr_slam.run_state import KeyframeInput, RunState


class FakeTime:
    def __init__(self) -> None:
        self.now = 100.0
        self.slept: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.now += seconds


def frame(index: int, stamp: float) -> Frame:
    return Frame(index=index, timestamp=stamp, image=np.zeros((4, 4, 3), np.uint8))


def test_frames_are_given_no_earlier_than_their_recorded_time() -> None:
    time = FakeTime()
    clock = SensorClock(2.0, 1.0, time.clock, time.sleep)  # twice the recorded rate
    stamps = [10.0, 10.2, 10.4, math.nan, 10.3, 11.0]
    given = []
    for _ in clock.paced(frame(i, t) for i, t in enumerate(stamps)):
        given.append(round(time.now - 100.0, 6))
    # due at (t - 10) / 2; a frame without a timestamp, or one earlier than the last, with the last
    assert given == [0.0, 0.1, 0.2, 0.2, 0.2, 0.5]


def test_a_late_keyframe_is_behind_and_the_stats_count_it() -> None:
    time = FakeTime()
    clock = SensorClock(1.0, 0.5, time.clock, time.sleep)
    frames = clock.paced(frame(i, 0.1 * i) for i in range(3))
    next(frames)  # frame 0 due at 100.0
    time.now += 0.3
    assert not clock.behind(0)
    clock.done(0, skipped=False)
    next(frames)  # frame 1 was due at 100.1: given at once
    time.now += 0.6  # 0.8 s after it was due
    assert clock.behind(1)
    clock.done(1, skipped=True)
    stats = clock.stats()
    assert (stats.keyframes, stats.keyframes_skipped, stats.kept_up) == (2, 1, False)
    assert stats.lag_max_s == pytest.approx(0.8) and stats.lag_median_s == pytest.approx(0.55)
    assert stats.to_dict()["kept_up"] is False


def test_the_source_thread_adds_frames_while_the_back_end_takes_them() -> None:
    """With the stages overlapped the source's thread paces frames while the back end's marks
    keyframes done: neither may see the other's frames half added (a dict changed while it was
    walked). Many frames, no waiting, so the two threads interleave at every step."""
    import threading

    clock = SensorClock(1e9, 1.0, lambda: 0.0, lambda _s: None)
    count = 50_000
    stamps = (frame(i, float(i)) for i in range(count))
    taken = threading.Event()
    errors: list[BaseException] = []

    def source() -> None:
        try:
            for _ in clock.paced(stamps):
                pass
        except BaseException as exc:  # noqa: BLE001  # reported below
            errors.append(exc)
        taken.set()

    thread = threading.Thread(target=source)
    thread.start()
    index = 0
    while not taken.is_set():
        clock.done(index, skipped=False)  # every 2nd frame a keyframe: the one before is dropped
        index = (index + 2) % count
    thread.join(30)
    assert not errors


@pytest.mark.parametrize("rate, lag", [(0.0, 1.0), (math.inf, 1.0), (1.0, -1.0), (1.0, math.nan)])
def test_a_rate_or_lag_bound_that_means_nothing_is_refused(rate: float, lag: float) -> None:
    with pytest.raises(ValueError):
        SensorClock(rate, lag)


class StubSystem:
    """What the pipeline calls, a keyframe per frame; `back` takes `cost` seconds of fake time
    with recognition and a tenth of it without."""

    def __init__(self, time: FakeTime, cost: float) -> None:
        self.config = SimpleNamespace(pipeline=SimpleNamespace(overlapped=False, release_heap_every_keyframes=0))
        self.state = RunState()
        self.time, self.cost = time, cost
        self.recognised: list[bool] = []

    def front(self, f: Frame) -> KeyframeInput:
        keyframe = SimpleNamespace(id=f.index, frame_index=f.index)
        return KeyframeInput(keyframe, f.image, None, f.index + 1, {}, 0.0)  # type: ignore[arg-type]

    def sync_front_counts(self) -> None:
        pass

    def back(self, item: KeyframeInput, recognise: bool = True) -> None:
        self.recognised.append(recognise)
        self.state.keyframes.append(item.keyframe)  # type: ignore[arg-type]
        self.time.now += self.cost if recognise else self.cost / 10


@pytest.mark.parametrize("cost, skipped", [(0.15, 0), (0.3, 6)])
def test_the_pipeline_skips_recognition_while_behind_and_catches_up(cost: float, skipped: int) -> None:
    """Frames every 0.2 s: a back end of 0.15 s keeps pace; one of 0.3 s falls behind, skips
    recognition once a keyframe is more than 0.5 s late, catches up and recognises again."""
    time = FakeTime()
    system = StubSystem(time, cost)
    pipeline = SlamPipeline(system)  # type: ignore[arg-type]
    pipeline.clock = SensorClock(1.0, 0.5, time.clock, time.sleep)
    pipeline.run(frame(i, 0.2 * i) for i in range(20))
    stats = pipeline.clock.stats()
    assert stats.keyframes == 20 and stats.keyframes_skipped == skipped == system.recognised.count(False)
    if skipped:
        assert system.recognised[:3] == [True, True, True]  # late, but not yet beyond the bound
        assert True in system.recognised[system.recognised.index(False) :]  # caught up, recognising again
        assert stats.lag_max_s <= 0.5 + cost  # the lag stays bounded
    else:
        assert stats.kept_up and stats.lag_max_s == pytest.approx(cost)


class StubDetector:
    """Encodes ahead what it is given, failing on one keyframe."""

    def __init__(self, fail_on: int) -> None:
        self.fail_on, self.encoded = fail_on, []

    def encode_ahead(self, image: np.ndarray, keyframe_id: int, rear_image: np.ndarray | None) -> str:
        self.encoded.append(keyframe_id)
        if keyframe_id in (self.fail_on, self.fail_on + 1):
            raise RuntimeError(f"no codes for {keyframe_id}")
        return f"codes {keyframe_id}"


def test_the_encoder_leaves_out_keyframes_already_too_late_and_tells_a_failure_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """In real time a keyframe already later than the bound when the encoder's thread takes it
    will skip recognition: no backbone pass is spent on it, or a run that fell behind could not
    catch up. One that fails to encode goes on without codes (the back end encodes it, and fails
    there in its turn), said once."""
    time = FakeTime()
    system = StubSystem(time, 0.0)
    system.detector = StubDetector(fail_on=4)  # type: ignore[attr-defined]
    pipeline = SlamPipeline(system)  # type: ignore[arg-type]
    clock = pipeline.clock = SensorClock(1.0, 0.5, time.clock, time.sleep)
    frames = list(clock.paced(frame(i, 0.2 * i) for i in range(7)))  # now: frame 6 due, 1.2 s in
    items = [system.front(f) for f in frames]
    with caplog.at_level("WARNING", logger="ssmvpr_slam.app.pipeline"):
        out = list(pipeline._encoded_ahead(iter(items)))
    assert system.detector.encoded == [4, 5, 6]  # type: ignore[attr-defined]  # 0-3 were due > 0.5 s ago
    assert [item.encoded for item in out] == [None] * 6 + ["codes 6"]
    told = [r.getMessage() for r in caplog.records]
    assert len(told) == 1 and "keyframe 4 could not be encoded ahead (RuntimeError: no codes for 4)" in told[0]


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """16 frames at 5 Hz of a simulated street, no LiDAR (logged odometry), and a config that
    makes every frame a keyframe and runs its backbone small."""
    settings = "detector: {pca_warmup_keyframes: 10}\nresults: {plots: false}\n" + EVERY_FRAME
    return small_camera_log(tmp_path_factory.mktemp("realtime"), settings, max_frames=16)


def _run(small_log: SimpleNamespace, out: Path, weights_path: Path, *options: str) -> tuple[dict, str]:
    result = invoke("run", small_log.log, "-c", small_log.config, "--weights", weights_path, "--out", out, *options)
    assert result.exit_code == 0, result.output
    return json.loads((out / "latest" / "metrics.json").read_text()), result.output


@pytest.mark.slow
def test_run_realtime_reports_its_pace_and_what_it_left_out(
    small_log: SimpleNamespace, weights_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    offline, _ = _run(small_log, tmp_path / "offline", weights_path)
    assert "realtime" not in offline
    # a lag bound no run can miss: it keeps up, and gives the offline run's keyframes and loops
    monkeypatch.setenv("SSMVPR_PIPELINE__REALTIME_MAX_LAG_S", "60")
    kept, output = _run(small_log, tmp_path / "kept", weights_path, "--realtime", "--rate", "4")
    live = kept["realtime"]
    assert live["rate"] == 4.0 and live["kept_up"] is True and live["keyframes_skipped"] == 0
    assert live["keyframes"] == kept["keyframes"] == offline["keyframes"]
    assert 0 <= live["lag_median_s"] <= live["lag_p99_s"] <= live["lag_max_s"] < 60
    assert kept["keyframes_judged"] == offline["keyframes_judged"]
    assert "real time x4: lag median / p99" in output and "fell behind" not in output
    # no lag allowed at all: every keyframe comes late and is handled by odometry alone, said so
    monkeypatch.setenv("SSMVPR_PIPELINE__REALTIME_MAX_LAG_S", "0")
    behind, output = _run(small_log, tmp_path / "behind", weights_path, "--realtime", "--rate", "100")
    live = behind["realtime"]
    assert live["kept_up"] is False and live["keyframes_skipped"] == live["keyframes"] == behind["keyframes"]
    assert "the run fell behind its log played at x100" in " ".join(output.split())
    assert behind["too_short_to_decide"] is not None  # nothing was recognised


def test_rate_without_realtime_is_refused(small_log: SimpleNamespace, tmp_path: Path) -> None:
    result = invoke("run", small_log.log, "--rate", "2", "--out", tmp_path)
    assert_user_error(result, "--rate", "--realtime")
