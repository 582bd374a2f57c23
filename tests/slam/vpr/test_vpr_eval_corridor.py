"""`vpr-eval` end to end on the real Corridor benchmark with the real ImageNet VGG16 weights,
single frames and sequences of L = 1, 2, 3, 5 (forward) side by side."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ssmvpr_slam.cli import app


@pytest.fixture(scope="module")
def corridor_run(
    tmp_path_factory: pytest.TempPathFactory, corridor_dir: Path, weights_path: Path, shared_backbone_passes: object
) -> Path:
    out = tmp_path_factory.mktemp("vpr_eval")
    result = CliRunner().invoke(app, [
        "vpr-eval", str(corridor_dir / "ref"), str(corridor_dir / "query"),
        "--weights", str(weights_path), "--device", "cpu", "--out", str(out),
        "--sequence", "1", "--sequence", "2", "--sequence", "3", "--sequence", "5",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    return out / "latest"


def test_outputs_are_written(corridor_run: Path) -> None:
    for name in (
        "metrics.json",
        "matches.csv",
        "config.yaml",
        "pr_tolerances.png",
        "pr_stages.png",
        "recall_at_n.png",
        "pr_sequence.png",
    ):
        assert (corridor_run / name).stat().st_size > 0, name
    assert (corridor_run / "database" / "manifest.json").is_file()
    rows = list(csv.DictReader((corridor_run / "matches.csv").open()))
    assert len(rows) == 111
    assert all(0 <= int(r["ref_index"]) < 111 for r in rows)


def test_recognition_far_above_chance(corridor_run: Path) -> None:
    metrics = json.loads((corridor_run / "metrics.json").read_text())
    chance = 5 / 111  # a random reference lands within ±2 frames about 4.5% of the time
    assert metrics["top1_accuracy_stage2"] > 10 * chance  # measured 0.84
    assert metrics["top1_accuracy_stage1"] > 10 * chance  # measured 0.87
    assert metrics["pr_auc"] > 0.6  # measured 0.78
    assert metrics["filtering_recall_at_n"]["50"] >= 0.95  # the paper's filtering claim at N=50
    assert metrics["bytes_per_place"] < 175_000  # the paper's 25 kB + 150 kB per image


def test_matches_agree_with_metrics(corridor_run: Path) -> None:
    metrics = json.loads((corridor_run / "metrics.json").read_text())
    rows = list(csv.DictReader((corridor_run / "matches.csv").open()))
    correct = sum(int(r["correct"]) for r in rows)
    assert correct / len(rows) == pytest.approx(metrics["top1_accuracy_stage2"])
    for r in rows:  # `correct` means within ±2 of the query index (frame-aligned ground truth)
        assert int(r["correct"]) == int(abs(int(r["ref_index"]) - int(r["query_index"])) <= 2)


def test_sequences_are_never_worse_than_single_frames(corridor_run: Path) -> None:
    metrics = json.loads((corridor_run / "metrics.json").read_text())
    single = metrics["single_frame"]["pr_auc"]
    assert single == metrics["pr_auc"]  # measured 0.780
    sequence = metrics["sequence"]
    assert set(sequence) == {"1", "2", "3", "5"}
    assert sequence["1"]["pr_auc"] == single  # L = 1 is single-frame recognition
    assert sequence["1"]["top1_accuracy"] == metrics["top1_accuracy_stage2"]
    for length in ("2", "3", "5"):  # measured 0.841, 0.872, 0.948
        assert sequence[length]["direction"] == "forward"
        assert sequence[length]["pr_auc"] >= single, (length, sequence[length]["pr_auc"], single)
        assert sequence[length]["pr_auc_minus_single_frame"] == pytest.approx(sequence[length]["pr_auc"] - single)
        assert sequence[length]["top1_accuracy"] >= metrics["top1_accuracy_stage2"]
    assert sequence["5"]["pr_auc"] >= 0.9


def test_sequence_columns_agree_with_metrics(corridor_run: Path) -> None:
    metrics = json.loads((corridor_run / "metrics.json").read_text())
    rows = list(csv.DictReader((corridor_run / "matches.csv").open()))
    for length in ("2", "3", "5"):
        correct = sum(int(r[f"seq{length}_correct"]) for r in rows)
        assert correct / len(rows) == pytest.approx(metrics["sequence"][length]["top1_accuracy"])
        # start-up: query q has at most q + 1 terms; later nearly all L exist (not at place 0)
        terms = [int(r[f"seq{length}_terms"]) for r in rows]
        assert all(t <= min(q + 1, int(length)) for q, t in enumerate(terms))
        assert sum(t == int(length) for t in terms) >= len(rows) - 2 * int(length)
    assert all(r["seq1_ref_index"] == r["ref_index"] for r in rows)
