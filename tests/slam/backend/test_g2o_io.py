"""g2o / TORO reading and writing: round trip, conversions, real files, malformed input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ssmvpr_slam.backend import g2o_io
from ssmvpr_slam.backend.g2o_io import PoseGraphFileError, read_pose_graph, write_g2o

GOOD_2D = """# a square
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 1.5707963
VERTEX_SE2 2 1 1 3.1415926
EDGE_SE2 0 1 1 0 1.5707963 100 0 0 100 0 400
EDGE_SE2 1 2 1 0 1.5707963 100 0 0 100 0 400
EDGE_SE2 2 0 1.4142 0 -2.356 10 1 0 20 0 30
"""


def write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_reads_2d_graph_and_lifts_information(tmp_path: Path) -> None:
    graph = read_pose_graph(write(tmp_path, GOOD_2D))
    assert graph.dim == 2 and graph.ids == (0, 1, 2)
    assert [e.is_odometry for e in graph.edges] == [True, True, False]
    np.testing.assert_allclose(graph.poses[1][:3, 3], [1, 0, 0])
    loop = graph.edges[2]
    # (x, y, theta) -> (tx, ty, rz); out-of-plane entries get the largest in-plane diagonal
    assert loop.information[3, 3] == 10 and loop.information[3, 4] == 1 and loop.information[4, 4] == 20
    assert loop.information[2, 2] == 30 and loop.information[0, 0] == 30 and loop.information[5, 5] == 30


def test_round_trip_2d_and_3d(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    lines = ["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1"]
    for k in range(1, 4):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        lines.append(f"VERTEX_SE3:QUAT {k} {' '.join(map(str, rng.normal(size=3)))} {' '.join(map(str, q))}")
    info = np.triu(np.eye(6) * 50 + 1)[np.triu_indices(6)]
    for i, j in ((0, 1), (1, 2), (2, 3), (3, 0)):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        lines.append(f"EDGE_SE3:QUAT {i} {j} 1 2 3 {' '.join(map(str, q))} {' '.join(map(str, info))}")
    for text in (GOOD_2D, "\n".join(lines) + "\n"):
        first = read_pose_graph(write(tmp_path, text, "a.g2o"))
        write_g2o(tmp_path / "b.g2o", first)
        second = read_pose_graph(tmp_path / "b.g2o")
        assert second.ids == first.ids and second.dim == first.dim
        np.testing.assert_allclose(second.poses, first.poses, atol=1e-9)
        for a, b in zip(first.edges, second.edges):
            assert (a.i, a.j) == (b.i, b.j)
            np.testing.assert_allclose(b.measured, a.measured, atol=1e-9)
            np.testing.assert_allclose(b.information, a.information, rtol=1e-9)


def test_toro_2d_matches_g2o(tmp_path: Path) -> None:
    # TORO orders the information xx xy yy tt xt yt; g2o xx xy xt yy yt tt
    toro = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\nEDGE2 0 1 1 0 0.1 10 1 20 30 2 3\n"
    g2o = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0.1 10 1 2 20 3 30\n"
    a = read_pose_graph(write(tmp_path, toro, "t.graph")).edges[0]
    b = read_pose_graph(write(tmp_path, g2o, "g.g2o")).edges[0]
    np.testing.assert_allclose(a.information, b.information)
    np.testing.assert_allclose(a.measured, b.measured)


def test_edges_only_file_gets_vertices_from_edges(tmp_path: Path) -> None:
    graph = read_pose_graph(write(tmp_path, "EDGE2 0 1 1 0 0 1 0 1 1 0 0\nEDGE2 1 2 1 0 0 1 0 1 1 0 0\n"))
    assert graph.ids == (0, 1, 2) and not graph.has_initial_estimate()
    np.testing.assert_allclose(g2o_io.chain_odometry(graph)[2][:3, 3], [2, 0, 0])


def test_zero_vertices_after_a_placed_first_one_chain_odometry_from_it(tmp_path: Path) -> None:
    """Only the first vertex placed (or an estimate dropped with without_estimate): no estimate,
    and the odometry chain starts at the first vertex, in the file's frame."""
    text = "VERTEX_SE2 0 5 2 1.5707963268\nVERTEX_SE2 1 0 0 0\nVERTEX_SE2 2 0 0 0\n"
    text += "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n"
    graph = read_pose_graph(write(tmp_path, text))
    assert not graph.has_initial_estimate()
    np.testing.assert_allclose(g2o_io.chain_odometry(graph)[2][:3, 3], [5, 4, 0], atol=1e-9)
    bent = read_pose_graph(write(tmp_path, text, "bent.g2o"))
    bent.poses[1:, :3, 3] = [[9.0, 9.0, 0.0], [7.0, 1.0, 0.0]]
    assert bent.has_initial_estimate() and not bent.without_estimate().has_initial_estimate()
    np.testing.assert_allclose(g2o_io.chain_odometry(bent.without_estimate()), g2o_io.chain_odometry(graph), atol=1e-12)


@pytest.mark.parametrize(
    ("line", "fragment"),
    [
        ("EDGE_FOO 0 1 1 0 0", "unknown tag 'EDGE_FOO'"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1", "too few values"),
        ("EDGE_SE2 0 1 nan 0 0 1 0 0 1 0 1", "NaN"),
        ("EDGE_SE2 0 7 1 0 0 1 0 0 1 0 1", "vertex 7"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1", "not positive definite"),
        ("VERTEX_SE3:QUAT 5 0 0 0 0 0 0 1", "3-D"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path: Path, line: str, fragment: str) -> None:
    path = write(tmp_path, "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n" + line + "\n")
    with pytest.raises(PoseGraphFileError) as info:
        read_pose_graph(path)
    assert f"{path}:3:" in str(info.value) and fragment in str(info.value)


def test_ground_truth_formats(tmp_path: Path, shared_dir: Path) -> None:
    base = shared_dir / "data" / "posegraphs"
    graph = read_pose_graph(base / "ring" / "originalDataset" / "ring.g2o")
    from_g2o = g2o_io.read_ground_truth(base / "ring" / "groundTruth" / "ring.g2o", graph)
    from_txt = g2o_io.read_ground_truth(base / "ring" / "groundTruth" / "poses.txt", graph)
    np.testing.assert_allclose(from_g2o, from_txt, atol=1e-6)
    assert len(graph.loops) == 26 and len(graph.ids) == 434
    pairs = g2o_io.read_edge_pairs(base / "ring" / "groundTruth" / "edges.txt")
    assert len(pairs) == 433 and all((e.i, e.j) in pairs for e in graph.odometry)


def test_pose_graph_of_a_run_is_written_as_g2o(tmp_path: Path) -> None:
    from ssmvpr_slam.backend.pose_graph import PoseGraph
    from ssmvpr_slam.backend.se3 import make_pose, rot_z

    pg = PoseGraph()
    poses = [make_pose(rot_z(0.3 * k), (k, 0.5 * k, 0)) for k in range(5)]
    for k, pose in enumerate(poses):
        pg.add_keyframe(k, pose)
    pg.add_loop(0, 4, np.linalg.inv(poses[0]) @ poses[4])
    optimised = np.array([pg.optimized_poses()[k] for k in range(5)])
    write_g2o(tmp_path / "pose_graph.g2o", g2o_io.from_pose_graph(pg, optimised))
    back = read_pose_graph(tmp_path / "pose_graph.g2o")
    assert back.dim == 3 and back.ids == (0, 1, 2, 3, 4)
    assert [(e.i, e.j) for e in back.loops] == [(0, 4)] and len(back.odometry) == 4
    np.testing.assert_allclose(back.poses, optimised, atol=1e-8)
