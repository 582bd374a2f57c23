"""More bad input, each refused as one line naming the input (docs/robustness.md, "Bad input policy"):

- a damaged checkpoint given to `run --resume` (cut-short .npz files, a missing array, NaN or
  misshapen poses, keyframe ids out of order, checkpoint.json fields of the wrong type or out of
  range, loop records a restore could not replay): a CheckpointError naming the file;
- seeds outside 0 .. 2**32 - 1 (what numpy and sklearn take), in a config variable or `--seed`;
- a KITTI calib.txt whose Tr is not a rigid transform, or is not text;
- a `--map` whose places.json holds a pose that is not rigid, a timestamp that is not a number
  or a name that is not a string.

The checkpoint here is written by `write_checkpoint` from a small made-up run (5 keyframes, one
loop factor), so every case costs milliseconds; the CLI cases check the exit status and the
absence of a traceback on a few of them.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: E402, F401
from pydantic import ValidationError

from frontend.config import DriftConfig
from frontend.errors import FrontendInputError
from frontend.simulation.config import SimulationConfig
from frontend.sources.kitti_source import KittiSource
from loopclosure.config import PCAConfig
from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.detector import LoopProposal
from loopclosure.encoder import PlaceCodes
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, PCAProjection
from ssmvpr_common.trajectory_io import write_kitti
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.backend.two_view import ReducedImage
from ssmvpr_slam.checkpoint.loading import load_checkpoint
from ssmvpr_slam.checkpoint.saving import CheckpointError, CheckpointMeta, write_checkpoint
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.prior_map import PriorMap, save_map
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult, StreamEnd, latency_summary

N = 5  # keyframes of the made-up run
FRAMES_SEEN = 12


def _projection(dim_in: int, dim: int, seed: int) -> PCAProjection:
    rng = np.random.default_rng(seed)
    components = np.linalg.qr(rng.standard_normal((dim_in, dim)))[0].T.astype(np.float32)
    return PCAProjection(
        rng.standard_normal(dim_in).astype(np.float32), components, np.ones(dim, np.float32), False, True
    )


def _database(vpr, places: int) -> PlaceDatabase:  # noqa: ANN001
    rng = np.random.default_rng(0)
    db = PlaceDatabase(Codebooks(_projection(30, 8, 1), _projection(20, 6, 2)), vpr.database)
    codes = PlaceCodes(
        rng.standard_normal((places, 16, 8)).astype(np.float32),
        rng.standard_normal((places, 3, 4, 6)).astype(np.float32),
    )
    db.add(codes, [PlaceInfo(frame_id=i, timestamp=float(i), extra={"session": "current"}) for i in range(places)])
    return db


# ------------------------------------------------------------------------------ checkpoints


def _write_valid_checkpoint(run_folder: Path) -> Path:
    """A checkpoint of a made-up run: 5 keyframes (frames 0, 2, .., 8 of 12), one loop 4 -> 1
    with its factor (handle 0), one rejected proposal, grey copies and a thumbnail."""
    config = load_config()
    config.results.plots = False
    config.vpr.filtering.pca.dim, config.vpr.spatial.pca.dim = 8, 6  # the made-up database's codes
    poses = np.tile(np.eye(4), (N, 1, 1))
    poses[:, 0, 3] = np.arange(N, dtype=float)
    grey = (np.arange(48 * 64).reshape(48, 64) % 251).astype(np.uint8)
    ok, png = cv2.imencode(".png", grey)
    ok2, jpeg = cv2.imencode(".jpg", np.dstack([grey] * 3))
    assert ok and ok2
    image = ReducedImage.from_png(png.tobytes(), 64, 48)
    kfs = tuple(
        Keyframe(k, 2 * k, 0.4 * k, poses[k], poses[k], None, image, thumbnail=jpeg.tobytes() if k == 0 else None)
        for k in range(N)
    )
    registration = LoopRegistration(np.eye(4), True, "ok", 0.9, 0.05, np.full(6, 0.1), "two_view_essential")
    loops = (
        LoopRecord(LoopProposal(3, 0, 0, 0.2, 0.1, 0, 0.0, False, "score"), None, None),
        LoopRecord(LoopProposal(4, 1, 1, 0.9, 0.5, 0, 0.0, True, "accepted", "forward"), registration, 0),
    )
    timings = tuple({"backbone": 0.1, "total": 0.2} for _ in range(N))
    partial = RunResult(kfs, loops, np.arange(N) * 0.4, poses, poses, in_map_frame=poses, frames_seen=FRAMES_SEEN,
                        frames_skipped={"no camera image": 1}, timings=timings,
                        ending=StreamEnd(interrupted=True, seconds=3.5), database=_database(config.vpr, N),
                        session_places={k: k for k in range(N)})  # fmt: skip
    state = {"prior_places": np.array(0, np.int64), "session_travelled": np.arange(N, dtype=float)}
    meta = CheckpointMeta("log.mcap", {"kind": "file", "size": 1, "sha256": "0"}, None, "run")
    run_folder.mkdir(parents=True, exist_ok=True)
    return write_checkpoint(run_folder, partial, state, config, meta)


@pytest.fixture(scope="module")
def valid_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_valid_checkpoint(tmp_path_factory.mktemp("checkpoint") / "run").parent


def _copy(valid: Path, tmp: Path) -> SimpleNamespace:
    run = tmp / "run"
    shutil.copytree(valid, run, symlinks=True)
    return SimpleNamespace(run=run, folder=(run / "checkpoint").resolve())


def _npz(name: str, edit: Callable[[dict[str, np.ndarray]], None]) -> Callable[[Path], str]:
    def apply(folder: Path) -> str:
        with np.load(folder / name) as data:
            arrays = dict(data)
        edit(arrays)
        np.savez(folder / name, **arrays)  # type: ignore[arg-type]
        return name

    return apply


def _set(key: str, index: tuple, value: float) -> Callable[[dict[str, np.ndarray]], None]:  # type: ignore[type-arg]
    def edit(arrays: dict[str, np.ndarray]) -> None:
        arrays[key] = arrays[key].copy()
        arrays[key][index] = value

    return edit


def _replace(key: str, value: np.ndarray | None) -> Callable[[dict[str, np.ndarray]], None]:
    def edit(arrays: dict[str, np.ndarray]) -> None:
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value

    return edit


def _cut(name: str) -> Callable[[Path], str]:
    def apply(folder: Path) -> str:
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: len(data) // 2])
        return name

    return apply


def _json_file(name: str, edit: Callable[[Any], None]) -> Callable[[Path], str]:
    """Edit a folder's JSON file `name` in place (checkpoint.json, a map's places.json)."""

    def apply(folder: Path) -> str:
        data = json.loads((folder / name).read_text())
        edit(data)
        (folder / name).write_text(json.dumps(data))
        return name

    return apply


def _record(edit: Callable[[dict], None]) -> Callable[[Path], str]:  # type: ignore[type-arg]
    return _json_file("checkpoint.json", edit)


def _field(key: str, value: object) -> Callable[[Path], str]:
    return _record(lambda r: r.__setitem__(key, value))


def _loop(index: int, part: str | None, **changes: object) -> Callable[[Path], str]:
    """Change loops[index] (part: "proposal", "registration", or None for the record itself)."""

    def edit(record: dict) -> None:  # type: ignore[type-arg]
        loop = record["loops"][index]
        (loop if part is None else loop[part]).update(changes)

    return _record(edit)


def _scaled_rotation(arrays: dict[str, np.ndarray]) -> None:
    arrays["odometry"] = arrays["odometry"].copy()
    arrays["odometry"][3, :3, :3] *= 2.0


def _lone_array(folder: Path) -> str:
    with open(folder / "keyframes.npz", "wb") as handle:
        np.save(handle, np.zeros(3))
    return "keyframes.npz"


def _not_utf8_config(folder: Path) -> str:
    (folder / "config.yaml").write_bytes(b"\xff\xfe" + (folder / "config.yaml").read_bytes())
    return "config.yaml"


def _edit_config(digest: bool) -> Callable[[Path], str]:
    """config.yaml's stage-I PCA dim 8 -> 4: with the digest checkpoint.json records (caught by
    it), or with the digest removed (a checkpoint of an older build: caught by the database)."""

    def apply(folder: Path) -> str:
        path = folder / "config.yaml"
        text = path.read_text()
        assert text.count("dim: 8") == 1
        path.write_text(text.replace("dim: 8", "dim: 4"))
        if not digest:
            record = json.loads((folder / "checkpoint.json").read_text())
            del record["config_sha256"]
            (folder / "checkpoint.json").write_text(json.dumps(record))
        return "config.yaml"

    return apply


CHECKPOINT_CASES: dict[str, tuple[Callable[[Path], str], str]] = {
    # name: (damage, returning the file the message must name; a fragment of the message)
    "keyframes_cut_short": (_cut("keyframes.npz"), "cannot read (BadZipFile"),
    "detector_cut_short": (_cut("detector.npz"), "cannot read (BadZipFile"),
    "keyframes_a_lone_array": (_lone_array, "not an .npz archive"),
    "keyframes_without_optimised": (_npz("keyframes.npz", _replace("optimised", None)), "lacks optimised"),
    "odometry_nan": (_npz("keyframes.npz", _set("odometry", (2, 0, 3), np.nan)), "odometry of keyframe 2: contains NaN"),
    "odometry_3x4": (_npz("keyframes.npz", lambda a: a.__setitem__("odometry", a["odometry"][:, :3])),
                     "odometry is float64 (5, 3, 4), expected float (5, 4, 4)"),
    "odometry_scaled": (_npz("keyframes.npz", _scaled_rotation), "odometry of keyframe 3: rotation is not orthonormal"),
    "optimised_nan": (_npz("keyframes.npz", _set("optimised", (1, 1, 1), np.nan)), "optimised poses contain NaN"),
    "gt_nan": (_npz("keyframes.npz", _set("gt", (0, 0, 0), np.nan)), "gt poses contain NaN"),
    "in_map_partly_nan": (_npz("keyframes.npz", _set("in_map_frame", (4, 0, 3), np.nan)), "in_map_frame must be all"),
    "ids_duplicate": (_npz("keyframes.npz", _set("ids", (3,), 2)), "keyframe ids must be 0..4 in order"),
    "ids_text": (_npz("keyframes.npz", _replace("ids", np.array(list("abcde")))), "ids is <U1 (5,), expected integer"),
    "ids_short": (_npz("keyframes.npz", lambda a: a.__setitem__("ids", a["ids"][:4])), "keyframes.npz holds 4"),
    "frame_index_backwards": (_npz("keyframes.npz", _set("frame_index", (2,), 1)), "frame_index must increase"),
    "frame_index_beyond_frames_seen": (_npz("keyframes.npz", _set("frame_index", (4,), 40)), "12 frames were seen"),
    "scan_lengths_off": (_npz("keyframes.npz", _set("scan_lengths", (1,), 7)), "as scan_lengths add up"),
    "image_size_zero": (_npz("keyframes.npz", _set("image_full_size", (2, 0), 0)), "image_full_size must be"),
    "timestamps_inf": (_npz("keyframes.npz", _set("timestamps", (0,), np.inf)), "timestamps contain NaN or inf"),
    "frames_seen_text": (_field("frames_seen", "many"), "frames_seen must be a whole number >= 0, got 'many'"),
    "frames_seen_negative": (_field("frames_seen", -4), "frames_seen must be a whole number >= 0, got -4"),
    "frames_seen_float": (_field("frames_seen", 12.5), "frames_seen must be a whole number"),
    "frames_seen_bool": (_field("frames_seen", True), "frames_seen must be a whole number"),
    "keyframes_text": (_field("keyframes", "5"), "keyframes must be a whole number"),
    "rear_keyframes_too_many": (_field("rear_keyframes", 6), "rear_keyframes must be at most keyframes (5)"),
    "seconds_nan": (_field("seconds", float("nan")), "seconds must be a number >= 0"),
    "frames_skipped_negative": (_field("frames_skipped", {"x": -1}), "frames_skipped must be an object"),
    "timings_text": (_field("timings", "x"), "timings must be a list of objects"),
    "timings_row_text": (_record(lambda r: r["timings"].__setitem__(1, {"total": "slow"})), "timings[1] must be"),
    "timings_row_other_stages": (_record(lambda r: r["timings"].__setitem__(2, {"gate": 0.1})), "timings[2] lacks stages timings[0] has"),
    "loops_an_object": (_field("loops", {"0": 1}), "loops must be a list of objects"),
    "log_a_number": (_field("log", 7), "log must be a string"),
    "prior_map_a_list": (_field("prior_map", []), "prior_map must be a path or null"),
    "a_misspelt_field": (_field("frames_sen", 12), "frames_sen is no field of a checkpoint record"),
    "prior_map_missing": (_record(lambda r: r.pop("prior_map")), "prior_map must be a path or null, got nothing"),
    "loop_handle_skips": (_loop(1, None, factor_handle=3), "factor_handle is 3, the graph would give 0"),
    "loop_query_unknown": (_loop(1, "proposal", query_id=99), "query keyframe 99 is not one of the 5 keyframes"),
    "loop_query_text": (_loop(0, "proposal", query_id="3"), "query_id must be a whole number"),
    "loop_match_after_query": (_loop(1, "proposal", match_id=4), "match keyframe 4 is not before query keyframe 4"),
    "loop_factor_not_accepted": (_loop(1, "registration", accepted=False), "a loop factor without an accepted"),
    "loop_T_mq_nan": (_loop(1, "registration", T_mq=[[float("nan")] * 4] * 4), "T_mq: contains NaN or inf"),
    "loop_sigmas_zero": (_loop(1, "registration", sigmas=[0.0] * 6), "sigmas must be finite and > 0"),
    "prior_places_too_many": (_npz("detector.npz", _replace("prior_places", np.array(9))), "prior_places must be"),
    "prior_places_text": (_npz("detector.npz", _replace("prior_places", np.array("x"))), "prior_places must be"),
    "config_not_utf8": (_not_utf8_config, "not UTF-8"),
    "config_edited": (_edit_config(digest=True), "changed after the checkpoint was written"),
    "config_dims_other_than_the_database": (_edit_config(digest=False), "PCA dims 4/6"),
}  # fmt: skip


def test_the_unbroken_checkpoint_loads(valid_checkpoint: Path) -> None:
    checkpoint = load_checkpoint(valid_checkpoint)
    result = checkpoint.result
    assert len(result.keyframes) == N and result.frames_seen == FRAMES_SEEN and result.frames_skipped
    assert [r.factor_handle for r in result.loops] == [None, 0] and result.keyframes[0].thumbnail
    assert result.in_map_frame is not None and len(result.timings) == N


def test_a_checkpoint_of_a_run_resumed_from_an_older_build_loads(valid_checkpoint: Path, tmp_path: Path) -> None:
    """Its first rows lack the stages added since (the front end's parts); the later rows have them."""
    copy = _copy(valid_checkpoint, tmp_path)

    def older_first_rows(record: dict) -> None:  # type: ignore[type-arg]
        for row in record["timings"][2:]:
            row.update(odometry=0.05, odometry_wait=0.06, keyframe_keeping=0.01)

    _record(older_first_rows)(copy.folder)
    timings = load_checkpoint(copy.run).result.timings
    assert "odometry" not in timings[0] and timings[-1]["odometry"] == 0.05
    assert latency_summary(timings)["odometry"]["median_s"] == pytest.approx(0.05)  # over the rows that have it
    assert latency_summary(timings)["total"]["median_s"] > 0  # the rest over every row


@pytest.mark.parametrize("case", sorted(CHECKPOINT_CASES))
def test_a_damaged_checkpoint_is_one_error_naming_its_file(case: str, valid_checkpoint: Path, tmp_path: Path) -> None:
    copy = _copy(valid_checkpoint, tmp_path)
    damage, fragment = CHECKPOINT_CASES[case]
    name = damage(copy.folder)
    with pytest.raises(CheckpointError) as caught:
        load_checkpoint(copy.run)
    message = str(caught.value)
    assert "\n" not in message and fragment in message, message
    assert str(copy.folder) in message and name.split(".")[0] in message, (name, message)


@pytest.mark.parametrize("case", ["keyframes_cut_short", "ids_duplicate", "frames_seen_text", "timings_text",
                                  "odometry_3x4", "frames_seen_negative"])  # fmt: skip
def test_resume_from_a_damaged_checkpoint_exits_2(case: str, valid_checkpoint: Path, tmp_path: Path) -> None:
    copy = _copy(valid_checkpoint, tmp_path)
    damage, fragment = CHECKPOINT_CASES[case]
    damage(copy.folder)
    log = tmp_path / "log.mcap"
    log.write_bytes(b"not read: the checkpoint is refused first")
    assert_user_error(invoke("run", log, "--resume", copy.run), str(copy.folder), fragment)


# -------------------------------------------------------------------------------------- seeds

SEED_VARIABLES = ["SSMVPR_SIMULATION__SEED", "SSMVPR_FRONTEND__ODOMETRY__LOGGED__DRIFT__SEED",
                  "SSMVPR_VPR__FILTERING__PCA__SEED", "SSMVPR_VPR__SPATIAL__PCA__SEED"]  # fmt: skip


@pytest.mark.parametrize("value", ["-1", "4294967296"])
@pytest.mark.parametrize("variable", SEED_VARIABLES)
def test_a_seed_out_of_range_in_a_variable_is_refused(variable: str, value: str, tmp_path: Path) -> None:
    out = tmp_path / "sim.mcap"
    result = invoke("simulate", "--frames", "2", "--out", out, env={variable: value})
    assert_user_error(result, variable, "seed")
    assert not out.exists()


@pytest.mark.parametrize("value", ["-1", "4294967296", "99999999999999999999"])
def test_a_seed_out_of_range_on_the_command_line_is_refused(value: str, tmp_path: Path) -> None:
    out = tmp_path / "sim.mcap"
    assert_user_error(invoke("simulate", "--frames", "2", "--seed", value, "--out", out), "seed", value)
    assert not out.exists()


@pytest.mark.parametrize("model", [SimulationConfig, DriftConfig, PCAConfig])
def test_seeds_take_what_numpy_and_sklearn_take(model: type) -> None:
    assert model(seed=0).seed == 0 and model(seed=2**32 - 1).seed == 2**32 - 1
    for bad in (-1, 2**32):
        with pytest.raises(ValidationError):
            model(seed=bad)


def test_the_largest_seed_simulates(tmp_path: Path) -> None:
    result = invoke("simulate", "--frames", "2", "--seed", str(2**32 - 1), "--out", tmp_path / "sim.mcap")
    assert result.exit_code == 0, result.output


# ------------------------------------------------------------------------------ KITTI calib.txt

# KITTI odometry sequence 00's Tr (velodyne -> camera 0), as calib.txt prints it
KITTI_00_TR = ("4.276802385584e-04 -9.999672484946e-01 -8.084491683470e-03 -1.198459927713e-02 "
               "-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
               "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01")  # fmt: skip


def _kitti_sequence(folder: Path, calib: bytes) -> Path:
    (folder / "image_2").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(3):
        assert cv2.imwrite(str(folder / "image_2" / f"{i:06d}.png"), rng.integers(0, 256, (40, 60, 3), np.uint8))
    (folder / "times.txt").write_text("0.0\n0.1\n0.2\n")
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 2, 3] = [0.0, 1.0, 2.0]
    write_kitti(folder / "poses.txt", poses)
    (folder / "calib.txt").write_bytes(calib)
    return folder


def _tr_line(values: str) -> bytes:
    return f"P0: {' '.join(['0'] * 12)}\nTr: {values}\n".encode()


CALIB_CASES = {
    "zeros": (_tr_line(" ".join(["0"] * 12)), "calib.txt:2: Tr is not a rigid"),
    "scaled": (_tr_line("2 0 0 0 0 2 0 0 0 0 2 0"), "rotation is not orthonormal"),
    "reflection": (_tr_line("1 0 0 0 0 1 0 0 0 0 -1 0"), "non-positive determinant"),
    "sheared": (_tr_line("1 0.01 0 0 0 1 0 0 0 0 1 0"), "rotation is not orthonormal"),
    "not_utf8": (b"P0: 1\n\xff\xfe\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n", "calib.txt: not UTF-8 text"),
}


@pytest.mark.parametrize("case", sorted(CALIB_CASES))
def test_a_bad_calib_file_is_refused(case: str, tmp_path: Path) -> None:
    calib, fragment = CALIB_CASES[case]
    sequence = _kitti_sequence(tmp_path / "seq", calib)
    with pytest.raises(FrontendInputError, match="Tr is not a rigid|not UTF-8 text") as caught:
        KittiSource(sequence)
    assert fragment in str(caught.value) and str(sequence / "calib.txt") in str(caught.value)


@pytest.mark.parametrize("case", ["zeros", "not_utf8"])
def test_run_on_a_bad_calib_file_exits_2(case: str, tmp_path: Path) -> None:
    sequence = _kitti_sequence(tmp_path / "seq", CALIB_CASES[case][0])
    out = tmp_path / "out"
    env = {"SSMVPR_FRONTEND__SOURCE__KITTI__GT_FRAME": "lidar"}
    assert_user_error(invoke("run", sequence, "--out", out, env=env), str(sequence / "calib.txt"))
    assert not (out / "latest").exists()


@pytest.mark.parametrize("values", [KITTI_00_TR, " ".join(f"{v:.4f}" for v in map(float, KITTI_00_TR.split()))])
def test_real_kitti_calibration_passes(values: str, tmp_path: Path) -> None:
    """KITTI's own Tr (12 digits), and the same typed in with 4 decimals, are rigid enough."""
    source = KittiSource(_kitti_sequence(tmp_path / "seq", _tr_line(values)))
    assert source.tr is not None and np.allclose(source.tr[:3].ravel(), [float(v) for v in values.split()])


# ----------------------------------------------------------------------------- --map places.json


def _valid_map(folder: Path) -> Path:
    vpr = load_config().vpr
    save_map(folder, _database(vpr, 4), vpr, {i: np.eye(4) for i in range(4)}, {},
             {i: np.eye(4) for i in range(4)})  # fmt: skip
    return folder


def _places(edit: Callable[[list], None]) -> Callable[[Path], str]:  # type: ignore[type-arg]
    return _json_file("places.json", edit)


def _pose_entry(key: str, index: int, entry: int, value: float) -> Callable[[Path], str]:
    return _places(lambda p: p[index]["extra"][key].__setitem__(entry, value))


MAP_CASES: dict[str, tuple[Callable[[Path], str], str]] = {
    "map_pose_rotation_entry_2": (_pose_entry("map_pose", 3, 0, 2.0), "place 3: map_pose is not a rigid pose"),
    "map_pose_reflection": (_pose_entry("map_pose", 1, 10, -1.0), "place 1: map_pose is not a rigid pose"),
    "map_pose_last_row": (_pose_entry("map_pose", 2, 12, 0.5), "place 2: map_pose is not a rigid pose (last row"),
    "map_pose_one_nan": (_pose_entry("map_pose", 0, 3, float("nan")), "place 0: map_pose is not a rigid pose"),
    "map_pose_inf": (_places(lambda p: p[2]["extra"].__setitem__("map_pose", [float("inf")] * 16)),
                     "place 2: map_pose is not a rigid pose"),
    "gt_pose_scaled": (_pose_entry("gt_pose", 1, 5, 3.0), "place 1: gt_pose is not a rigid pose"),
    "timestamp_text": (_places(lambda p: p[3].__setitem__("timestamp", "later")), "place 3: timestamp must be a number"),
    "timestamp_null": (_places(lambda p: p[3].__setitem__("timestamp", None)), "place 3: timestamp must be a number"),
    "timestamp_bool": (_places(lambda p: p[0].__setitem__("timestamp", True)), "place 0: timestamp must be a number"),
    "name_a_list": (_places(lambda p: p[3].__setitem__("name", [1, 2])), "place 3: name must be a string"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_malformed_places_are_refused(case: str, tmp_path: Path) -> None:
    folder = _valid_map(tmp_path / "map")
    damage, fragment = MAP_CASES[case]
    damage(folder)
    with pytest.raises(LoopClosureInputError) as caught:
        PriorMap.load(folder, load_config().vpr)
    message = str(caught.value)
    assert str(folder / "places.json") in message and fragment in message, message


@pytest.mark.parametrize("case", ["map_pose_rotation_entry_2", "timestamp_text", "name_a_list"])
def test_run_with_a_malformed_map_exits_2(case: str, tmp_path: Path) -> None:
    folder = _valid_map(tmp_path / "map")
    MAP_CASES[case][0](folder)
    log = _kitti_sequence(tmp_path / "seq", _tr_line(KITTI_00_TR))
    out = tmp_path / "out"
    env = {"SSMVPR_FRONTEND__ODOMETRY__LOGGED__POSE_SOURCE": "gt"}  # KITTI logs no odometry
    assert_user_error(invoke("run", log, "--odometry", "logged", "--map", folder, "--out", out, env=env),
                      str(folder / "places.json"), MAP_CASES[case][1])  # fmt: skip
    assert not (out / "latest").exists()


def test_what_a_map_may_hold_still_loads(tmp_path: Path) -> None:
    """NaN for "no pose" or "no time", an integer timestamp, and free-form extra keys (`session`
    is a label nothing reads) are not damage."""
    folder = _valid_map(tmp_path / "map")

    def edit(places: list) -> None:  # type: ignore[type-arg]
        places[1]["extra"]["map_pose"] = [float("nan")] * 16
        places[2]["timestamp"] = float("nan")
        places[3]["timestamp"] = 7
        places[0]["extra"]["session"] = 42

    _places(edit)(folder)
    prior = PriorMap.load(folder, load_config().vpr)
    assert sorted(prior.poses) == [0, 2, 3] and prior.database.places[3].timestamp == 7.0
    assert np.isnan(prior.database.places[2].timestamp)


# ------------------------------------------------------------------------ resume as a contract


def test_resume_refuses_environment_variables_that_change_the_settings(valid_checkpoint: Path, tmp_path: Path) -> None:
    """A resume keeps its checkpoint's settings: SSMVPR_ variables that would change them are
    refused like --config (before: applied silently, 22 proposals against 1). The weights and
    the device may change, as --weights and --device may."""
    log = tmp_path / "log.mcap"
    log.write_bytes(b"not read: the resume is refused first")
    result = invoke("run", log, "--resume", valid_checkpoint, env={"SSMVPR_DETECTOR__CALIBRATED__ACCEPT": "5"})
    assert_user_error(result, f"--resume {valid_checkpoint}", "SSMVPR_DETECTOR__CALIBRATED__ACCEPT", "unset them")
    allowed = invoke("run", log, "--resume", valid_checkpoint, env={"SSMVPR_VPR__BACKBONE__DEVICE": "cpu",
                                                                    "SSMVPR_WEIGHTS": "/nowhere.pth"})  # fmt: skip
    assert "environment variable" not in allowed.stderr and "log.mcap" in allowed.stderr  # refused later, for the log


def test_resume_checks_the_folder_is_writable_before_any_replay(
    valid_checkpoint: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A read-only results folder: refused in one line before the log is read (before: the whole
    rest was processed, every checkpoint failed, and the resumed work was lost)."""
    import errno
    import tempfile

    import ssmvpr_slam.results.run_folder as results

    copy = _copy(valid_checkpoint, tmp_path)
    real = tempfile.TemporaryFile

    def read_only(*args: Any, **kwargs: Any) -> Any:
        if Path(kwargs.get("dir", "")) == copy.run:
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*args, **kwargs)

    monkeypatch.setattr(results.tempfile, "TemporaryFile", read_only)
    log = tmp_path / "log.mcap"
    log.write_bytes(b"never read")
    result = invoke("run", log, "--resume", copy.run)
    assert_user_error(result, f"--resume {copy.run}: cannot write in {copy.run} (Read-only file system)")


def test_a_run_stopped_before_its_first_checkpoint_says_so(tmp_path: Path) -> None:
    run = tmp_path / "run_x"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"interrupted": True}))
    log = tmp_path / "log.mcap"
    log.write_bytes(b"never read")
    assert_user_error(invoke("run", log, "--resume", run), str(run), "stopped before its first checkpoint")
    (run / "metrics.json").write_text(json.dumps({"interrupted": False}))
    assert_user_error(invoke("run", log, "--resume", run), str(run), "this run finished")


# ---------------------------------------------------------------------------------- disk full


def test_a_checkpoint_that_fills_the_disk_leaves_no_folder_and_the_last_one_resumable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A disk that fills while a checkpoint is written: the half-written version is removed (its
    space is free for the next one), the error names the file, the previous checkpoint stays linked."""
    import errno

    import ssmvpr_slam.checkpoint.saving as checkpoint_module

    run = tmp_path / "run"
    first = _write_valid_checkpoint(run)
    real = checkpoint_module.atomic_write_bytes

    def fills_up(path: Path, data: bytes) -> Path:
        if Path(path).name == "detector.npz":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, data)

    monkeypatch.setattr(checkpoint_module, "atomic_write_bytes", fills_up)
    with pytest.raises(OSError) as caught:
        _write_valid_checkpoint(run)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename.endswith("detector.npz")
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint", first.name]  # no half-written version left
    assert load_checkpoint(run).folder == first
