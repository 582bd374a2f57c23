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
import torch
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
    """A small detector (8-dimensional PCA fitted on the first 20 frames) on 64 px inputs, its
    cubes cut to keep the layout 128 px gave with the default cubes (one stage-I cube, a 7 x 7
    stage-II grid) for a quarter of the backbone's work."""
    config = tmp_path / "small.yaml"
    config.write_text(
        "detector: {pca_warmup_keyframes: 20, exclusion_keyframes: 5, exclusion_distance: 0.0,\n"
        "           calibrated: {min_history: 5}}\n"
        "vpr: {backbone: {input_size: 64}, filtering: {cubes: {cube_size: 4, stride: 2}, pca: {dim: 8}},\n"
        "     spatial: {cubes: {cube_size: 2, stride: 1}, pca: {dim: 8}}}\n"
    )
    return config


def test_one_sequence_with_a_loop_matrix(tmp_path: Path, images: Path, seeded_random_backbone_passes: object) -> None:
    matrix = np.zeros((50, 50), np.uint8)
    matrix[40, 12] = matrix[41, 13] = 1
    np.save(tmp_path / "gt.npy", matrix)
    torch.manual_seed(0)  # the weights of the next test too: it finds these images' passes
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


def test_one_sequence_with_poses(tmp_path: Path, images: Path, seeded_random_backbone_passes: object) -> None:
    # 25 frames around a 25 m loop driven twice: frame q revisits q - 25
    angle = np.arange(50) * 2 * np.pi / 25
    lines = [f"{i} {4 * np.cos(a):.4f} {4 * np.sin(a):.4f} 0 0 0 0 1" for i, a in enumerate(angle)]
    (tmp_path / "gt.tum").write_text("\n".join(lines) + "\n")
    torch.manual_seed(0)
    result = invoke("loop-eval", images, "--gt-poses", tmp_path / "gt.tum", "--radius", "0.5",
                    "-c", small_config(tmp_path), "--out", tmp_path / "out", *SMALL)  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["loops"]["with_truth"] == 25 and metrics["inputs"]["radius_m"] == 0.5


def test_a_similarity_matrix_is_one_error_line_unless_a_threshold_is_given(
    tmp_path: Path, images: Path, seeded_random_backbone_passes: object
) -> None:
    """Before: a matrix of similarities (0.05 .. 0.95) was read as 0/1, every pair a loop, and
    the run's recall was that of a detector asked to find every frame."""
    matrix = np.random.default_rng(1).uniform(0.05, 0.5, (50, 50))
    matrix[40, 12] = matrix[41, 13] = 0.95
    np.save(tmp_path / "sim.npy", matrix)
    args = ["loop-eval", images, "--gt-matrix", tmp_path / "sim.npy", "-c", small_config(tmp_path), *SMALL]
    line = assert_user_error(invoke(*args, "--out", tmp_path / "refused"), f"{tmp_path / 'sim.npy'}: 2,500 values "
                             f"between {matrix.min():.4g} and 0.95, not 0/1", "--gt-threshold")  # fmt: skip
    assert len(line) < 300 and not (tmp_path / "refused").exists()
    torch.manual_seed(0)
    result = invoke(*args, "--gt-threshold", "0.9", "--out", tmp_path / "out")
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "out" / "latest" / "metrics.json").read_text())
    assert metrics["loops"]["with_truth"] == 2 and metrics["inputs"]["gt_threshold"] == 0.9


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
    assert_user_error(invoke("loop-eval", images, "--gt-poses", tmp_path / "gt.tum", "--gt-threshold", "0.5", *out),
                      "--gt-threshold reads a --gt-matrix")  # fmt: skip
    assert_user_error(
        invoke("loop-eval", images, images, "--rear", images, *out), "one rear-camera folder per sequence"
    )
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two laps of a 10 m block grid with a rear camera, ground truth, no LiDAR: the second lap
    revisits the first."""
    from frontend.simulation.config import SimulationConfig
    from frontend.simulation.simulator import TraverseSimulator
    from frontend.sources import write_frames

    sim = SimulationConfig(frame_rate_hz=2.0, city={"block_size_m": 10.0}, route={"preset": "block_grid", "laps": 2},
                           max_frames=50, lidar={"enabled": False}, camera={"width": 64, "height": 48})  # fmt: skip
    log = tmp_path_factory.mktemp("log") / "sim.mcap"
    write_frames(TraverseSimulator(sim).frames(), log)
    return log


def test_a_log_is_one_sequence_judged_by_its_own_ground_truth(
    tmp_path: Path, sim_log: Path, seeded_random_backbone_passes: object
) -> None:
    """An MCAP (and the same log as a ROS 1 bag): keyframes every metre of the true path, the
    rear camera streamed, revisits within --radius; the bag gives the very same decisions (its
    images, byte for byte the MCAP's, find the MCAP run's backbone passes: an image the bag
    decoded otherwise would be encoded afresh)."""
    from tool_module import load_tool

    mcap_to_rosbag = load_tool("mcap_to_rosbag").mcap_to_rosbag

    runs = {}
    bag = mcap_to_rosbag(sim_log, tmp_path / "sim.bag", "ros1")
    for name, log in (("mcap", sim_log), ("bag", bag)):
        out = tmp_path / name
        torch.manual_seed(0)  # the same random weights for both
        result = invoke("loop-eval", log, "--radius", "3", "-c", small_config(tmp_path), "--out", out, *SMALL)
        assert result.exit_code == 0, result.output
        metrics = json.loads((out / "latest" / "metrics.json").read_text())
        rows = list(csv.DictReader((out / "latest" / "loops.csv").open()))
        runs[name] = (metrics, rows)
    metrics, rows = runs["mcap"]
    assert metrics["inputs"]["ground_truth"] == "the log's ground-truth poses" and metrics["inputs"]["radius_m"] == 3
    assert 30 <= metrics["loops"]["frames"] <= 50 and metrics["loops"]["with_truth"] >= 3  # lap 2 begins revisits
    assert rows and all(r["image"].startswith("sim.mcap#") for r in rows)
    from ssmvpr_slam.config.slam import load_config
    from ssmvpr_slam.loop_eval.log_frames import images_of_log, keyframes_of

    config = load_config(str(small_config(tmp_path)))
    keyframes = keyframes_of(sim_log, config)
    assert keyframes.has_rear and len(keyframes.frame_indices) == metrics["loops"]["frames"]
    first, rear = next(images_of_log(keyframes, config))
    assert first.shape == rear.shape == (48, 64, 3)  # the log's rear camera is streamed too
    assert runs["bag"][0]["loops"] == metrics["loops"]
    assert [{k: v for k, v in r.items() if "image" not in k} for r in runs["bag"][1]] == [
        {k: v for k, v in r.items() if "image" not in k} for r in rows
    ]


def test_a_log_without_ground_truth_or_with_folder_options_is_refused(tmp_path: Path, sim_log: Path) -> None:
    from frontend.sources import McapSource, write_frames

    blind = tmp_path / "blind.mcap"
    frames = []
    for frame in McapSource(sim_log):
        frame.gt_pose = None
        frames.append(frame)
    write_frames(iter(frames), blind)
    assert_user_error(invoke("loop-eval", blind, *SMALL), str(blind), "no ground-truth poses")
    assert_user_error(
        invoke("loop-eval", sim_log, "--gt-poses", tmp_path / "p.txt", *SMALL), "--gt-poses is for image folders"
    )
