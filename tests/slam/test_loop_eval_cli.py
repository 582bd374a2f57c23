"""`loop-eval` through the command line: the one-sequence modes end to end on small synthetic
image folders (random weights: the mechanics, not recognition), and input errors as one line.
Real recognition on real data: test_loop_eval_corridor.py."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401


def folder(path: Path, n: int, seed: int = 0) -> Path:
    path.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        cv2.imwrite(str(path / f"{i:04d}.png"), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    return path


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return folder(tmp_path_factory.mktemp("seq") / "images", 50)


SMALL = ["--weights", "random", "--device", "cpu"]


def small_config(tmp_path: Path) -> Path:
    config = tmp_path / "small.yaml"
    config.write_text(
        "detector: {pca_warmup_keyframes: 20, exclusion_keyframes: 5, exclusion_distance: 0.0,\n"
        "           calibrated: {min_history: 5}}\n"
        "vpr: {backbone: {input_size: 128}, filtering: {pca: {dim: 8}}, spatial: {pca: {dim: 8}}}\n"
    )
    return config


def test_one_sequence_with_a_loop_matrix(tmp_path: Path, images: Path) -> None:
    matrix = np.zeros((50, 50), np.uint8)
    matrix[40, 12] = matrix[41, 13] = 1
    np.save(tmp_path / "gt.npy", matrix)
    result = invoke("loop-eval", images, "--gt-matrix", tmp_path / "gt.npy", "-c", small_config(tmp_path),
                    "--out", tmp_path / "out", *SMALL)  # fmt: skip
    assert result.exit_code == 0, result.output
    run = tmp_path / "out" / "latest"
    metrics = json.loads((run / "metrics.json").read_text())
    loops = metrics["loops"]
    assert (loops["frames"], loops["with_truth"]) == (50, 2)
    for key in ("precision", "recall", "max_recall_at_full_precision", "pr_auc", "accepted", "false_accepts"):
        assert key in loops
    assert "loops_across_passes" not in metrics and metrics["decision"] == "calibrated"
    rows = list(csv.DictReader((run / "loops.csv").open()))
    assert rows and all(int(r["match_frame"]) < int(r["frame"]) for r in rows)
    assert (run / "pr.png").stat().st_size > 0 and (run / "config.yaml").is_file()


def test_one_sequence_with_poses(tmp_path: Path, images: Path) -> None:
    # 25 frames around a 25 m loop driven twice: frame q revisits q - 25
    angle = np.arange(50) * 2 * np.pi / 25
    lines = [f"{i} {4 * np.cos(a):.4f} {4 * np.sin(a):.4f} 0 0 0 0 1" for i, a in enumerate(angle)]
    (tmp_path / "gt.tum").write_text("\n".join(lines) + "\n")
    result = invoke("loop-eval", images, "--gt-poses", tmp_path / "gt.tum", "--radius", "0.5",
                    "-c", small_config(tmp_path), "--out", tmp_path / "out", *SMALL)  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["loops"]["with_truth"] == 25 and metrics["inputs"]["radius_m"] == 0.5


def test_two_passes_report_the_decisions_across_passes_apart(tmp_path: Path) -> None:
    first, second = folder(tmp_path / "a", 30, 1), folder(tmp_path / "b", 30, 2)
    result = invoke("loop-eval", first, second, "-c", small_config(tmp_path), "--out", tmp_path / "out", *SMALL)
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["loops"]["with_truth"] == 30 and metrics["inputs"]["frames"] == [30, 30]
    assert set(metrics["loops"]["false_accepts_by_place"]) == {"within_pass", "across_passes"}
    assert metrics["loops_across_passes"]["with_truth"] == 30


@pytest.mark.parametrize(
    ("extra", "fragments"),
    [
        ([], ["one sequence needs its ground truth"]),
        (["--gt-matrix", "nowhere.npy"], ["nowhere.npy: no such ground-truth matrix file"]),
        (["--gt", "pairs.csv"], ["--gt pairs a second pass"]),
    ],
)
def test_one_sequence_input_errors(tmp_path: Path, images: Path, extra: list[str], fragments: list[str]) -> None:
    assert_user_error(invoke("loop-eval", images, *extra, "--out", tmp_path / "out", *SMALL), *fragments)
    assert not (tmp_path / "out").exists()


def test_other_input_errors(tmp_path: Path, images: Path) -> None:
    out = ["--out", tmp_path / "out", *SMALL]
    assert_user_error(invoke("loop-eval", images, images, "--gt-poses", "p.txt", *out), "--gt-poses and --gt-matrix")
    assert_user_error(invoke("loop-eval", images, tmp_path / "none", *out), "none: no such image folder")
    (tmp_path / "empty").mkdir()
    assert_user_error(invoke("loop-eval", images, tmp_path / "empty", *out), "no images", "empty")
    (tmp_path / "gt.tum").write_text("0 0 0 0 0 0 0 1\n")
    assert_user_error(invoke("loop-eval", images, "--gt-poses", tmp_path / "gt.tum", *out), "1 poses for 50 images")
    assert_user_error(invoke("loop-eval", images, images, "--spacing", "0", *out), "--spacing must be positive")
    assert_user_error(
        invoke("loop-eval", images, images, "--rear", images, *out), "one rear-camera folder per sequence"
    )
    assert not (tmp_path / "out").exists()
