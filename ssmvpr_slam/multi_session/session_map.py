"""A finished session as the merge reads it: its places (codes, map poses, scans, ground
truth, rear codes) from the saved database and its odometry and loop factors from
pose_graph.g2o, all in the session's own frame."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from loopclosure.config import VPRConfig
from ssmvpr_slam.backend.g2o_io import PoseGraphData, read_pose_graph
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.prior_map import PriorMap


class SessionMapError(SlamError, ValueError):
    """A session's results folder that cannot be merged; the message names it."""


@dataclass
class SessionMap:
    """One session: `places` (a `PriorMap` of its own database) and `graph` (its factors).

    Keyframe k of the session is place k and vertex k of the graph: a session runs without a
    prior map, so its database holds its own keyframes only, in order."""

    name: str
    log: str
    folder: Path
    places: PriorMap
    graph: PoseGraphData

    def __len__(self) -> int:
        return len(self.graph.ids)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) the session's optimised keyframe poses, in its own frame."""
        return self.graph.poses

    def gt_poses(self) -> np.ndarray | None:
        """(N, 4, 4) world ground truth of every keyframe, or None when some keyframe has none."""
        gt = self.places.gt_poses
        if any(k not in gt for k in range(len(self))):
            return None
        return np.array([gt[k] for k in range(len(self))])

    @classmethod
    def load(cls, name: str, log: str, folder: Path, vpr: VPRConfig) -> SessionMap:
        """Read a `run`'s results folder (database/ and pose_graph.g2o)."""
        database, graph_file = folder / "database", folder / "pose_graph.g2o"
        if not (database / "manifest.json").is_file() or not graph_file.is_file():
            raise SessionMapError(
                f"session {name} ({log}): {folder} holds no place database or pose graph "
                "(the run ended before recognition started?)"
            )
        places = PriorMap.load(database, vpr)
        graph = read_pose_graph(graph_file)
        if graph.ids != tuple(range(len(graph.ids))):
            raise SessionMapError(f"session {name}: {graph_file}: keyframe vertices are not 0..N-1")
        if len(places) != len(graph.ids) or any(p.frame_id != k for k, p in enumerate(places.database.places)):
            raise SessionMapError(
                f"session {name}: {folder}: its {len(places)} places are not its {len(graph.ids)} keyframes in order"
            )
        return cls(name, log, folder, places, graph)
