"""Pose-graph files: g2o (2D and 3D) and TORO in, g2o out, plus ground-truth pose files.

Read
----
* g2o: ``VERTEX_SE2 id x y theta``, ``EDGE_SE2 i j x y theta I11 I12 I13 I22 I23 I33``,
  ``VERTEX_SE3:QUAT id x y z qx qy qz qw``, ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21
  upper-triangular entries of the 6x6 information matrix over (x, y, z, qx, qy, qz).
* TORO: ``VERTEX2 id x y theta``, ``EDGE2 i j x y theta I_xx I_xy I_yy I_tt I_xt I_yt`` (TORO's
  order), and, for gtsam's 3-D data, ``VERTEX3 id x y z roll pitch yaw`` / ``EDGE3 i j x y z roll
  pitch yaw`` + 21 upper-triangular information entries over (x, y, z, roll, pitch, yaw).
* ``FIX id`` lines are accepted and ignored (the first vertex is always held by a prior).
* Blank lines and ``#`` comments are skipped. A file without any vertex line takes its vertices
  from the edges (all at the origin, so they are initialised from odometry).

Every problem raises :class:`PoseGraphFileError` naming ``file:line``: an unknown tag, a wrong
number of values, a value that is not a number, NaN/inf, a bad quaternion, an edge to a vertex
the file does not declare, a duplicate vertex, mixed 2D/3D records, an information matrix that
is not positive definite.

Representation
--------------
2-D graphs are **held lifted into Pose3 form**, so one representation serves both (the SLAM
pipeline's graphs are 3-D): a planar pose becomes a rotation about z plus (x, y, 0); the 3x3
information over (x, y, theta) maps onto the Pose3 tangent (rx, ry, rz, tx, ty, tz) at (tx, ty,
rz), and the three out-of-plane directions get the largest in-plane diagonal entry. The
optimiser (`graph_optimizer`) takes the planar part back and solves 2-D graphs with Pose2,
which has the same optimum (Pose3's local coordinates restricted to the plane are Pose2's) at a
fraction of the cost; the writer writes a 2-D graph back as EDGE_SE2 from the same planar part.
3-D information is permuted from g2o's (translation, rotation) order to GTSAM's (rotation,
translation) order, as gtsam's own ``readG2o`` does.

Over 400 lines: three record formats in two dimensions, each with its own checks, plus the
ground-truth files `optimize` reads beside a graph; they share the line parsing and the one
error type, and no caller wants one without the other.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_common.poses import matrix_to_quaternion, quaternion_to_matrix
from ssmvpr_common.quoting import quoted
from ssmvpr_common.text_files import read_text
from ssmvpr_common.trajectory_io import TrajectoryFileError, read_tum
from ssmvpr_slam.backend.se3 import make_pose, project_to_so3, rot_z, yaw_of

QUATERNION_NORM_TOL = 1e-3
MAX_COORDINATE_M = 1e8
"""Coordinates and edge lengths past this (100,000 km) are refused: no map is that large, so such
a value is a wrong unit or a corrupted number (at 1e300 its square overflows to inf)."""
MAX_INFORMATION_RATIO = 1e12
"""Largest spread of information eigenvalues across one graph: the standard graphs span 1 to 1e3,
the pipeline's about 1e6; past 1e12 the weak edges vanish from the normal equations."""
"""A stored quaternion whose norm is off by more than this is refused (else renormalised)."""
NUMBER_FORMAT = "{:.12g}"

# tag -> (dimension, kind, number of values after the tag)
_TAGS: dict[str, tuple[int, str, int]] = {
    "VERTEX_SE2": (2, "vertex", 4),
    "EDGE_SE2": (2, "edge", 11),
    "VERTEX_SE3:QUAT": (3, "vertex", 8),
    "EDGE_SE3:QUAT": (3, "edge", 30),
    "VERTEX2": (2, "vertex", 4),
    "EDGE2": (2, "edge", 11),
    "VERTEX3": (3, "vertex", 7),
    "EDGE3": (3, "edge", 29),
}
_IGNORED_TAGS = {"FIX": 1}
_G2O_TO_POSE3 = [3, 4, 5, 0, 1, 2]  # Pose3 tangent index k reads g2o index _G2O_TO_POSE3[k]
_PLANAR_IN_POSE3 = [3, 4, 2]  # (x, y, theta) -> (tx, ty, rz)


class PoseGraphFileError(ValueError):
    """A pose-graph or ground-truth file that cannot be used; the message names file:line."""


@dataclass(frozen=True)
class GraphEdge:
    """A relative-pose measurement ``T_ij = inv(T_i) @ T_j`` between vertices i and j."""

    i: int
    j: int
    measured: np.ndarray
    """4x4 T_ij."""
    information: np.ndarray
    """6x6 in GTSAM's Pose3 tangent order (rx, ry, rz, tx, ty, tz)."""
    line: int = 0
    """Line of the file it came from (0 when built in code)."""

    @property
    def is_odometry(self) -> bool:
        """Consecutive vertex ids: an odometry edge; anything else is a loop candidate."""
        return abs(self.j - self.i) == 1


@dataclass(frozen=True)
class PoseGraphData:
    """A pose graph as read from a file: vertex ids in increasing order, their stored poses
    (N, 4, 4), and the edges in file order."""

    dim: int
    ids: tuple[int, ...]
    poses: np.ndarray
    edges: tuple[GraphEdge, ...]
    source: str = "<memory>"
    declared_vertices: bool = True
    """False when the file had no vertex lines and the vertices come from the edges."""
    _index: dict[int, int] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self._index.update({v: k for k, v in enumerate(self.ids)})

    def index_of(self, vertex_id: int) -> int:
        return self._index[vertex_id]

    @property
    def odometry(self) -> list[GraphEdge]:
        return [e for e in self.edges if e.is_odometry]

    @property
    def loops(self) -> list[GraphEdge]:
        return [e for e in self.edges if not e.is_odometry]

    def has_initial_estimate(self) -> bool:
        """False when every stored pose after the first is the identity (all-zero vertices; the
        first only says where a chain of odometry starts) or none were stored."""
        if not self.declared_vertices or len(self.poses) == 0:
            return False
        return not np.allclose(self.poses[1:], np.eye(4), atol=1e-12)

    def without_estimate(self) -> PoseGraphData:
        """The same graph with every vertex but the first zeroed, so that the optimiser chains
        odometry from the first vertex, in the file's frame: for a stored estimate that is not to
        be trusted (one bent by false loops)."""
        poses = np.tile(np.eye(4), (len(self.ids), 1, 1))
        if self.declared_vertices and len(self.poses):
            poses[0] = self.poses[0]
        return PoseGraphData(self.dim, self.ids, poses, self.edges, self.source, self.declared_vertices)

    def with_edges(self, edges: Iterable[GraphEdge], source: str | None = None) -> PoseGraphData:
        """The same vertices with another edge list (e.g. with injected false loops)."""
        return PoseGraphData(self.dim, self.ids, self.poses, tuple(edges), source or self.source,
                             self.declared_vertices)  # fmt: skip


# --------------------------------------------------------------------------- conversions


def planar_pose(x: float, y: float, theta: float) -> np.ndarray:
    """4x4 pose of a planar (x, y, theta)."""
    return make_pose(rot_z(theta), np.array([x, y, 0.0]))


def planar_of(pose: np.ndarray) -> tuple[float, float, float]:
    """(x, y, theta) of a planar 4x4 pose."""
    return float(pose[0, 3]), float(pose[1, 3]), yaw_of(pose[:3, :3])


def _euler_pose(values: np.ndarray) -> np.ndarray:
    """TORO / gtsam EDGE3 pose: x y z roll pitch yaw, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll, pitch, yaw = values[3:6]
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return make_pose(rot_z(yaw) @ ry @ rx, values[:3])


def _upper_to_full(values: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros((n, n))
    out[np.triu_indices(n)] = values
    return out + np.triu(out, 1).T


def _full_to_upper(matrix: np.ndarray) -> np.ndarray:
    return matrix[np.triu_indices(len(matrix))]


def information_planar_to_pose3(info3: np.ndarray) -> np.ndarray:
    """3x3 information over (x, y, theta) -> 6x6 Pose3 tangent information (see module doc)."""
    out = np.zeros((6, 6))
    out[np.ix_(_PLANAR_IN_POSE3, _PLANAR_IN_POSE3)] = info3
    stiff = float(np.max(np.diag(info3)))
    for k in (0, 1, 5):  # rx, ry, tz
        out[k, k] = stiff
    return out


def information_pose3_to_planar(info6: np.ndarray) -> np.ndarray:
    return np.asarray(info6)[np.ix_(_PLANAR_IN_POSE3, _PLANAR_IN_POSE3)]


def information_g2o_to_pose3(info6: np.ndarray) -> np.ndarray:
    """6x6 over (translation, rotation) -> GTSAM's (rotation, translation)."""
    return np.asarray(info6)[np.ix_(_G2O_TO_POSE3, _G2O_TO_POSE3)]


def information_pose3_to_g2o(info6: np.ndarray) -> np.ndarray:
    inverse = np.argsort(_G2O_TO_POSE3)
    return np.asarray(info6)[np.ix_(inverse, inverse)]


# --------------------------------------------------------------------------- reading


def _fail(path: str, lineno: int, message: str) -> PoseGraphFileError:
    return PoseGraphFileError(f"{path}:{lineno}: {message}")


def _numbers(path: str, lineno: int, tag: str, tokens: list[str], expected: int) -> np.ndarray:
    if len(tokens) != expected:
        few = "too few" if len(tokens) < expected else "too many"
        raise _fail(path, lineno, f"{tag} expects {expected} values, got {len(tokens)} ({few} values)")
    try:
        values = np.array([float(t) for t in tokens])
    except ValueError:
        raise _fail(path, lineno, f"{tag}: not a number in {quoted(' '.join(tokens))}") from None
    if not np.all(np.isfinite(values)):
        raise _fail(path, lineno, f"{tag}: NaN or inf in {quoted(' '.join(tokens))}")
    return values


def _vertex_id(path: str, lineno: int, token: str) -> int:
    try:
        value = int(token)
    except ValueError:
        raise _fail(path, lineno, f"vertex id {quoted(token)} is not an integer") from None
    if value < 0:
        raise _fail(path, lineno, f"vertex id {value} is negative")
    return value


def _quaternion(path: str, lineno: int, q: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOL:
        raise _fail(path, lineno, f"quaternion norm {norm:.6g} is not 1 (not a rotation)")
    return quaternion_to_matrix(q / norm)


def _checked_information(path: str, lineno: int, info: np.ndarray) -> np.ndarray:
    eigenvalues = np.linalg.eigvalsh(info)
    if float(eigenvalues.min()) <= 0.0:
        raise _fail(path, lineno, "information matrix is not positive definite "
                                  f"(smallest eigenvalue {float(eigenvalues.min()):.3g})")  # fmt: skip
    return info


def _vertex_pose(tag: str, values: np.ndarray) -> np.ndarray:
    if tag in ("VERTEX_SE2", "VERTEX2"):
        return planar_pose(*values)
    if tag == "VERTEX3":
        return _euler_pose(values)
    raise AssertionError(tag)  # VERTEX_SE3:QUAT is handled by the caller (quaternion check)


def _edge(path: str, lineno: int, tag: str, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T_ij, 6x6 Pose3 information) of an edge's values after the two ids."""
    if tag == "EDGE_SE2":
        info3 = _checked_information(path, lineno, _upper_to_full(values[3:9], 3))
        return planar_pose(*values[:3]), information_planar_to_pose3(info3)
    if tag == "EDGE2":  # TORO: xx xy yy tt xt yt
        xx, xy, yy, tt, xt, yt = values[3:9]
        info3 = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]])
        info3 = _checked_information(path, lineno, info3)
        return planar_pose(*values[:3]), information_planar_to_pose3(info3)
    if tag == "EDGE_SE3:QUAT":
        rot = _quaternion(path, lineno, values[3:7])
        info6 = _checked_information(path, lineno, _upper_to_full(values[7:28], 6))
        return make_pose(rot, values[:3]), information_g2o_to_pose3(info6)
    if tag == "EDGE3":
        info6 = _checked_information(path, lineno, _upper_to_full(values[6:27], 6))
        return _euler_pose(values[:6]), information_g2o_to_pose3(info6)
    raise AssertionError(tag)


def read_pose_graph(path: str | os.PathLike[str]) -> PoseGraphData:
    """Read a g2o or TORO pose graph (see the module docstring)."""
    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pose-graph file not found")
    text = read_text(path, PoseGraphFileError)
    dim: int | None = None
    dim_line = 0
    vertices: dict[int, tuple[np.ndarray, int]] = {}
    edges: list[GraphEdge] = []
    known = ", ".join([*_TAGS, *_IGNORED_TAGS])
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag, rest = tokens[0], tokens[1:]
        if tag in _IGNORED_TAGS:
            _numbers(name, lineno, tag, rest, _IGNORED_TAGS[tag])
            continue
        if tag not in _TAGS:
            raise _fail(name, lineno, f"unknown tag {quoted(tag)} (expected one of {known})")
        tag_dim, kind, count = _TAGS[tag]
        if dim is None:
            dim, dim_line = tag_dim, lineno
        elif tag_dim != dim:
            raise _fail(name, lineno, f"{tag} is {tag_dim}-D but line {dim_line} made this a {dim}-D graph")
        ids_count = 1 if kind == "vertex" else 2
        if len(rest) < ids_count:
            raise _fail(name, lineno, f"{tag} expects {count} values, got {len(rest)} (too few values)")
        ids = [_vertex_id(name, lineno, t) for t in rest[:ids_count]]
        values = _numbers(name, lineno, tag, rest, count)[ids_count:]
        if kind == "vertex":
            if ids[0] in vertices:
                raise _fail(name, lineno, f"vertex {ids[0]} was already declared on line {vertices[ids[0]][1]}")
            if tag == "VERTEX_SE3:QUAT":
                pose = make_pose(_quaternion(name, lineno, values[3:7]), values[:3])
            else:
                pose = _vertex_pose(tag, values)
            vertices[ids[0]] = (pose, lineno)
        else:
            if ids[0] == ids[1]:
                raise _fail(name, lineno, f"edge from vertex {ids[0]} to itself")
            measured, information = _edge(name, lineno, tag, values)
            edges.append(GraphEdge(ids[0], ids[1], measured, information, lineno))
    if dim is None:
        raise PoseGraphFileError(f"{path}: no vertices or edges (not a g2o / TORO pose graph)")
    declared = bool(vertices)
    if declared:
        for edge in edges:
            for end in (edge.i, edge.j):
                if end not in vertices:
                    raise _fail(name, edge.line, f"edge {edge.i} -> {edge.j} refers to vertex {end}, "
                                                 "which the file does not declare")  # fmt: skip
    else:
        vertices = {v: (np.eye(4), 0) for e in edges for v in (e.i, e.j)}
    _check_scales(name, vertices, edges)
    ids_sorted = tuple(sorted(vertices))
    poses = np.array([vertices[v][0] for v in ids_sorted]).reshape(-1, 4, 4)
    return PoseGraphData(dim, ids_sorted, poses, tuple(edges), name, declared)


def _check_scales(name: str, vertices: dict[int, tuple[np.ndarray, int]], edges: list[GraphEdge]) -> None:
    """Refuse what double-precision least squares cannot use, naming the line: a coordinate past
    `MAX_COORDINATE_M`, or information eigenvalues
    spread wider than `MAX_INFORMATION_RATIO` across the graph (the normal equations lose every
    digit of the weak edges: GNC then rejects every loop and the estimate comes back unchanged)."""
    for vertex, (pose, lineno) in vertices.items():
        reach = float(np.abs(pose[:3, 3]).max())
        if reach > MAX_COORDINATE_M:
            raise _fail(name, lineno, f"vertex {vertex} lies {reach:.3g} m out, beyond the {MAX_COORDINATE_M:.0e} m "
                                      "double-precision least squares can solve; shift or rescale the graph")  # fmt: skip
    if not edges:
        return
    for edge in edges:
        reach = float(np.abs(edge.measured[:3, 3]).max())
        if reach > MAX_COORDINATE_M:
            raise _fail(name, edge.line, f"edge {edge.i} -> {edge.j} measures {reach:.3g} m, beyond the "
                                         f"{MAX_COORDINATE_M:.0e} m double-precision least squares can solve")  # fmt: skip
    spectra = np.linalg.eigvalsh(np.array([e.information for e in edges]))  # (E, 6), ascending
    weakest, strongest = int(np.argmin(spectra[:, 0])), int(np.argmax(spectra[:, -1]))
    low, high = float(spectra[weakest, 0]), float(spectra[strongest, -1])
    if high > MAX_INFORMATION_RATIO * low:
        # Name the edge further from the graph's typical weight: that is the one to fix.
        typical = float(np.median(np.log10(spectra)))
        k, value = (strongest, high) if np.log10(high) - typical >= typical - np.log10(low) else (weakest, low)
        edge = edges[k]
        raise _fail(name, edge.line, f"edge {edge.i} -> {edge.j} has information eigenvalue {value:.3g} against "
                                     f"{low if k == strongest else high:.3g} elsewhere in the graph: a spread past "
                                     f"{MAX_INFORMATION_RATIO:.0e} that double-precision least squares cannot solve; "
                                     "fix that edge's information")  # fmt: skip


# --------------------------------------------------------------------------- writing


def _fmt(values: Iterable[float]) -> str:
    return " ".join(NUMBER_FORMAT.format(float(v)) for v in values)


def format_g2o(graph: PoseGraphData, poses: np.ndarray | None = None) -> str:
    """g2o text of `graph` with `poses` (N, 4, 4, in ``graph.ids`` order; default: the stored
    ones): VERTEX_SE2/EDGE_SE2 for 2-D graphs, VERTEX_SE3:QUAT/EDGE_SE3:QUAT for 3-D ones."""
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(graph.ids), 4, 4):
        raise ValueError(f"poses: expected shape ({len(graph.ids)}, 4, 4), got {poses.shape}")
    lines: list[str] = []
    for vid, pose in zip(graph.ids, poses):
        if graph.dim == 2:
            lines.append(f"VERTEX_SE2 {vid} {_fmt(planar_of(pose))}")
        else:
            quat = matrix_to_quaternion(project_to_so3(pose[:3, :3]))
            lines.append(f"VERTEX_SE3:QUAT {vid} {_fmt(pose[:3, 3])} {_fmt(quat)}")
    for e in graph.edges:
        if graph.dim == 2:
            info = _full_to_upper(information_pose3_to_planar(e.information))
            lines.append(f"EDGE_SE2 {e.i} {e.j} {_fmt(planar_of(e.measured))} {_fmt(info)}")
        else:
            quat = matrix_to_quaternion(project_to_so3(e.measured[:3, :3]))
            info = _full_to_upper(information_pose3_to_g2o(e.information))
            lines.append(f"EDGE_SE3:QUAT {e.i} {e.j} {_fmt(e.measured[:3, 3])} {_fmt(quat)} {_fmt(info)}")
    return "".join(line + "\n" for line in lines)


def write_g2o(path: str | os.PathLike[str], graph: PoseGraphData, poses: np.ndarray | None = None) -> Path:
    """Write `graph` (with `poses`, see `format_g2o`) atomically."""
    return atomic_write_text(path, format_g2o(graph, poses))


# --------------------------------------------------------------------------- ground truth


def read_vertex_poses(path: str | os.PathLike[str]) -> tuple[np.ndarray | None, np.ndarray]:
    """A per-vertex pose file: (ids or None, poses (N, 4, 4)).

    One pose per line, by column count: 3 = ``x y theta`` (line k is the k-th vertex),
    4 = ``id x y theta``, 7 = ``x y z qx qy qz qw``, 8 = ``id x y z qx qy qz qw``.
    """
    path = Path(path)
    name = str(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pose file not found")
    ids: list[int] = []
    poses: list[np.ndarray] = []
    width: int | None = None
    for lineno, line in enumerate(read_text(path, PoseGraphFileError).splitlines(), start=1):
        tokens = line.replace(",", " ").split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if width is None:
            width = len(tokens)
            if width not in (3, 4, 7, 8):
                raise _fail(name, lineno, f"expected 3 (x y theta), 4 (id x y theta), 7 (x y z qx qy qz qw) "
                                          f"or 8 (id x y z qx qy qz qw) values per line, got {width}")  # fmt: skip
        values = _numbers(name, lineno, "pose", tokens, width)
        with_id = width in (4, 8)
        if with_id:
            ids.append(_vertex_id(name, lineno, tokens[0]))
            values = values[1:]
        if len(values) == 3:
            poses.append(planar_pose(*values))
        else:
            poses.append(make_pose(_quaternion(name, lineno, values[3:7]), values[:3]))
    if not poses:
        raise PoseGraphFileError(f"{path}: no poses")
    return (np.array(ids) if ids else None), np.array(poses)


def read_edge_pairs(path: str | os.PathLike[str]) -> set[tuple[int, int]]:
    """The (i, j) vertex pairs of a ground-truth edge list: g2o/TORO edge lines, or lines
    starting with the two vertex ids (the Vertigo ``edges.txt`` / ``*_edges_groundTruth.dat``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: edge file not found")
    pairs: set[tuple[int, int]] = set()
    for lineno, line in enumerate(read_text(path, PoseGraphFileError).splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#") or tokens[0].startswith("VERTEX"):
            continue
        if tokens[0] in _TAGS:
            tokens = tokens[1:]
        if len(tokens) < 2:
            raise _fail(str(path), lineno, f"expected two vertex ids, got {quoted(line.strip())}")
        i, j = (_vertex_id(str(path), lineno, t) for t in tokens[:2])
        pairs.add((min(i, j), max(i, j)))
    return pairs


def check_loop_truth(path: str | os.PathLike[str], pairs: set[tuple[int, int]], graph: PoseGraphData) -> None:
    """Refuse an edge truth that lists none of the graph's loops: it is an odometry list (Vertigo's
    ring ``edges.txt``) or another graph's, and would silently count every loop as false.
    A truth listing some of the loops is the real use: the loops it leaves out are the false ones."""
    loops = {(min(e.i, e.j), max(e.i, e.j)) for e in graph.loops}
    if not loops or loops & pairs:
        return
    listed = sum(1 for i, j in pairs if j - i != 1)
    what = "all odometry (i, i+1)" if listed == 0 else f"{listed} of them loops"
    raise PoseGraphFileError(
        f"--gt-edges {path}: {len(pairs)} edges, {what}: none of the graph's {len(loops)} loop edges; "
        f"pass a file that lists the true loops (e.g. the ground-truth .g2o) or use --gt with --gt-radius"
    )


def read_ground_truth(
    path: str | os.PathLike[str], graph: PoseGraphData, times: np.ndarray | None = None
) -> np.ndarray:
    """Ground-truth poses (N, 4, 4) in ``graph.ids`` order from a g2o/TORO graph (its vertex
    poses, or for a vertex-less edge file, its odometry chained), a TUM file (``.tum``, matched
    by `times` when given, else by order) or a per-vertex pose file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: ground-truth file not found")
    first = _first_token(path)
    if first in _TAGS:
        gt_graph = read_pose_graph(path)
        if gt_graph.declared_vertices:
            by_id = dict(zip(gt_graph.ids, gt_graph.poses))
        else:
            by_id = dict(zip(gt_graph.ids, chain_odometry(gt_graph)))
        return _in_graph_order(path, graph, by_id)
    if path.suffix.lower() == ".tum":
        try:
            stamps, poses = read_tum(path)
        except TrajectoryFileError as error:
            raise PoseGraphFileError(str(error)) from None
        if times is not None:
            index = {round(float(t), 6): k for k, t in enumerate(stamps)}
            missing = [float(t) for t in times if round(float(t), 6) not in index]
            if missing:
                raise PoseGraphFileError(f"{path}: no ground-truth pose at time {missing[0]:.6f}")
            return np.array([poses[index[round(float(t), 6)]] for t in times])
        if len(poses) != len(graph.ids):
            raise PoseGraphFileError(f"{path}: {len(poses)} poses for {len(graph.ids)} vertices "
                                     "(give --times to match them by timestamp)")  # fmt: skip
        return poses
    ids, poses = read_vertex_poses(path)
    if ids is None:
        if len(poses) != len(graph.ids):
            raise PoseGraphFileError(f"{path}: {len(poses)} poses for {len(graph.ids)} vertices")
        return poses
    return _in_graph_order(path, graph, dict(zip(ids.tolist(), poses)))


def _in_graph_order(path: Path, graph: PoseGraphData, by_id: dict[int, np.ndarray]) -> np.ndarray:
    missing = [v for v in graph.ids if v not in by_id]
    if missing:
        raise PoseGraphFileError(f"{path}: no ground-truth pose for vertex {missing[0]} "
                                 f"({len(missing)} of {len(graph.ids)} missing)")  # fmt: skip
    return np.array([by_id[v] for v in graph.ids])


def _first_token(path: Path) -> str:
    for line in read_text(path, PoseGraphFileError).splitlines():
        tokens = line.split()
        if tokens and not tokens[0].startswith("#"):
            return tokens[0]
    return ""


def read_times(path: str | os.PathLike[str], graph: PoseGraphData) -> np.ndarray:
    """Timestamps of the vertices: one per line, ``t`` (k-th vertex) or ``id t``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: times file not found")
    by_id: dict[int, float] = {}
    plain: list[float] = []
    for lineno, line in enumerate(read_text(path, PoseGraphFileError).splitlines(), start=1):
        tokens = line.replace(",", " ").split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) == 2:
            by_id[_vertex_id(str(path), lineno, tokens[0])] = float(
                _numbers(str(path), lineno, "time", tokens[1:], 1)[0]
            )
        else:
            plain.append(float(_numbers(str(path), lineno, "time", tokens, 1)[0]))
    if plain and by_id:
        raise PoseGraphFileError(f"{path}: mixes 't' and 'id t' lines")
    if by_id:
        stamps = _in_graph_order(path, graph, {k: np.asarray(v, dtype=np.float64) for k, v in by_id.items()})
        return np.asarray(stamps, dtype=np.float64)
    if len(plain) != len(graph.ids):
        raise PoseGraphFileError(f"{path}: {len(plain)} times for {len(graph.ids)} vertices")
    return np.asarray(plain, dtype=np.float64)


# --------------------------------------------------------------------------- helpers


def chain_odometry(graph: PoseGraphData) -> np.ndarray:
    """Poses (N, 4, 4, ``graph.ids`` order) composed along a spanning tree from the first
    vertex, odometry edges first (then loops for vertices no odometry reaches); the first
    vertex keeps its stored pose. Raises PoseGraphFileError for a disconnected graph."""
    n = len(graph.ids)
    poses: list[np.ndarray | None] = [None] * n
    poses[0] = graph.poses[0].copy() if graph.declared_vertices and len(graph.poses) else np.eye(4)
    adjacency: dict[int, list[tuple[int, np.ndarray, bool]]] = {v: [] for v in graph.ids}
    for e in graph.edges:
        adjacency[e.i].append((e.j, e.measured, e.is_odometry))
        adjacency[e.j].append((e.i, np.linalg.inv(e.measured), e.is_odometry))
    for v in adjacency:  # odometry first, then by id: the chain a stream would build
        adjacency[v].sort(key=lambda item: (not item[2], item[0]))
    # odometry-only sweep in id order, then a breadth-first pass over every edge for the rest
    for k in range(1, n):
        prev, cur = graph.ids[k - 1], graph.ids[k]
        if poses[k - 1] is None:
            continue
        for other, rel, odo in adjacency[prev]:
            if other == cur and odo:
                poses[k] = poses[k - 1] @ rel
                break
    frontier = [k for k in range(n) if poses[k] is not None]
    while frontier:
        nxt = []
        for k in frontier:
            for other, rel, _ in adjacency[graph.ids[k]]:
                m = graph.index_of(other)
                if poses[m] is None:
                    poses[m] = poses[k] @ rel
                    nxt.append(m)
        frontier = nxt
    missing = [graph.ids[k] for k in range(n) if poses[k] is None]
    if missing:
        raise PoseGraphFileError(f"{graph.source}: vertex {missing[0]} is not connected to vertex "
                                 f"{graph.ids[0]} by any edge ({len(missing)} such vertices)")  # fmt: skip
    out = np.array(poses)
    out[:, :3, :3] = [project_to_so3(p[:3, :3]) for p in out]
    return out


def from_pose_graph(pose_graph, poses: np.ndarray) -> PoseGraphData:  # noqa: ANN001 - a PoseGraph
    """A `PoseGraph`'s keyframes (with `poses`, in keyframe order) and the factors it solves
    between them (`PoseGraph.solved_edges`) as a 3-D graph, for `write_g2o`."""
    ids = tuple(pose_graph.keyframe_ids)
    edges = tuple(GraphEdge(i, j, measured, information) for i, j, measured, information in pose_graph.solved_edges())
    return PoseGraphData(3, ids, np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4), edges, "run")
