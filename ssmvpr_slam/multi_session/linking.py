"""Which sessions join, and where one lies in the other's frame.

Every verified loop q (session b) -> m (session a) says where b's frame lies in a's:
T_ab = P_a[m] @ T_mq @ inv(P_b[q]), with each session's own optimised poses. True loops of a
pair agree on it (within what each session's own drift allows); a wrong loop that ICP still
aligned (a look-alike street corner) says something else. A pair is joined only when at
least `min_agreeing_loops` loops agree, and only those loops go into the graph: two sessions
that met through one or two lone loops stay apart, reported as separate maps, never forced
together. Joined pairs make connected components; each is one map, in the frame of its
first session, and every verified loop between two of its sessions goes into its graph, where
the robust solve judges it (`graph_loops`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ssmvpr_slam.backend.se3 import invert, yaw_of
from ssmvpr_slam.config.map import MapConfig
from ssmvpr_slam.multi_session.cross_loops import CrossLoop
from ssmvpr_slam.multi_session.session_map import SessionMap


@dataclass(frozen=True)
class SessionLink:
    """Sessions `a` < `b` joined: `T_ab` places b's frame in a's; `loops` agreed on it,
    `disagreeing` were verified but said otherwise (indices into the cross-loop list)."""

    a: int
    b: int
    T_ab: np.ndarray
    loops: tuple[int, ...]
    disagreeing: tuple[int, ...]


@dataclass
class SessionLinks:
    """The links, the loops kept, and the components (largest first), each with every
    session's frame in the component's (its first session's) frame."""

    links: list[SessionLink]
    kept: set[int]
    """The loops that agreed on a join (the `linked` column of cross_session_loops.csv)."""
    components: list[list[int]]
    frames: dict[int, np.ndarray] = field(default_factory=dict)
    unjoined_pairs: dict[tuple[int, int], int] = field(default_factory=dict)
    """Pairs with verified loops too few or too scattered to join them: how many loops."""


def graph_loops(loops: list[CrossLoop], links: SessionLinks) -> list[int]:
    """The loops that go into the graphs: every verified loop between two sessions of one map,
    not only those that agreed on the join. The agreement decides *whether* two sessions are one
    map (and gives the graph its start); within a map the robust solve decides which loops hold.
    (Loops of one street stretch agree with each other; a second stretch, further along either
    session's drift, implies a slightly other offset, yet its loops are as right.)"""
    component = {s: c for c, members in enumerate(links.components) for s in members}
    return [k for k, loop in enumerate(loops) if loop.verified and component[loop.query] == component[loop.match]]


def loop_offset(loop: CrossLoop, sessions: list[SessionMap]) -> tuple[int, int, np.ndarray]:
    """(a, b, T_ab) with a < b: where the loop puts session b's frame in session a's."""
    m_pose = sessions[loop.match].poses[loop.match_kf]
    q_pose = sessions[loop.query].poses[loop.query_kf]
    T_match_query = m_pose @ loop.registration.T_mq @ invert(q_pose)
    if loop.match < loop.query:
        return loop.match, loop.query, T_match_query
    return loop.query, loop.match, invert(T_match_query)


def _agreeing(offsets: list[np.ndarray], config: MapConfig) -> list[int]:
    """The largest set of offsets that agree with one of them (its own neighbourhood)."""
    best: list[int] = []
    max_yaw = math.radians(config.agree_yaw_deg)
    for centre in offsets:
        near = [
            k
            for k, other in enumerate(offsets)
            if np.linalg.norm(other[:3, 3] - centre[:3, 3]) < config.agree_translation_m
            and abs(math.remainder(yaw_of(other) - yaw_of(centre), 2 * math.pi)) < max_yaw
        ]
        if len(near) > len(best):
            best = near
    return best


def _mean_offset(offsets: list[np.ndarray]) -> np.ndarray:
    """The offsets' mean: translations averaged, rotation the chordal mean projected to SO(3)."""
    u, _, vt = np.linalg.svd(sum(o[:3, :3] for o in offsets))
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.mean([o[:3, 3] for o in offsets], axis=0)
    return out


def link_sessions(loops: list[CrossLoop], sessions: list[SessionMap], config: MapConfig) -> SessionLinks:
    """Join the pairs whose verified loops agree; components and frames from the joins."""
    by_pair: dict[tuple[int, int], list[tuple[int, np.ndarray]]] = {}
    for index, loop in enumerate(loops):
        if loop.verified:
            a, b, offset = loop_offset(loop, sessions)
            by_pair.setdefault((a, b), []).append((index, offset))
    links: list[SessionLink] = []
    kept: set[int] = set()
    unjoined: dict[tuple[int, int], int] = {}
    for (a, b), items in sorted(by_pair.items()):
        agreeing = _agreeing([offset for _, offset in items], config)
        if len(agreeing) < config.min_agreeing_loops:
            unjoined[(a, b)] = len(items)
            continue
        chosen = [items[k] for k in agreeing]
        T_ab = _mean_offset([offset for _, offset in chosen])
        loop_ids = tuple(index for index, _ in chosen)
        others = tuple(index for k, (index, _) in enumerate(items) if k not in agreeing)
        links.append(SessionLink(a, b, T_ab, loop_ids, others))
        kept.update(loop_ids)
    components, frames = _components(len(sessions), links, sessions)
    return SessionLinks(links, kept, components, frames, unjoined)


def _components(
    n: int, links: list[SessionLink], sessions: list[SessionMap]
) -> tuple[list[list[int]], dict[int, np.ndarray]]:
    """Connected components (most keyframes first), and each session's frame in its component's
    first session's frame, along a breadth-first tree of the links."""
    neighbours: dict[int, list[tuple[int, np.ndarray]]] = {k: [] for k in range(n)}
    for link in links:
        neighbours[link.a].append((link.b, link.T_ab))
        neighbours[link.b].append((link.a, invert(link.T_ab)))
    seen: set[int] = set()
    components, frames = [], {}
    for root in range(n):
        if root in seen:
            continue
        frames[root] = np.eye(4)
        component, queue = [root], deque([root])
        seen.add(root)
        while queue:
            here = queue.popleft()
            for there, T in neighbours[here]:
                if there not in seen:
                    seen.add(there)
                    frames[there] = frames[here] @ T
                    component.append(there)
                    queue.append(there)
        components.append(sorted(component))
    components.sort(key=lambda c: (-sum(len(sessions[k]) for k in c), c[0]))
    return components, frames
