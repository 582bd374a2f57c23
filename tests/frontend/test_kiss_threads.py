"""kiss-icp caps its threads once per process, at its first registration (see
frontend/odometry/kiss_threads.py): a later, different setting is reported, not silently dropped."""

from __future__ import annotations

import logging
import os

import pytest

from frontend.config import KissIcpConfig
from frontend.odometry import kiss_threads
from frontend.odometry.kiss_icp import KissIcpOdometry
from frontend.odometry.kiss_threads import claim_kiss_icp_threads, thread_cap
from ssmvpr_slam.backend.config import LidarRegistrationConfig
from ssmvpr_slam.backend.icp import SeededIcp


@pytest.fixture
def fresh_process(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kiss_threads, "_first", None)


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_the_first_claim_sets_the_cap_and_a_different_one_is_reported(
    fresh_process: None, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        assert claim_kiss_icp_threads(1, "first.setting") == 1
        assert claim_kiss_icp_threads(1, "same.value") == 1
        assert _warnings(caplog) == []
        assert claim_kiss_icp_threads(2, "other.setting") == 1  # asks for two, and gets one
    [warning] = _warnings(caplog)
    assert "other.setting=2 has no effect" in warning and "1 thread(s)" in warning and "first.setting" in warning


def test_all_cores_spelled_three_ways_is_the_same_cap(fresh_process: None, caplog: pytest.LogCaptureFixture) -> None:
    cores = len(os.sched_getaffinity(0))  # the CPUs this process may use, as TBB counts them
    with caplog.at_level(logging.WARNING):
        assert claim_kiss_icp_threads(0, "a") == thread_cap(0) == cores
        assert claim_kiss_icp_threads(cores, "b") == cores
        assert claim_kiss_icp_threads(cores + 4, "c") == cores  # more than the cores: TBB runs no more
    assert _warnings(caplog) == []


def test_odometry_then_loop_registration_with_other_caps_is_reported(
    fresh_process: None, caplog: pytest.LogCaptureFixture
) -> None:
    """As a sequential run builds them: kiss-icp odometry first, then the loop registration. The
    odometry asks for every core, the default, so that if this test were the first to build a
    registration in the test process it would cap later tests as they would be anyway."""
    if thread_cap(0) == 1:
        pytest.skip("one core: every cap is the same")
    with caplog.at_level(logging.WARNING):
        KissIcpOdometry(KissIcpConfig(max_num_threads=0))
        SeededIcp(LidarRegistrationConfig(max_num_threads=1))
    [warning] = _warnings(caplog)
    assert warning.startswith("backend.registration.lidar.max_num_threads=1 has no effect")
    assert "frontend.odometry.kiss_icp.max_num_threads" in warning
