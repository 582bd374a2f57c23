"""`vpr-eval --gt`: a ground-truth file that lists windows gets its tolerance on top, said out loud.

Corridor's ground_truth_new.npy lists q-2..q+2 for query q; the default ±2 on top counted ±4
(PR-AUC 0.889 instead of the paper protocol's 0.780) while metrics.json said "tolerance": 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401

from loopclosure.benchmark_truth import GroundTruth, frame_aligned, load_ground_truth, truth_windows
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.vpr.evaluate import QueryOutcome, compute_metrics, window_warning, windows_record

N = 10
FILES = [f"{i}.jpg" for i in range(N)]


def _save_rows(path: Path, sets: list[list[int]]) -> Path:
    rows = np.empty((len(sets), 2), dtype=object)
    for q, refs in enumerate(sets):
        rows[q] = [q, refs]
    np.save(path, rows, allow_pickle=True)
    return path


def _windows_npy(path: Path, half: int = 1) -> Path:
    """VPR-Bench style: query q lists q-half..q+half (clipped), as Corridor's file does with half=2."""
    return _save_rows(path, [list(range(max(0, q - half), min(N - 1, q + half) + 1)) for q in range(N)])


def _windowed(tmp_path: Path) -> GroundTruth:
    return load_ground_truth(_windows_npy(tmp_path / "gt.npy"), FILES, FILES)


def test_ground_truth_windows_found_in_a_synthetic_npy(tmp_path: Path) -> None:
    windows = truth_windows(_windowed(tmp_path))
    assert windows.windowed and (windows.queries, windows.with_truth, windows.median_refs) == (10, 10, 3.0)


def test_ground_truth_without_windows_is_not_windowed(tmp_path: Path) -> None:
    assert not truth_windows(frame_aligned(FILES, FILES)).windowed
    scattered = load_ground_truth(_save_rows(tmp_path / "s.npy", [[q, (q + 5) % N] for q in range(N)]), FILES, FILES)
    assert not truth_windows(scattered).windowed  # several references per query, but no run of neighbours
    assert window_warning(scattered, 2) is None and windows_record(scattered, 2) is None


def test_ground_truth_windows_warning_names_file_and_the_way_out(tmp_path: Path) -> None:
    gt = _windowed(tmp_path)
    warning = window_warning(gt, 2)
    assert warning is not None and "\n" not in warning
    assert str(tmp_path / "gt.npy") in warning
    assert "10 of 10 queries, median 3 references" in warning
    assert "widens each window by ±2 frames" in warning and "--tolerance 0 uses the file as it is" in warning
    assert window_warning(gt, 0) is None  # the file as it is: nothing to warn about


def test_ground_truth_windows_recorded_in_vpr_eval_metrics(tmp_path: Path) -> None:
    gt = _windowed(tmp_path)
    config = load_config(None)
    match = np.minimum(np.arange(N) + 2, N - 1)  # two frames off: only the tolerance on top makes it right
    outcome = QueryOutcome(match, np.ones(N, np.float32), match, np.linspace(1, 0.5, N).astype(np.float32),
                           np.tile(np.arange(5), (N, 1)), np.zeros(N))  # fmt: skip
    widened = compute_metrics(outcome, gt, config)
    assert widened["tolerance"] == 2
    assert widened["ground_truth_windows"] == {"queries": 10, "of": 10, "median_refs": 3.0, "widened_by": 2}
    assert widened["top1_accuracy_stage2"] == 1.0
    config.vpr_eval.tolerance = 0
    as_listed = compute_metrics(outcome, gt, config)
    assert as_listed["ground_truth_windows"]["widened_by"] == 0 and as_listed["top1_accuracy_stage2"] < 1.0
    config.vpr_eval.tolerance = 2
    aligned = compute_metrics(outcome, frame_aligned(FILES, FILES), config)
    assert aligned["tolerance"] == 2 and aligned["ground_truth_windows"] is None


def test_ground_truth_windows_of_the_corridor_file(corridor_dir: Path) -> None:
    files = sorted((corridor_dir / "ref").glob("*.jpg"))
    gt = load_ground_truth(corridor_dir / "ground_truth_new.npy", files, files)
    assert windows_record(gt, 2) == {"queries": 111, "of": 111, "median_refs": 5.0, "widened_by": 2}


@pytest.mark.slow
def test_vpr_eval_warns_once_for_ground_truth_windows(tmp_path: Path, gardens_dir: Path, weights_path: Path) -> None:
    """End to end on the 10-place Gardens Point subset (about 10 s of encoding on 2 cores)."""
    gt = _windows_npy(tmp_path / "gt.npy")
    result = invoke("vpr-eval", gardens_dir / "ref", gardens_dir / "query", "--gt", gt, "--weights", weights_path,
                    "--device", "cpu", "--out", tmp_path / "out")  # fmt: skip
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.output.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "--tolerance 0 uses the file as it is" in warnings[0], result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["tolerance"] == 2 and metrics["ground_truth_windows"]["widened_by"] == 2
