"""`optimize --gt-edges`: a truth that lists none of the graph's loops is refused, not scored.

Vertigo's ring/groundTruth/edges.txt lists only the 433 odometry edges; taken as the truth it
called all 26 loops false and reported the odometry start as the bound, without a word."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401

from ssmvpr_slam.backend import g2o_io
from ssmvpr_slam.backend.g2o_io import PoseGraphFileError, read_pose_graph

TWELVE_GON = (
    [f"VERTEX_SE2 {k} 0 0 0" for k in range(12)]
    + [f"EDGE_SE2 {k} {k + 1} 1 0 0.5235987756 100 0 0 100 0 100" for k in range(11)]
    + ["EDGE_SE2 0 11 0.5 0.866025 5.759586531 100 0 0 100 0 100", "EDGE_SE2 2 8 0.1 0.1 0 100 0 0 100 0 100"]
)


def _ring(shared_dir: Path) -> Path:
    return shared_dir / "data" / "posegraphs" / "ring"


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def test_optimize_refuses_gt_edges_of_odometry_only(tmp_path: Path, shared_dir: Path) -> None:
    ring = _ring(shared_dir)
    edges = ring / "groundTruth" / "edges.txt"
    result = invoke("optimize", ring / "originalDataset" / "ring.g2o", "--gt", ring / "groundTruth" / "ring.g2o",
                    "--gt-edges", edges, "--out", tmp_path / "o")  # fmt: skip
    assert_user_error(
        result,
        f"--gt-edges {edges}: 433 edges, all odometry (i, i+1): none of the graph's 26 loop edges",
        "--gt-radius",
    )
    assert not (tmp_path / "o").exists()  # refused before the solve wrote anything


def test_optimize_refuses_gt_edges_listing_other_loops(tmp_path: Path) -> None:
    graph = _write(tmp_path / "g.g2o", TWELVE_GON)
    edges = _write(tmp_path / "edges.txt", [f"{k} {k + 1}" for k in range(11)] + ["3 9"])  # another graph's loop
    result = invoke("optimize", graph, "--gt-edges", edges, "--out", tmp_path / "o")
    assert_user_error(result, "12 edges, 1 of them loops: none of the graph's 2 loop edges")


def test_optimize_gt_edges_from_the_ground_truth_g2o(tmp_path: Path, shared_dir: Path) -> None:
    """The ground-truth graph as --gt-edges lists all 26 loops: none is false, the bound is the optimum."""
    ring = _ring(shared_dir)
    truth = ring / "groundTruth" / "ring.g2o"
    out = tmp_path / "o"
    result = invoke("optimize", ring / "originalDataset" / "ring.g2o", "--gt", truth, "--gt-edges", truth,
                    "--out", out)  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "latest-optimize" / "metrics.json").read_text())
    assert metrics["loop_classification"]["true_outliers"] == 0 and metrics["loop_classification"]["loops"] == 26
    assert metrics["ate_oracle"]["rmse"] == pytest.approx(metrics["ate"]["rmse"], rel=1e-3)
    assert metrics["ate_oracle"]["rmse"] < 0.5 * metrics["ate_initial"]["rmse"]  # not the odometry start


def test_check_loop_truth_accepts_a_partial_truth_and_a_loopless_graph(tmp_path: Path) -> None:
    graph = read_pose_graph(_write(tmp_path / "g.g2o", TWELVE_GON))
    partial = {(k, k + 1) for k in range(11)} | {(0, 11)}  # 2-8 left out: it is the false one
    g2o_io.check_loop_truth("edges.txt", partial, graph)
    chain = graph.with_edges(graph.odometry)
    g2o_io.check_loop_truth("edges.txt", {(0, 1)}, chain)  # no loop to classify, nothing to refuse
    with pytest.raises(PoseGraphFileError, match=r"^--gt-edges edges.txt: 11 edges, all odometry"):
        g2o_io.check_loop_truth("edges.txt", {(k, k + 1) for k in range(11)}, graph)


def test_check_loop_truth_accepts_the_manhattan_edge_ground_truth(shared_dir: Path) -> None:
    base = shared_dir / "data" / "posegraphs" / "manhattan"
    graph = read_pose_graph(base / "originalDataset" / "g2o" / "manhattanOlson3500.g2o")
    edges = base / "groundTruth" / "manhattanOlson3500_edges_groundTruth.dat"
    g2o_io.check_loop_truth(edges, g2o_io.read_edge_pairs(edges), graph)
