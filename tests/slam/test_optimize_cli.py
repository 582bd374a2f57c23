"""`ssmvpr-slam optimize`: outputs, evaluation, and one clear error line on malformed input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ssmvpr_common.trajectory_io import read_tum
from ssmvpr_slam.backend.g2o_io import planar_of, planar_pose, read_pose_graph
from ssmvpr_slam.cli import app


def invoke(*args: object):  # noqa: ANN201
    return CliRunner().invoke(app, [str(a) for a in args])


def test_optimize_ring_writes_outputs(tmp_path: Path, shared_dir: Path) -> None:
    base = shared_dir / "data" / "posegraphs" / "ring"
    times = tmp_path / "times.txt"
    times.write_text("".join(f"{0.1 * k:.1f}\n" for k in range(434)))
    out = tmp_path / "out"
    result = invoke("optimize", base / "originalDataset" / "ring.g2o", "--gt", base / "groundTruth" / "ring.g2o",
                    "--times", times, "--out", out)  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "latest-optimize" / "metrics.json").read_text())
    assert metrics["vertices"] == 434 and metrics["loop_candidates"] == 26 and metrics["loops_outlier"] == 0
    assert metrics["ate"]["rmse"] < 0.5 * metrics["ate_initial"]["rmse"]
    assert metrics["solver"] == "auto" and metrics["kernel_solve"] == "batch"  # the default, from stored vertices
    assert metrics["gnc"] is True and metrics["kernel"] == "dcs"
    assert metrics["check"] is True and metrics["check_removed"] == 0
    graph = read_pose_graph(out / "latest-optimize" / "optimised.g2o")
    assert graph.ids == tuple(range(434)) and len(graph.edges) == 459
    stamps, poses = read_tum(out / "latest-optimize" / "optimised.tum")
    assert len(poses) == 434 and stamps[1] == pytest.approx(0.1)
    np.testing.assert_allclose(poses[:, :3, 3], graph.poses[:, :3, 3], atol=1e-6)


@pytest.mark.parametrize("truth", ["edges", "radius"])
def test_optimize_reports_loop_classification(tmp_path: Path, truth: str) -> None:
    lines = [f"VERTEX_SE2 {k} 0 0 0" for k in range(12)]
    lines += [f"EDGE_SE2 {k} {k + 1} 1 0 0.5235987756 100 0 0 100 0 100" for k in range(11)]
    lines += ["EDGE_SE2 0 11 0.5 0.866025 5.759586531 100 0 0 100 0 100",  # true (12-gon closes)
              "EDGE_SE2 2 8 0.1 0.1 0 100 0 0 100 0 100"]  # false  # fmt: skip
    graph = tmp_path / "g.g2o"
    graph.write_text("\n".join(lines) + "\n")
    true_edges = tmp_path / "edges.txt"
    true_edges.write_text("".join(f"{k} {k + 1}\n" for k in range(11)) + "0 11\n")
    if truth == "radius":  # the 12-gon of 1 m sides: 0-11 are 1 m apart, 2-8 3.9 m
        step, pose, vertices = planar_pose(1.0, 0.0, np.pi / 6), np.eye(4), []
        for k in range(12):
            vertices.append("VERTEX_SE2 {} {} {} {}".format(k, *planar_of(pose)))
            pose = pose @ step
        (tmp_path / "gt.g2o").write_text("\n".join(vertices) + "\n")
        truth_args = ["--gt", tmp_path / "gt.g2o", "--gt-radius", 2.0]
    else:
        truth_args = ["--gt-edges", true_edges]
    result = invoke("optimize", graph, *truth_args, "--out", tmp_path / "o")
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "o" / "latest-optimize" / "metrics.json").read_text())
    assert metrics["initialised_from_odometry"] is True
    # from an odometry start both kernel solves run and the lower TLS objective is kept
    assert metrics["solver"] == "auto" and set(metrics["start_tls"]) == {"batch", "isam2"}
    assert metrics["start_tls"][metrics["kernel_solve"]] == min(metrics["start_tls"].values())
    assert metrics["loop_classification"]["outlier_precision"] == 1.0
    assert metrics["loop_classification"]["outlier_recall"] == 1.0
    assert metrics["outlier_loops"] == [[2, 8]]
    assert ("within 2.0 m" in metrics["loop_classification"]["truth"]) == (truth == "radius")
    if truth == "radius":  # the false loop rejected, the answer is the bound: least squares over the true ones
        assert metrics["ate_ratio_to_oracle"] == pytest.approx(1.0, abs=1e-4) and metrics["ate_oracle"]["rmse"] > 0.1


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        (["--gt-radius", "5"], "--gt-radius: needs --gt"),
        (["--gt", "g.g2o", "--gt-edges", "g.g2o", "--gt-radius", "5"], "replaces --gt-edges"),
        (["--gt", "g.g2o", "--gt-radius", "-1"], "expected metres > 0, got -1.0"),
    ],
)
def test_gt_radius_needs_ground_truth_and_a_positive_radius(tmp_path: Path, extra: list[str], fragment: str) -> None:
    graph = tmp_path / "g.g2o"
    graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    extra = [str(tmp_path / x) if x == "g.g2o" else x for x in extra]
    result = invoke("optimize", graph, *extra, "--out", tmp_path / "o")
    assert result.exit_code == 2 and fragment in result.stderr, result.output
    assert not (tmp_path / "o").exists()  # refused before any work


def test_from_odometry_ignores_a_bent_stored_estimate(tmp_path: Path) -> None:
    """A 12-gon whose stored vertices were bent (as by a false loop): --from-odometry chains the
    odometry from the file's first vertex instead, and reaches the 12-gon the consistent loop
    closes; with exact measurements the bound is exact too (no ratio to divide by zero)."""
    step, anchor = planar_pose(1.0, 0.0, np.pi / 6), planar_pose(100.0, 50.0, 0.3)
    chain = [anchor]
    for _ in range(11):
        chain.append(chain[-1] @ step)
    x, y, theta = planar_of(np.linalg.inv(chain[0]) @ chain[11])
    lines = ["VERTEX_SE2 0 100 50 0.3"] + [f"VERTEX_SE2 {k} {100 + k} {50 + 0.3 * k * k} 0" for k in range(1, 12)]
    lines += [f"EDGE_SE2 {k} {k + 1} 1 0 {np.pi / 6} 100 0 0 100 0 100" for k in range(11)]
    lines.append(f"EDGE_SE2 0 11 {x} {y} {theta} 100 0 0 100 0 100")
    graph = tmp_path / "bent.g2o"
    graph.write_text("\n".join(lines) + "\n")
    truth = tmp_path / "gt.g2o"
    truth.write_text("".join("VERTEX_SE2 {} {} {} {}\n".format(k, *planar_of(p)) for k, p in enumerate(chain)))
    result = invoke("optimize", graph, "--from-odometry", "--gt", truth, "--gt-radius", 5, "--out", tmp_path / "o")
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "o" / "latest-optimize" / "metrics.json").read_text())
    assert metrics["initialised_from_odometry"] is True and metrics["loops_outlier"] == 0
    assert metrics["ate_oracle"]["rmse"] < 1e-6 and metrics["ate_ratio_to_oracle"] is None
    optimised = read_pose_graph(tmp_path / "o" / "latest-optimize" / "optimised.g2o")
    np.testing.assert_allclose(optimised.poses, np.array(chain), atol=1e-6)


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        ("BOGUS 0 1", "unknown tag 'BOGUS'"),
        ("EDGE_SE2 0 1 1 0", "too few values"),
        ("EDGE_SE2 0 1 1 0 NaN 1 0 0 1 0 1", "NaN"),
        ("EDGE_SE2 0 9 1 0 0 1 0 0 1 0 1", "vertex 9"),
        ("EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1", "not positive definite"),
        ("VERTEX_SE2 2 1e300 0 0", "vertex 2 lies 1e+300 m out"),
        ("EDGE_SE2 0 1 2e9 0 0 1 0 0 1 0 1", "measures 2e+09 m"),
    ],
)
def test_malformed_graph_is_one_error_line(tmp_path: Path, line: str, fragment: str) -> None:
    graph = tmp_path / "bad.g2o"
    graph.write_text(f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n{line}\n")
    result = invoke("optimize", graph, "--out", tmp_path / "o")
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    errors = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and f"{graph}:3:" in errors[0] and fragment in errors[0], result.stderr
    assert not (tmp_path / "o").exists()


THIRTY_MB = 30 * 2**20


@pytest.mark.parametrize(
    ("line", "said"),
    [
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 " + "7" * THIRTY_MB + "x", "EDGE_SE2: not a number in '0 1 1 0 0 1 0 0 1 0 777"),
        ("X" * THIRTY_MB, "unknown tag 'XXX"),
        ("EDGE_SE2 0 " + "1" * THIRTY_MB + "z 1 0 0 1 0 0 1 0 1", "vertex id '111"),
    ],
)
def test_a_30_mb_line_is_quoted_in_at_most_200_characters(tmp_path: Path, line: str, said: str) -> None:
    """Before: the whole 30 MB line was echoed into the error."""
    graph = tmp_path / "bad.g2o"
    graph.write_text(f"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n{line}\n")
    result = invoke("optimize", graph, "--out", tmp_path / "o")
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output[:500]
    errors = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and len(result.stderr) < 600, result.stderr[:600]
    assert f"{graph}:3:" in errors[0] and "characters)" in errors[0], errors[0]
    assert said in errors[0], errors[0]


def test_missing_graph_file(tmp_path: Path) -> None:
    result = invoke("optimize", tmp_path / "nope.g2o")
    assert result.exit_code == 2 and "nope.g2o" in result.stderr


@pytest.mark.parametrize(
    ("edges", "extra"),
    [
        # two pieces (0-1 and 2-3) that no edge joins, solved incrementally
        ("VERTEX_SE2 3 3 0 0\nEDGE_SE2 0 1 1 0 0 100 0 0 100 0 100\nEDGE_SE2 2 3 1 0 0 100 0 0 100 0 100\n",
         ["--isam2"]),
    ],
)  # fmt: skip
def test_a_graph_gtsam_cannot_solve_is_one_error_line(tmp_path: Path, edges: str, extra: list[str]) -> None:
    graph = tmp_path / "ill.g2o"
    graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n" + edges)
    result = invoke("optimize", graph, "--out", tmp_path / "o", *extra)
    assert result.exit_code == 2, (result.output, result.exception)
    errors = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert (
        len(errors) == 1
        and f"{graph}: GTSAM could not optimise this graph in the robust solve (indeterminate linear system near "
        in errors[0]
    )
    assert "Traceback" not in result.output and not (tmp_path / "o" / "latest-optimize").exists()


def _ring_of_loops(path: Path, odometry_information: str = "100 0 0 100 0 100") -> Path:
    """A 40-pose planar ring (1 m steps) with 20 true loops, each from pose k across to k + 20."""
    step = planar_pose(1.0, 0.0, 2 * np.pi / 40)
    pose, lines = np.eye(4), []
    for k in range(40):
        lines.append("VERTEX_SE2 {} {} {} {}".format(k, *planar_of(pose)))
        pose = pose @ step
    for k in range(39):
        info = odometry_information if k == 17 else "100 0 0 100 0 100"
        lines.append(f"EDGE_SE2 {k} {k + 1} 1 0 {2 * np.pi / 40:.12f} {info}")
    for k in range(20):  # loops from k to k + 20: half a circle
        rel = np.linalg.inv(_ring_pose(k)) @ _ring_pose(k + 20)
        lines.append("EDGE_SE2 {} {} {} {} {} 100 0 0 100 0 100".format(k, k + 20, *planar_of(rel)))
    path.write_text("\n".join(lines) + "\n")
    return path


def _ring_pose(k: int) -> np.ndarray:
    step, pose = planar_pose(1.0, 0.0, 2 * np.pi / 40), np.eye(4)
    for _ in range(k):
        pose = pose @ step
    return pose


def test_an_edge_weight_past_double_precision_is_one_error_line_naming_it(tmp_path: Path) -> None:
    """One odometry edge of information 1e20: before, GNC silently rejected all 20 loops and the
    estimate came back unchanged (exit 0). Now the line of that edge is named, nothing written."""
    graph = _ring_of_loops(tmp_path / "heavy.g2o", "1e20 0 0 1e20 0 1e20")
    result = invoke("optimize", graph, "--out", tmp_path / "o")
    assert result.exit_code == 2, result.output
    errors = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and f"{graph}:58: edge 17 -> 18 has information eigenvalue 1e+20" in errors[0], errors
    assert not (tmp_path / "o" / "latest-optimize").exists()
    clean = invoke("optimize", _ring_of_loops(tmp_path / "clean.g2o"), "--out", tmp_path / "o")
    assert clean.exit_code == 0, clean.output
    metrics = json.loads((tmp_path / "o" / "latest-optimize" / "metrics.json").read_text())
    assert metrics["loops_inlier"] == 20 and metrics["check_error"] is None


@pytest.mark.parametrize("option", ["--gt-edges", "--gt", "--times"])
@pytest.mark.parametrize("content", [b"\xff\xfe\x00binary\x80", b"\x00" * 64])
def test_a_file_that_is_not_text_is_one_error_line_naming_it(tmp_path: Path, option: str, content: bytes) -> None:
    graph = _ring_of_loops(tmp_path / "g.g2o")
    bad = tmp_path / "binary.dat"
    bad.write_bytes(content)
    result = invoke("optimize", graph, option, bad, "--out", tmp_path / "o")
    assert result.exit_code == 2, (result.output, result.exception)
    errors = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and f"{bad}: not UTF-8 text" in errors[0], result.stderr
    assert "Traceback" not in result.output


def test_a_check_gtsam_cannot_solve_keeps_gncs_answer_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The 60,000-pose case: the leave-one-out check's marginals failed and the whole command
    blamed the graph. Now GNC's solution is written, the step that failed is named."""
    import ssmvpr_slam.backend.graph_optimizer as optimizer

    def fails(*_args: object, **_kwargs: object) -> None:
        raise RuntimeError("\nIndeterminate linear system detected while working near variable\n7 (Symbol: x7).\n")

    monkeypatch.setattr(optimizer, "_leave_one_out_check", fails)
    graph = _ring_of_loops(tmp_path / "g.g2o")
    result = invoke("optimize", graph, "--out", tmp_path / "o")
    assert result.exit_code == 0, result.output
    assert "the leave-one-out check could not solve (indeterminate linear system near x7)" in " ".join(
        result.output.split()
    )
    metrics = json.loads((tmp_path / "o" / "latest-optimize" / "metrics.json").read_text())
    assert metrics["check"] is False and "leave-one-out check could not solve" in metrics["check_error"]
    assert metrics["loops_inlier"] == 20  # GNC's answer: every true loop kept
    solved = read_pose_graph(tmp_path / "o" / "latest-optimize" / "optimised.g2o")
    np.testing.assert_allclose(solved.poses[20, :2, 3], _ring_pose(20)[:2, 3], atol=1e-6)


def test_a_full_disk_names_the_file_and_where_to_go_instead(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Before: 'error: [Errno 28] No space left on device', naming neither the file nor --out."""
    import errno

    import ssmvpr_common.atomic as atomic

    def full(_fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", full)
    result = invoke("optimize", _ring_of_loops(tmp_path / "g.g2o"), "--out", tmp_path / "o")
    assert result.exit_code == 2, result.output
    errors = [x for x in result.stderr.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and "optimised.g2o: disk full while writing it (No space left on device; " in errors[0]
    assert "--out" in errors[0] and str(tmp_path / "o") in errors[0]
    assert not (tmp_path / "o" / "latest-optimize").exists() and not list((tmp_path / "o").glob(".optimize*"))
