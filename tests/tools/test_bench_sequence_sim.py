"""tools/bench_sequence_sim.py's analysis, on codes of a made-up traverse (no backbone): two laps of a
circle whose second lap repeats the first lap's places; a rear camera that matches nothing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "bench_sequence_sim.py"
LAP = 70  # keyframes per lap, 2 m apart


def unit_rows(a: np.ndarray) -> np.ndarray:
    return (a / np.linalg.norm(a, axis=-1, keepdims=True)).astype(np.float32)


def traverse_codes(laps: float, circle: bool = True, seed: int = 0) -> dict[str, np.ndarray]:
    """Keyframe k shows lap place k % LAP: its codes are that place's plus noise."""
    rng = np.random.default_rng(seed)
    n = int(laps * LAP)
    places1 = rng.standard_normal((LAP, 16, 24))
    places2 = rng.standard_normal((LAP, 13, 13, 6))
    lap = np.arange(n) % LAP
    travelled = 2.0 * np.arange(n)
    gt = np.tile(np.eye(4), (n, 1, 1))
    if circle:
        angle = 2 * np.pi * lap / LAP
        radius = 2.0 * LAP / (2 * np.pi)
        gt[:, 0, 3], gt[:, 1, 3] = radius * np.cos(angle), radius * np.sin(angle)
    else:
        gt[:, 0, 3] = travelled
    return {
        "stage1": unit_rows(places1[lap] + 0.3 * rng.standard_normal((n, 16, 24))),
        "stage2": (places2[lap] + 0.3 * rng.standard_normal((n, 13, 13, 6))).astype(np.float16),
        "rear_stage1": unit_rows(rng.standard_normal((n, 16, 24))),
        "rear_stage2": rng.standard_normal((n, 13, 13, 6)).astype(np.float32),
        "travelled": travelled,
        "gt": gt,
        "warmup": np.array(40),
    }


def run(codes: dict[str, np.ndarray], folder: Path) -> subprocess.CompletedProcess:
    path = folder / "codes.npz"
    np.savez(path, **codes)
    cmd = [sys.executable, str(SCRIPT), "--codes", str(path), "--lengths", "1,3"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)


def test_second_lap_is_recalled_and_the_rear_camera_adds_nothing(tmp_path: Path) -> None:
    proc = run(traverse_codes(laps=2.3), tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["revisits"]["reverse"] == 0 and out["revisits"]["forward"] > 60
    for length in ("1", "3"):
        result = out["results"][length]
        decision = result["absolute_decision"]
        assert decision["precision"] == 1.0 and decision["recall_forward"] > 0.9
        calibrated = result["calibrated_decision"]
        assert calibrated["precision"] == 1.0 and calibrated["recall_forward"] > 0.8
        assert result["stream_pr_auc"] > 0.9
        sweep = result["absolute_accept_score_sweep"]
        assert sweep[f"{out['thresholds']['accept_score']:g}"] == decision  # the configured one is swept too
        # the rear codes are noise: its accepted loops, if any, only lower the precision
        both = result["absolute_decision_front_and_rear"]
        assert both["recall"] == decision["recall"]
        assert result["calibrated_decision_front_and_rear"]["recall"] == calibrated["recall"]
        assert result["rear"]["recall_at_precision_1"]["forward"] == 0.0
    assert out["single_frame"]["detector_decision_before"]["precision"] == 1.0


def test_a_traverse_without_revisits_is_one_line_not_a_traceback(tmp_path: Path) -> None:
    proc = run(traverse_codes(laps=2.3, circle=False), tmp_path)
    assert proc.returncode == 2
    assert "has no ground-truth revisit after the 40-keyframe warm-up" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_saved_codes_with_simulation_options_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "codes.npz"
    np.savez(path, **traverse_codes(laps=1.0))
    cmd = [sys.executable, str(SCRIPT), "--codes", str(path), "--frames", "10"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2 and "--codes replays saved codes" in proc.stderr
