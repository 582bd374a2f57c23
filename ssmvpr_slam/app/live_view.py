"""A live view of a run: the trajectory, the loop edges, the current keyframe and its match, as
they happen, in a web page the run serves itself (viser).

Why viser: the view is a page any browser opens (http://localhost:8080, or through an SSH tunnel
from the robot), served by the run's own process from a pure-Python package, with no viewer to
install beside it; it draws 3D lines, frames and images. Foxglove (through `trajectory.mcap`,
which every run writes) is the place to study a run afterwards; Rerun needs its own viewer
application or a WebGPU page.

Drawn, in the odometry's world frame (z up):
- /slam/odometry: the odometry's keyframe path (grey);
- /slam/optimised: iSAM2's current estimate of it (blue);
- /slam/loops: every loop factor in the graph, between its two keyframes on the odometry's path,
  where it spans the drift it takes out (green);
- /slam/keyframe: the newest keyframe's pose, with its camera image on a frustum;
- /slam/match: the keyframe the newest accepted loop matched, with its image (orange);
- a text panel with the counts (keyframes, loops proposed, accepted, in the graph).

The view is redrawn after a keyframe at most every `min_interval_s` (the estimate of a long
run's graph is not free to read); the run's last state is drawn when it ends.
"""

from __future__ import annotations

import contextlib
import io
import time
from typing import Any

import cv2
import numpy as np

from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.run_result import Keyframe
from ssmvpr_slam.run_state import RunState

_GREY, _BLUE, _GREEN, _ORANGE = (150, 150, 150), (30, 100, 230), (20, 180, 60), (240, 140, 20)
# an OpenCV camera (z forward, x right, y down) looking along the body's x (forward), y left, z up
_CAMERA_IN_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class LiveViewError(SlamError, RuntimeError):
    """The live view could not start (viser missing, nothing to serve on: a taken port is not this, viser
    takes the next free one and the run prints where)."""


class LiveView:
    """Serves the view on `host:port`; `update(state, graph)` after each keyframe, `close()` at the end."""

    def __init__(self, port: int = 8080, host: str = "127.0.0.1", min_interval_s: float = 0.25) -> None:
        try:
            import viser
        except ImportError:
            raise LiveViewError(
                "--viewer needs viser: pip install 'ssmvpr-slam[viewer]' (or pip install 'viser>=1.1,<2')"
            ) from None
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # its banner: the run says where the view is
                self.server = viser.ViserServer(host=host, port=port, verbose=False)
        except OSError as exc:
            raise LiveViewError(f"--viewer: cannot serve on {host}:{port} ({exc.strerror or exc})") from None
        self.url = f"http://{host}:{self.server.get_port()}"
        self.min_interval_s = min_interval_s
        self._last = -np.inf
        self._drawn_keyframes = 0
        self._panel = self.server.gui.add_markdown("**ssmvpr-slam**: waiting for the first keyframe")
        self.server.scene.set_up_direction("+z")
        self._framed: dict[int, float] = {}  # client id -> the path's extent when its camera was last set
        self._scale = 3.0  # metres: a keyframe's camera, drawn a twentieth of the path's extent

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    def update(self, state: RunState, graph: Any, force: bool = False) -> bool:
        """Redraw from the run's state and graph if a keyframe came since, and not more often
        than `min_interval_s` unless `force`; whether it redrew."""
        n = len(state.keyframes)
        now = time.monotonic()
        if n == self._drawn_keyframes or (not force and now - self._last < self.min_interval_s):
            return False
        self._last, self._drawn_keyframes = now, n
        estimate = graph.optimized_poses() if n else {}
        self._draw(state, estimate)
        return True

    def _draw(self, state: RunState, estimate: dict[int, np.ndarray]) -> None:
        scene = self.server.scene
        kfs = state.keyframes
        odometry = np.array([k.odom_pose[:3, 3] for k in kfs], np.float32)
        optimised = np.array([estimate.get(k.id, k.odom_pose)[:3, 3] for k in kfs], np.float32)
        if len(kfs) >= 2:
            self._frame(optimised)
            scene.add_line_segments(
                "/slam/odometry", _segments(odometry), _GREY, thickness=2.0, thickness_units="screen"
            )
            scene.add_line_segments("/slam/optimised", _segments(optimised), _BLUE, thickness=3.0,
                                    thickness_units="screen")  # fmt: skip
        in_graph = [r for r in state.loops if r.factor_handle is not None and not r.proposal.prior_map]
        if in_graph:  # on the odometry's path: a loop spans what it corrects
            ends = np.array([[odometry[r.proposal.match_id], odometry[r.proposal.query_id]] for r in in_graph])
            scene.add_line_segments("/slam/loops", ends.astype(np.float32), _GREEN, thickness=3.0,
                                    thickness_units="screen")  # fmt: skip
        if kfs:
            latest = kfs[-1]
            self._keyframe("/slam/keyframe", latest, estimate.get(latest.id, latest.odom_pose), _BLUE)
        accepted = [r for r in state.loops if r.proposal.accepted and not r.proposal.prior_map]
        if accepted:
            match = kfs[accepted[-1].proposal.match_id]
            self._keyframe("/slam/match", match, estimate.get(match.id, match.odom_pose), _ORANGE)
        self._panel.content = (
            f"**ssmvpr-slam**: {len(kfs)} keyframes, {state.frames_seen} frames  \n"
            f"loops: {len(state.loops)} proposed, {len(accepted)} accepted, {len(in_graph)} in the graph"
        )

    def _frame(self, path: np.ndarray) -> None:
        """Look down on the whole path: the view a new client opens with (and "Reset View"), and
        the camera of a client whose view the path has outgrown twice over since it was set."""
        low, high = path.min(axis=0), path.max(axis=0)
        centre, extent = (low + high) / 2, max(float(np.max(high - low)), 10.0)
        self._scale = max(3.0, extent / 20)
        position = centre + np.array([0.0, -0.5 * extent, 1.1 * extent])
        self.server.initial_camera.position = position
        self.server.initial_camera.look_at = centre
        for client_id, client in self.server.get_clients().items():
            if extent > 2.0 * self._framed.get(client_id, 0.0):
                client.camera.position = position
                client.camera.look_at = centre  # after the position: setting it alone keeps the view's direction
                self._framed[client_id] = extent

    def _keyframe(self, name: str, kf: Keyframe, pose: np.ndarray, color: tuple[int, int, int]) -> None:
        """A keyframe's body pose, and its camera (looking along body x) with its thumbnail."""
        wxyz = _wxyz(pose[:3, :3])
        scene = self.server.scene
        scene.add_frame(
            name, wxyz=wxyz, position=pose[:3, 3], axes_length=self._scale / 2, axes_radius=self._scale / 40
        )
        image = _thumbnail(kf)
        if image is not None:
            scene.add_camera_frustum(f"{name}/camera", fov=np.pi / 2, aspect=image.shape[1] / image.shape[0],
                                     scale=self._scale, color=color, image=image, format="jpeg", jpeg_quality=80,
                                     wxyz=_wxyz(_CAMERA_IN_BODY), position=(0.0, 0.0, 0.0))  # fmt: skip

    def close(self) -> None:
        self.server.stop()


def _segments(points: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N-1, 2, 3): consecutive points joined."""
    return np.stack([points[:-1], points[1:]], axis=1)


def _wxyz(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def _thumbnail(kf: Keyframe) -> np.ndarray | None:
    if not kf.thumbnail:
        return None
    image = cv2.imdecode(np.frombuffer(kf.thumbnail, np.uint8), cv2.IMREAD_COLOR)
    return None if image is None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
