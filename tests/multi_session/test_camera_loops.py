"""Camera-only sessions in a map: the kept images a saved session carries (`KeptImages`), how a
loop between two such sessions is verified (`register_cross_views`: the deep two views or
nothing), the agreement rule on loops whose translation is a zero place prior, and a run's loop
to a camera-only prior map registered by two views."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.detector import LoopDetector, LoopProposal
from loopclosure.encoder import PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, PCAProjection
from ssmvpr_slam.backend.config import LoopRegistrationConfig
from ssmvpr_slam.backend.g2o_io import GraphEdge, PoseGraphData
from ssmvpr_slam.backend.loop_registration import LoopRegistrar, LoopRegistration
from ssmvpr_slam.backend.noise import sigmas6
from ssmvpr_slam.backend.se3 import invert, make_pose, rot_z
from ssmvpr_slam.backend.two_view import ReducedImage, reduce_image
from ssmvpr_slam.config.map import MapConfig
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.loop_policy import LoopPolicy
from ssmvpr_slam.multi_session.cross_loops import CrossLoop, register_cross_views, views_verifier
from ssmvpr_slam.multi_session.linking import link_sessions
from ssmvpr_slam.multi_session.session_map import SessionMap
from ssmvpr_slam.prior_map import IMAGES_FILE, KeptImages, PriorMap, save_map
from ssmvpr_slam.results.writers import kept_images
from ssmvpr_slam.run_result import Keyframe

Image = np.ndarray | ReducedImage


def _image(seed: int, width: int = 64, height: int = 48) -> ReducedImage:
    pixels = np.random.default_rng(seed).integers(0, 256, (height * 2, width * 2), dtype=np.uint8)
    return reduce_image(pixels, width * height)


def _projection(dim_in: int, dim: int, seed: int) -> PCAProjection:
    rng = np.random.default_rng(seed)
    components = np.linalg.qr(rng.standard_normal((dim_in, dim)))[0].T.astype(np.float32)
    return PCAProjection(
        rng.standard_normal(dim_in).astype(np.float32), components, np.ones(dim, np.float32), False, True
    )


def _saved_map(folder: Path, images: KeptImages | None) -> Path:
    vpr = load_config().vpr
    rng = np.random.default_rng(0)
    database = PlaceDatabase(Codebooks(_projection(30, 8, 1), _projection(20, 6, 2)), vpr.database)
    codes = PlaceCodes(
        rng.standard_normal((4, 16, 8)).astype(np.float32), rng.standard_normal((4, 3, 4, 6)).astype(np.float32)
    )
    database.add(codes, [PlaceInfo(frame_id=i, timestamp=float(i)) for i in range(4)])
    save_map(folder, database, vpr, {i: np.eye(4) for i in range(4)}, {}, {}, images)
    return folder


def _kept() -> KeptImages:
    camera = (160.0, 161.0, 159.5, math.nan, 90.0)  # cy left to the image size
    return KeptImages({0: _image(0), 2: _image(2)}, {2: _image(12)}, {0: camera, 2: camera})


# ------------------------------------------------------------------------------ saved images


def test_a_saved_map_keeps_its_places_images_and_their_calibration(tmp_path: Path) -> None:
    kept = _kept()
    prior = PriorMap.load(_saved_map(tmp_path / "map", kept), load_config().vpr)
    assert prior.images.front == kept.front and prior.images.rear == kept.rear  # PNG bytes, kept and full sizes
    assert prior.images.cameras.keys() == kept.cameras.keys()
    np.testing.assert_array_equal(list(prior.images.cameras.values()), list(kept.cameras.values()))  # NaN: unset
    two_view = prior.images.two_view(2, load_config().backend.registration.two_view)
    assert (two_view.fx, two_view.fy, two_view.cx, two_view.cy, two_view.hfov_deg) == (160.0, 161.0, 159.5, None, 90.0)
    default = load_config().backend.registration.two_view
    assert prior.images.two_view(1, default) is default  # a place kept without images: as configured
    assert not PriorMap.load(_saved_map(tmp_path / "lidar", None), load_config().vpr).images
    assert not (tmp_path / "lidar" / IMAGES_FILE).exists()


def test_a_merged_map_moves_each_sessions_images_to_its_places() -> None:
    merged = KeptImages()
    merged.update(_kept())
    merged.update(_kept().moved(4))
    assert sorted(merged.front) == [0, 2, 4, 6] and sorted(merged.rear) == [2, 6]
    assert merged.front[6] == merged.front[2] and merged.cameras[4] == merged.cameras[0]


def test_a_run_saves_the_images_of_its_keyframes_without_a_scan() -> None:
    config = load_config(None, {"backend": {"registration": {"two_view": {"fx": 150.0}}}})
    pose = np.eye(4)
    keyframes = [Keyframe(0, 0, 0.0, pose, None, None, _image(0), _image(1)), Keyframe(1, 2, 1.0, pose, None, None, None)]  # fmt: skip
    kept = kept_images(keyframes, {0: 5, 1: 6}, config)
    assert kept.front == {5: keyframes[0].image} and kept.rear == {5: keyframes[0].rear_image}
    assert kept.cameras[5][0] == 150.0 and math.isnan(kept.cameras[5][2]) and list(kept.cameras) == [5]


def _truncated(folder: Path) -> None:
    path = folder / IMAGES_FILE
    path.write_bytes(path.read_bytes()[:300])


def _not_a_png(folder: Path) -> None:
    with np.load(folder / IMAGES_FILE) as data:
        arrays = dict(data)
    arrays["front2"] = np.frombuffer(b"not a png at all", np.uint8)
    np.savez(folder / IMAGES_FILE, **arrays)


def _unknown_place(folder: Path) -> None:
    with np.load(folder / IMAGES_FILE) as data:
        arrays = dict(data)
    arrays["front_places"] = np.array([0, 9])
    arrays["front9"] = arrays.pop("front2")
    np.savez(folder / IMAGES_FILE, **arrays)


def _bad_focal(folder: Path) -> None:
    with np.load(folder / IMAGES_FILE) as data:
        arrays = dict(data)
    arrays["cameras"][0, 0] = -1.0
    np.savez(folder / IMAGES_FILE, **arrays)


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (_truncated, "cannot read the prior map's images"),
        (_not_a_png, "front image of place 2: not a grey 8-bit PNG"),
        (_unknown_place, "images of unknown places: [9]"),
        (_bad_focal, "intrinsics"),
    ],
)
def test_a_damaged_images_file_is_refused_in_one_line_naming_it(tmp_path: Path, damage, words: str) -> None:  # noqa: ANN001
    folder = _saved_map(tmp_path / "map", _kept())
    damage(folder)
    with pytest.raises(LoopClosureInputError) as caught:
        PriorMap.load(folder, load_config().vpr)
    message = str(caught.value)
    assert str(folder / IMAGES_FILE) in message and words in message and "\n" not in message, message


# ------------------------------------------------------------------------------ verifying a loop


class _Registrar(LoopRegistrar):
    """Says what the two views gave without computing them; records what it was asked."""

    def __init__(self, method: str) -> None:
        super().__init__(LoopRegistrationConfig(), verifier=object())  # type: ignore[arg-type]  # never called
        self.method = method
        self.asked: list[tuple[Image, Image, float]] = []

    def register_images(
        self, query_image: Image, match_image: Image, yaw_guess: float = 0.0, query_yaw_offset: float = 0.0
    ) -> LoopRegistration:
        self.asked.append((query_image, match_image, query_yaw_offset))
        sigmas = sigmas6(0.05, 2.0)
        return LoopRegistration(make_pose(rot_z(0.1), np.zeros(3)), True, "the views", 0.8, math.nan, sigmas,
                                method=self.method)  # fmt: skip


def _camera_session(name: str, n: int, seed: int, scans: bool = False) -> SessionMap:
    """A session of `n` places that kept images (forward and rear), or scans instead."""
    if scans:
        places = PriorMap(None, scans={k: np.zeros((10, 3)) for k in range(n)})  # type: ignore[arg-type]
    else:
        front, rear = {k: _image(seed + k) for k in range(n)}, {k: _image(seed + 100 + k) for k in range(n)}
        places = PriorMap(None, images=KeptImages(front, rear))  # type: ignore[arg-type]  # no codes: not read
    graph = PoseGraphData(3, tuple(range(n)), np.tile(np.eye(4), (n, 1, 1)), ())
    return SessionMap(name, f"{name}.mcap", Path(name), places, graph)


def _proposal(query_kf: int, match_kf: int, camera: Literal["front", "rear"] = "front") -> LoopProposal:
    return LoopProposal(query_kf, match_kf, match_kf, 0.9, 0.5, 0, 0.1, True, "accepted", camera=camera)


def test_only_the_deep_two_views_verify_a_loop_between_sessions() -> None:
    a, b = _camera_session("a", 5, 0), _camera_session("b", 5, 50)
    deep = _Registrar("two_view_deep")
    verified = register_cross_views(b, 3, a, 1, _proposal(3, 1), deep)
    assert verified.accepted and verified.method == "two_view_deep"
    assert deep.asked == [(b.places.images.front[3], a.places.images.front[1], 0.0)]
    # what a run falls back to when the views do not verify is no verification between sessions
    for method in ("yaw_prior", "two_view_essential"):
        refused = register_cross_views(b, 3, a, 1, _proposal(3, 1), _Registrar(method))
        assert not refused.accepted and refused.method == "unverified", method
        assert "two views did not verify it (the views)" in refused.reason and np.isnan(refused.sigmas).all()


def test_a_rear_match_registers_the_query_rear_image_against_the_place_forward_one() -> None:
    a, b = _camera_session("a", 5, 0), _camera_session("b", 5, 50)
    deep = _Registrar("two_view_deep")
    assert register_cross_views(b, 2, a, 4, _proposal(2, 4, "rear"), deep).accepted
    assert deep.asked == [(b.places.images.rear[2], a.places.images.front[4], math.pi)]


def test_without_images_or_a_verifier_a_loop_between_sessions_stays_unverified() -> None:
    camera, lidar = _camera_session("a", 5, 0), _camera_session("b", 5, 50, scans=True)
    registration = register_cross_views(lidar, 1, camera, 1, _proposal(1, 1), _Registrar("two_view_deep"))
    assert not registration.accepted and "no kept scans nor images on both sides" in registration.reason
    no_verifier = LoopRegistrar(LoopRegistrationConfig())
    registration = register_cross_views(camera, 1, _camera_session("c", 5, 9), 1, _proposal(1, 1), no_verifier)
    assert not registration.accepted and "two_view.method: deep" in registration.reason


def test_a_lidar_map_loads_no_backbone_for_two_views() -> None:
    config = load_config()
    lidar = [_camera_session("a", 3, 0, scans=True), _camera_session("b", 3, 5, scans=True)]
    assert views_verifier(0, lidar, config) is None
    mixed = [_camera_session("a", 3, 0), lidar[1]]  # nothing of the other session's to compare with
    assert views_verifier(0, mixed, config) is None
    orb = load_config(None, {"backend": {"registration": {"two_view": {"method": "orb"}}}})
    assert views_verifier(0, [_camera_session("a", 3, 0), _camera_session("b", 3, 5)], orb) is None


# ------------------------------------------------------------------------------ joining by camera loops


def _street(n: int, start_x: float, lateral: float, step: float) -> np.ndarray:
    return np.array([make_pose(rot_z(0.0), np.array([start_x + step * k, lateral, 0.0])) for k in range(n)])


def _posed_session(name: str, world: np.ndarray) -> SessionMap:
    own = np.array([invert(world[0]) @ p for p in world])
    edges = tuple(GraphEdge(k, k + 1, invert(own[k]) @ own[k + 1], np.eye(6)) for k in range(len(own) - 1))
    graph = PoseGraphData(3, tuple(range(len(own))), own, edges)
    return SessionMap(name, f"{name}.mcap", Path(name), None, graph)  # type: ignore[arg-type]  # places: not read


def _camera_loop(worlds: list[np.ndarray], query_kf: int, accepted: bool = True) -> CrossLoop:
    """A loop of session 1 to session 0's nearest keyframe as two views give it: the true
    rotation, no translation (the place prior), whatever the keyframes' real offset."""
    match_kf = int(np.argmin(np.linalg.norm(worlds[0][:, :3, 3] - worlds[1][query_kf, :3, 3], axis=1)))
    true = invert(worlds[0][match_kf]) @ worlds[1][query_kf]
    method = "two_view_deep" if accepted else "unverified"
    registration = LoopRegistration(make_pose(true[:3, :3], np.zeros(3)), accepted, "views", 0.8, math.nan,
                                    sigmas6(0.05, 2.0), method=method)  # fmt: skip
    return CrossLoop(1, query_kf, 0, match_kf, _proposal(query_kf, match_kf), registration)


def test_camera_loops_join_two_sessions_only_when_enough_of_them_agree() -> None:
    """The place prior's zero translation errs by the keyframes' real offset: a lane (1.8 m)
    across and up to 2 m along (keyframes 4 and 3.7 m apart), 2.7 m at most. The offsets the loops
    imply scatter by as much, within `map.agree_translation_m` (3 m) of the middle ones: three
    such loops join the sessions; two, or unverified ones, leave them apart."""
    worlds = [_street(25, 0.0, 0.0, 4.0), _street(12, 30.0, 1.8, 3.7)]
    sessions = [_posed_session("a", worlds[0]), _posed_session("b", worlds[1])]
    loops = [_camera_loop(worlds, q) for q in (0, 3, 6, 9)]
    ignored = [np.linalg.norm(worlds[1][lp.query_kf, :3, 3] - worlds[0][lp.match_kf, :3, 3]) for lp in loops]
    assert max(ignored) > 2.5 and min(ignored) < 2.0
    joined = link_sessions(loops, sessions, MapConfig())
    assert joined.components == [[0, 1]] and joined.links[0].loops == (0, 1, 2, 3)
    truth = invert(worlds[0][0]) @ worlds[1][0]
    assert np.linalg.norm(joined.frames[1][:3, 3] - truth[:3, 3]) < 2.5  # off by the offsets the priors ignore
    apart = link_sessions(loops[1:3], sessions, MapConfig())
    assert apart.components == [[0], [1]] and apart.unjoined_pairs == {(0, 1): 2}
    unverified = [_camera_loop(worlds, q, accepted=False) for q in (1, 2, 4)]
    assert link_sessions([*loops[1:3], *unverified], sessions, MapConfig()).components == [[0], [1]]


# ------------------------------------------------------------------------------ run --map on a camera-only map


def _policy(tmp_path: Path, method: str) -> tuple[LoopPolicy, PriorMap, _Registrar]:
    config = load_config()
    prior = PriorMap.load(_saved_map(tmp_path / "map", _kept()), config.vpr)
    policy = LoopPolicy(config, LoopDetector(config.vpr, config.detector, None, prior.database), prior)
    policy.registrar = registrar = _Registrar(method)
    return policy, prior, registrar


@pytest.mark.parametrize("camera", ["front", "rear"])
def test_a_run_registers_a_loop_to_a_camera_only_map_by_two_views(tmp_path: Path, camera: str) -> None:
    """The keyframe's image (its rear one for a rear match) against the place's kept forward image,
    as a run registers a loop within itself; not the yaw prior a map without images gives."""
    policy, prior, registrar = _policy(tmp_path, "two_view_deep")
    kf = Keyframe(0, 0, 0.0, np.eye(4), None, None, _image(30), _image(31))
    proposal = replace(_proposal(0, 2, camera), prior_map=True)  # type: ignore[arg-type]
    registration = policy.register(kf, proposal, [kf], [], 0.0)
    assert registration.accepted and registration.method == "two_view_deep"
    query = kf.rear_image if camera == "rear" else kf.image
    assert registrar.asked == [(query, prior.images.front[2], math.pi if camera == "rear" else 0.0)]
