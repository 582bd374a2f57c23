"""Bad input, category by category: each case must exit with the documented status, print no
traceback, name the input it refuses, and lose no finished data (results folders and `latest`
stay valid). docs/robustness.md, "Bad input policy", quotes the case counts per category from here.

Categories: config and environment, --out, prior map folders, logs / route files / images,
partial ground truth; plus the results writer's atomicity under crashes and interrupts.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: E402, F401

from frontend.config import McapWriterConfig
from frontend.simulation import SimulationConfig, TraverseSimulator
from frontend.sources import write_frames
from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.detector import LoopProposal
from loopclosure.encoder import Encoder, PlaceCodes
from loopclosure.pca import Codebooks, PCAProjection
from ssmvpr_common.trajectory_io import write_kitti
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.evaluation.run_report import evaluate
from ssmvpr_slam.prior_map import PriorMap, save_map
from ssmvpr_slam.results.run_folder import staged_results_dir
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult


def _tree(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")} if folder.exists() else set()


# ------------------------------------------------------------------------------- inputs


def _write_images(folder: Path, n: int, seed: int, shape: tuple[int, int] = (48, 64)) -> None:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        assert cv2.imwrite(str(folder / f"img{i}.png"), rng.integers(0, 256, (*shape, 3), dtype=np.uint8))


def _simulated_log(path: Path, frames: int, drop_gt: range = range(0)) -> Path:
    sim = TraverseSimulator(SimulationConfig(max_frames=frames, lidar={"enabled": False}))
    kept = (dataclasses.replace(f, gt_pose=None) if f.index in drop_gt else f for f in sim.frames())
    assert write_frames(kept, path, McapWriterConfig(chunk_size=64 * 1024)) == frames
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """Small valid inputs for every command (a 6-frame log, image folders, a pose graph)."""
    base = tmp_path_factory.mktemp("inputs")
    _write_images(base / "ref", 3, 0)
    _write_images(base / "query", 3, 1)
    graph = base / "ring.g2o"
    graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 2 0 0\n"
                     "EDGE_SE2 0 1 1 0 0 100 0 0 100 0 100\nEDGE_SE2 1 2 1 0 0 100 0 0 100 0 100\n")  # fmt: skip
    return SimpleNamespace(log=_simulated_log(base / "log.mcap", 6), ref=base / "ref", query=base / "query",
                           graph=graph, base=base)  # fmt: skip


# -------------------------------------------------------------------- config and environment

CONFIG_FILE_CASES = {
    # name: (file bytes, fragment of the message besides the file name)
    "not_utf8": (b"vpr:\n  \xff\xfe: 1\n", "not UTF-8"),
    "latin1_comment": ("# caf\u00e9\nvpr: {}\n".encode("latin-1"), "not UTF-8"),
    "not_yaml": (b"vpr: [unclosed\n", "not valid YAML"),
    "a_list": (b"- 1\n- 2\n", "mapping"),
    "a_scalar": (b"42\n", "mapping"),
    "unknown_section": (b"vpr_typo: {}\n", "vpr_typo"),
    "typo_in_field": (b"detector: {min_scor: 0.3}\n", "detector.min_scor"),
    "wrong_type": (b"detector: {min_score: high}\n", "detector.min_score"),
    "unknown_preset": (b"preset: nosuchpreset\n", "nosuchpreset"),
}


@pytest.mark.parametrize("case", sorted(CONFIG_FILE_CASES))
def test_bad_config_file(case: str, tmp_path: Path) -> None:
    data, fragment = CONFIG_FILE_CASES[case]
    path = tmp_path / "bad config [x].yaml"  # brackets: the message must be printed verbatim
    path.write_bytes(data)
    assert_user_error(invoke("config", "-c", path), str(path), fragment)


ENV_CASES = {
    "SSMVPR_VPR__FILTERING": ("notjson", "vpr.filtering is a section"),
    "SSMVPR_VPR": ("{bad", "vpr is a section"),
    "SSMVPR_FRONTEND__SOURCE__MCAP": ("[1, 2", "frontend.source.mcap is a section"),
    "SSMVPR_VPR_EVAL__RECALL_NS": ("notjson", "vpr_eval.recall_ns"),
    "SSMVPR_DETECTOR__MIN_SCORE": ("high", "detector.min_score"),
    "SSMVPR_VPR__FILTERING__NUM_CANDIDATES": ("-3", "num_candidates"),
    "SSMVPR_VPR__FILTERING__": ("{}", "SSMVPR_VPR__FILTERING__"),
}


@pytest.mark.parametrize("variable", sorted(ENV_CASES))
def test_bad_environment_variable(variable: str) -> None:
    value, fragment = ENV_CASES[variable]
    assert_user_error(invoke("config", env={variable: value}), variable, fragment)


@pytest.mark.parametrize("command", ["run", "vpr-eval"])
def test_torch_search_on_a_missing_gpu_is_refused_before_any_work(
    command: str, inputs: SimpleNamespace, weights_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`torch_device: cuda` where torch sees no GPU: one line before the first frame (a run of
    six frames never leaves the PCA warm-up, where the search would first be built)."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    env = {"SSMVPR_VPR__FILTERING__EXACT_BACKEND": "torch", "SSMVPR_VPR__FILTERING__TORCH_DEVICE": "cuda"}
    out = tmp_path / "out"
    assert_user_error(invoke(*_command(command, inputs, weights_path, out), env=env), "torch_device: cuda")
    assert not out.exists() or not any(out.iterdir())  # no results, not even a partial run's


def test_config_path_that_is_a_folder(tmp_path: Path) -> None:
    assert_user_error(invoke("config", "-c", tmp_path), str(tmp_path), "neither a file nor a preset")


# ------------------------------------------------------------------------------------ --out


def _command(name: str, inputs: SimpleNamespace, weights: Path, out: Path) -> list[object]:
    """Valid arguments for `name`, writing to `out`."""
    common = ["--weights", weights, "--device", "cpu"]
    return {
        "run": ["run", inputs.log, "--odometry", "logged", *common, "--out", out],
        "vpr-eval": ["vpr-eval", inputs.ref, inputs.query, *common, "--out", out],
        "demo": ["demo", "--frames", 2, "--odometry", "logged", *common, "--out", out],
        "fit-pca": ["fit-pca", inputs.ref, *common, "--output", out],
        "simulate": ["simulate", "--frames", 2, "--out", out],
        "optimize": ["optimize", inputs.graph, "--out", out],
    }[name]


FOLDER_OUTPUTS = ("run", "vpr-eval", "demo", "optimize")
FILE_OUTPUTS = ("fit-pca", "simulate")


def _bad_out(kind: str, tmp: Path, is_file_output: bool) -> tuple[Path, str]:
    """A bad --out of `kind` under `tmp`, and the fragment its error must hold."""
    name = "x.npz" if is_file_output else "results"
    if kind == "is_a_file":  # a file where a results folder is wanted
        path = tmp / "odd [" / "] taken"  # its text holds "[/]", rich's closing tag
        path.parent.mkdir()
        path.write_text("precious")
        return path, "is a file, not a folder"
    if kind == "is_a_folder":  # a folder where a file is wanted
        path = tmp / "taken [x]"
        (path / "keep").mkdir(parents=True)
        return path, "is a folder"
    if kind == "under_a_file":
        (tmp / "plain").write_text("precious")
        return tmp / "plain" / "sub" / name, "is a file, not a folder"
    if kind == "unwritable":  # /proc refuses new entries even to root
        return Path("/proc") / "ssmvpr-fuzz" / name, "/proc/ssmvpr-fuzz"
    raise AssertionError(kind)


OUT_CASES = [(c, k) for c in FOLDER_OUTPUTS for k in ("is_a_file", "under_a_file", "unwritable")] + [
    (c, k) for c in FILE_OUTPUTS for k in ("is_a_folder", "under_a_file", "unwritable")
]


@pytest.mark.parametrize(("command", "kind"), OUT_CASES)
def test_bad_out_is_refused_before_any_work(command: str, kind: str, inputs: SimpleNamespace, weights_path: Path,
                                            tmp_path: Path) -> None:  # fmt: skip
    out, fragment = _bad_out(kind, tmp_path, command in FILE_OUTPUTS)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    result = invoke(*_command(command, inputs, weights_path, out))
    option = "--output" if command == "fit-pca" else "--out"
    assert_user_error(result, f"{option} {out}", fragment)
    assert "SLAM" not in result.stdout and "simulating" not in result.stdout  # no work started
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before  # nothing touched
    assert not list(tmp_path.rglob("*.tmp")) and not list(tmp_path.rglob("*.partial"))


def test_simulate_out_with_markup_characters_is_printed_verbatim(tmp_path: Path) -> None:
    out = tmp_path / "odd[x]" / "[/]log[bold].mcap"
    result = invoke("simulate", "--frames", 2, "--out", out)
    assert result.exit_code == 0, result.output
    assert out.is_file() and str(out) in result.stdout.replace("\n", "")
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no temp file beside it


def test_missing_out_folders_made_for_a_refused_run_are_removed(tmp_path: Path) -> None:
    out = tmp_path / "new" / "results"
    missing = tmp_path / "no_such_log.mcap"
    assert_user_error(invoke("run", missing, "--out", out), str(missing))
    assert not (tmp_path / "new").exists()


# ---------------------------------------------------------- results written as one unit


def _publish(base: Path, payload: str, during: Callable[[Path], None] | None = None) -> Path:
    with staged_results_dir(base, "run") as staged:
        (staged.path / "metrics.json").write_text(payload)
        if during is not None:
            during(staged.path)
        (staged.path / "loop_closures.csv").write_text("done\n")
    assert staged.final is not None
    return staged.final


def _assert_latest(base: Path, folder: Path, payload: str) -> None:
    for latest in (base / "latest", base / "latest-run"):
        assert latest.is_symlink() and latest.resolve() == folder.resolve()
        assert (latest / "metrics.json").read_text() == payload and (latest / "loop_closures.csv").is_file()
    assert not [p for p in base.iterdir() if p.name.startswith(".")]  # no staging or temp link left


def _crash(_: Path) -> None:
    raise OSError(28, "No space left on device")


def _interrupt_twice(_: Path) -> None:
    os.kill(os.getpid(), signal.SIGINT)
    os.kill(os.getpid(), signal.SIGINT)


WRITE_FAULTS = {"crash": (_crash, OSError), "second_interrupt": (_interrupt_twice, KeyboardInterrupt)}


@pytest.mark.parametrize("fault", sorted(WRITE_FAULTS))
def test_a_failed_write_leaves_the_previous_results_and_latest(fault: str, tmp_path: Path) -> None:
    first = _publish(tmp_path, "first")
    during, error = WRITE_FAULTS[fault]
    with pytest.raises(error):
        _publish(tmp_path, "second", during)
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == sorted(
        [first.name, "latest", "latest-run"]
    )
    _assert_latest(tmp_path, first, "first")


def test_one_interrupt_while_writing_waits_for_the_write(tmp_path: Path) -> None:
    _publish(tmp_path, "first")
    second = _publish(tmp_path, "second", lambda _: os.kill(os.getpid(), signal.SIGINT))
    _assert_latest(tmp_path, second, "second")


@pytest.mark.slow
def test_run_failing_while_writing_keeps_the_earlier_run(partial_gt_run: SimpleNamespace, weights_path: Path,
                                                         tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    out = tmp_path / "out"
    shutil.copytree(partial_gt_run.out, out, symlinks=True)
    first = (out / "latest").resolve()
    monkeypatch.setattr("ssmvpr_slam.results.writers.write_json", lambda *_: _crash(Path()))
    result = invoke("run", partial_gt_run.log, "--odometry", "logged", "--weights", weights_path,
                    "--device", "cpu", "--out", out)  # fmt: skip
    assert_user_error(result, "No space left on device")  # one line, exit 2: the disk, not a bug
    assert (out / "latest").resolve() == first and json.loads((first / "metrics.json").read_text())["keyframes"]
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in partial_gt_run.out.iterdir())


# ------------------------------------------------------------------------ prior map folders


def _projection(dim_in: int, dim: int, seed: int) -> PCAProjection:
    rng = np.random.default_rng(seed)
    components = np.linalg.qr(rng.standard_normal((dim_in, dim)))[0].T.astype(np.float32)
    return PCAProjection(
        rng.standard_normal(dim_in).astype(np.float32), components, np.ones(dim, np.float32), False, True
    )


def _valid_map(folder: Path, vpr=None) -> Path:  # noqa: ANN001
    """A small saved map (4 places, poses, one scan) signed with `vpr` (default: the default config)."""
    vpr = vpr or load_config().vpr
    rng = np.random.default_rng(0)
    db = PlaceDatabase(Codebooks(_projection(30, 8, 1), _projection(20, 6, 2)), vpr.database)
    codes = PlaceCodes(
        rng.standard_normal((4, 16, 8)).astype(np.float32), rng.standard_normal((4, 3, 4, 6)).astype(np.float32)
    )
    db.add(codes, [PlaceInfo(frame_id=i, timestamp=float(i)) for i in range(4)])
    save_map(folder, db, vpr, {i: np.eye(4) for i in range(4)}, {0: rng.standard_normal((10, 3))}, {})
    return folder


def _edit_json(name: str, edit: Callable[[object], object]) -> Callable[[Path], str]:
    def apply(folder: Path) -> str:
        path = folder / name
        path.write_text(json.dumps(edit(json.loads(path.read_text()))))
        return name

    return apply


def _manifest(**changes: object) -> Callable[[Path], str]:
    return _edit_json("manifest.json", lambda m: {**m, **changes})


def _drop_manifest_key(key: str) -> Callable[[Path], str]:
    return _edit_json("manifest.json", lambda m: {k: v for k, v in m.items() if k != key})


def _place(index: int, **changes: object) -> Callable[[Path], str]:
    def edit(places: list) -> list:
        places[index] = {**places[index], **changes}
        return places

    return _edit_json("places.json", edit)


def _place_extra(index: int, **extra: object) -> Callable[[Path], str]:
    def edit(places: list) -> list:
        places[index]["extra"] = {**places[index]["extra"], **extra}
        return places

    return _edit_json("places.json", edit)


def _bytes(name: str, make: Callable[[bytes], bytes]) -> Callable[[Path], str]:
    def apply(folder: Path) -> str:
        path = folder / name
        path.write_bytes(make(path.read_bytes()))
        return name

    return apply


def _array(name: str, make: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], str]:
    def apply(folder: Path) -> str:
        np.save(folder / name, make(np.load(folder / name)))
        return name

    return apply


def _remove(name: str) -> Callable[[Path], str]:
    def apply(folder: Path) -> str:
        (folder / name).unlink()
        return name

    return apply


def _other_encoder(folder: Path) -> str:
    vpr = load_config().vpr
    vpr.backbone.input_size = vpr.backbone.input_size + 32
    shutil.rmtree(folder)
    _valid_map(folder, vpr)
    return "input_size"


def _set_nan(index: tuple) -> Callable[[np.ndarray], np.ndarray]:  # type: ignore[type-arg]
    def make(a: np.ndarray) -> np.ndarray:
        a = a.copy()
        a[index] = np.nan
        return a

    return make


MAP_CASES: dict[str, Callable[[Path], str]] = {
    # each returns the file (or a fragment) the error must name
    "manifest_not_json": _bytes("manifest.json", lambda b: b[: len(b) // 2]),
    "manifest_not_utf8": _bytes("manifest.json", lambda b: b"\xff\xfe" + b),
    "manifest_a_list": _edit_json("manifest.json", lambda m: [m]),
    "manifest_a_number": _edit_json("manifest.json", lambda m: 4),
    "no_num_places": _drop_manifest_key("num_places"),
    "num_places_text": _manifest(num_places="four"),
    "num_places_float": _manifest(num_places=2.5),
    "num_places_negative": _manifest(num_places=-1),
    "num_places_bool": _manifest(num_places=True),
    "num_places_too_many": lambda f: (_manifest(num_places=9)(f), "stage1.npy")[1],
    "no_stage1_shape": _drop_manifest_key("stage1_shape"),
    "stage2_shape_text": _manifest(stage2_shape="3x4x6"),
    "other_format": _manifest(format="something-else"),
    "other_version": _manifest(version=99),
    "config_wrong_type": _manifest(config={"stage1_dtype": "complex-ish"}),
    "extra_a_list": _manifest(extra=[1]),
    "encoder_not_an_object": _manifest(extra={"encoder": "vgg"}),
    "encoded_with_other_settings": _other_encoder,
    "codebooks_truncated": _bytes("codebooks.npz", lambda b: b[: len(b) // 2]),
    "codebooks_garbage": _bytes("codebooks.npz", lambda b: b"PK\x03\x04" + b"\x00" * 40),
    "codebooks_missing": _remove("codebooks.npz"),
    "codebooks_nan": lambda f: (
        np.savez(
            f / "codebooks.npz",
            **{k: (v * np.nan if k == "stage1_mean" else v) for k, v in np.load(f / "codebooks.npz").items()},
        ),
        "codebooks.npz",
    )[1],
    "scans_truncated": _bytes("scans.npz", lambda b: b[: len(b) // 2]),
    "scans_garbage": _bytes("scans.npz", lambda b: b"not a zip at all"),
    "scans_nan": lambda f: (np.savez(f / "scans.npz", p0=np.full((5, 3), np.nan)), "scans.npz")[1],
    "scans_unknown_place": lambda f: (np.savez(f / "scans.npz", p99=np.zeros((5, 3))), "scans.npz")[1],
    "stage1_all_nan": _array("stage1.npy", lambda a: np.full_like(a, np.nan)),
    "stage1_one_nan": _array("stage1.npy", _set_nan((2, 0, 0))),
    "stage2_inf": _array("stage2.npy", lambda a: a + np.inf),
    "stage1_truncated": _bytes("stage1.npy", lambda b: b[: len(b) // 2]),
    "stage1_wrong_shape": _array("stage1.npy", lambda a: a[:, :, :5]),
    "stage1_text": _array("stage1.npy", lambda a: a.astype(str)),
    "stage2_missing": _remove("stage2.npy"),
    "places_not_a_list": _edit_json("places.json", lambda p: {"0": p[0]}),
    "places_too_few": _edit_json("places.json", lambda p: p[:2]),
    "place_not_an_object": _edit_json("places.json", lambda p: [7, *p[1:]]),
    "place_without_frame_id": _edit_json(
        "places.json", lambda p: [{k: v for k, v in p[0].items() if k != "frame_id"}, *p[1:]]
    ),
    "place_unknown_key": _place(1, colour="red"),
    "map_pose_15_values": _place_extra(2, map_pose=[0.0] * 15),
    "map_pose_text": _place_extra(2, map_pose=["a"] * 16),
    "map_pose_nested_wrong": _place_extra(2, map_pose=[[1.0, 0.0], [0.0, 1.0]]),
    "gt_pose_wrong_length": _place_extra(0, gt_pose=[1.0, 2.0, 3.0]),
}


def test_the_unbroken_map_loads(tmp_path: Path) -> None:
    prior = PriorMap.load(_valid_map(tmp_path / "map"), load_config().vpr)
    assert len(prior) == 4 and len(prior.poses) == 4 and list(prior.scans) == [0]


@pytest.mark.parametrize("case", sorted(MAP_CASES))
def test_bad_map_folder(case: str, inputs: SimpleNamespace, tmp_path: Path) -> None:
    folder = _valid_map(tmp_path / "map [1]")
    named = MAP_CASES[case](folder)
    out = tmp_path / "out"
    result = invoke("run", inputs.log, "--odometry", "logged", "--map", folder, "--out", out)
    line = assert_user_error(result, str(folder))
    assert named in line, (named, line)
    assert not out.exists()  # refused before anything was written


@pytest.mark.parametrize("kind", ["missing", "a_file", "empty_folder"])
def test_map_path_that_is_no_map(kind: str, inputs: SimpleNamespace, tmp_path: Path) -> None:
    path = tmp_path / "map"
    if kind == "a_file":
        path.write_text("x")
    elif kind == "empty_folder":
        path.mkdir()
    said = "no such place database folder" if kind == "missing" else "not a place database"
    assert_user_error(invoke("run", inputs.log, "--odometry", "logged", "--map", path), str(path), said)


SMALL_PCA = {"SSMVPR_VPR__FILTERING__PCA__DIM": "8", "SSMVPR_VPR__SPATIAL__PCA__DIM": "8"}  # 3 images suffice


@pytest.mark.slow
def test_vpr_eval_database_is_signed_and_a_mismatch_is_refused(inputs: SimpleNamespace, weights_path: Path,
                                                               tmp_path: Path) -> None:  # fmt: skip
    out = tmp_path / "out"
    result = invoke("vpr-eval", inputs.ref, inputs.query, "--weights", weights_path, "--device", "cpu",
                    "--out", out, env=SMALL_PCA)  # fmt: skip
    assert result.exit_code == 0, (result.output, result.exception)
    database = out / "latest" / "database"
    result = invoke("run", inputs.log, "--odometry", "logged", "--map", database,
                    env={**SMALL_PCA, "SSMVPR_VPR__BACKBONE__STAGE1_LAYER": "conv5_3"})  # fmt: skip
    assert_user_error(result, str(database), "encoded with other settings (stage1_layer)")
    # with the settings it was encoded with it is signed right, but it has no poses: a recognition
    # benchmark's map would lend a SLAM run its codebooks and anchor nothing (`results/latest` is
    # vpr-eval's after a vpr-eval run)
    result = invoke("run", inputs.log, "--odometry", "logged", "--map", database, env=SMALL_PCA)
    assert_user_error(result, str(database), "none of its 3 places has a map pose")


# ------------------------------------------------------------ logs, route files and images


def _log_cases(inputs: SimpleNamespace, tmp: Path) -> dict[str, tuple[list[object], str]]:
    text = tmp / "notes.txt"
    text.write_text("not a log")
    garbage = tmp / "garbage.mcap"
    garbage.write_bytes(b"definitely not an mcap file" * 10)
    cut = tmp / "cut.mcap"
    cut.write_bytes(inputs.log.read_bytes()[: inputs.log.stat().st_size // 3])
    route = tmp / "route"
    _write_images(route / "images", 3, 2)
    write_kitti(route / "poses.txt", np.tile(np.eye(4), (4, 1, 1)))
    bad_line = tmp / "route_bad_line"
    _write_images(bad_line / "images", 2, 3)
    (bad_line / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 x 0 1 0 0 0 0 1 0\n")
    return {
        "missing_log": (["run", tmp / "nothing.mcap"], "nothing.mcap"),
        "text_file": (["run", text], "not a .mcap"),
        "garbage_mcap": (["run", garbage], str(garbage)),
        "truncated_mcap": (["run", cut, "--odometry", "logged"], "truncated"),
        "route_count_mismatch": (["run", route], "4 poses for 3 images"),
        "route_bad_number": (["run", bad_line], f"{bad_line / 'poses.txt'}:2"),
    }


LOG_CASES = ["missing_log", "text_file", "garbage_mcap", "truncated_mcap", "route_count_mismatch", "route_bad_number"]


@pytest.mark.parametrize("case", LOG_CASES)
def test_bad_log_or_route_file(case: str, inputs: SimpleNamespace, weights_path: Path, tmp_path: Path) -> None:
    args, fragment = _log_cases(inputs, tmp_path)[case]
    out = tmp_path / "out"
    result = invoke(*args, "--weights", weights_path, "--device", "cpu", "--out", out)
    assert_user_error(result, fragment)
    if case == "truncated_mcap":  # the frames before the cut are kept in a complete folder
        assert json.loads((out / "latest" / "metrics.json").read_text())["frames"] >= 1
    else:
        assert not out.exists()


IMAGE_CASES = {
    "one_pixel": (lambda p: cv2.imwrite(str(p), np.zeros((1, 1, 3), np.uint8)), "1x1 pixels"),
    "thin_strip": (lambda p: cv2.imwrite(str(p), np.zeros((200, 8, 3), np.uint8)), "8x200 pixels"),
    "corrupt": (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\nnot really"), "cannot decode"),
    "empty_file": (lambda p: p.write_bytes(b""), "cannot decode"),
}


IMAGE_ROLES = [(case, "ref") for case in sorted(IMAGE_CASES)] + [
    pytest.param("one_pixel", "query", marks=pytest.mark.slow)  # after the references are encoded
]


@pytest.mark.parametrize(("case", "role"), IMAGE_ROLES)
def test_bad_image_in_vpr_eval(
    case: str, role: str, inputs: SimpleNamespace, weights_path: Path, tmp_path: Path
) -> None:
    folders = {"ref": tmp_path / "ref", "query": tmp_path / "query"}
    shutil.copytree(inputs.ref, folders["ref"])
    shutil.copytree(inputs.query, folders["query"])
    write, fragment = IMAGE_CASES[case]
    bad = folders[role] / "img0.png"
    write(bad)
    out = tmp_path / "out"
    result = invoke("vpr-eval", folders["ref"], folders["query"], "--weights", weights_path, "--device", "cpu",
                    "--out", out, env=SMALL_PCA)  # fmt: skip
    assert_user_error(result, str(bad), fragment)
    assert not out.exists()


def test_tiny_image_in_a_stream_is_used_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    encoder = Encoder(load_config().vpr, backbone=None)  # type: ignore[arg-type]  # prepare needs no backbone
    with caplog.at_level("WARNING"):
        prepared = encoder.prepare(np.zeros((1, 1, 3), np.uint8), "keyframe 7 image")
    assert prepared.shape[:2] == (encoder.config.backbone.input_size,) * 2
    assert "keyframe 7 image: image of 1x1 pixels" in caplog.text
    caplog.clear()
    encoder.prepare(np.zeros((48, 64, 3), np.uint8), "fine")
    assert caplog.text == ""


# --------------------------------------------------------------------- partial ground truth


@pytest.fixture(scope="module")
def partial_gt_run(tmp_path_factory: pytest.TempPathFactory, weights_path: Path) -> SimpleNamespace:
    """`run` on a 12-frame log whose ground truth is missing for frames 3-5."""
    base = tmp_path_factory.mktemp("partial_gt")
    log = _simulated_log(base / "log.mcap", 12, drop_gt=range(3, 6))
    out = base / "out"
    result = invoke("run", log, "--odometry", "logged", "--weights", weights_path, "--device", "cpu", "--out", out)
    return SimpleNamespace(log=log, out=out, result=result)


def test_run_with_partial_ground_truth_evaluates_the_covered_keyframes(partial_gt_run: SimpleNamespace) -> None:
    result = partial_gt_run.result
    assert result.exit_code == 0, (result.output, result.exception)
    assert "Traceback" not in result.output
    metrics = json.loads((partial_gt_run.out / "latest" / "metrics.json").read_text())
    covered, total = metrics["ground_truth_keyframes"], metrics["keyframes"]
    assert 0 < covered < total and metrics["ground_truth_coverage"] == pytest.approx(covered / total)
    assert metrics["ground_truth"] and metrics["ate_odometry"]["n"] == covered
    assert f"{covered} / {total} keyframes" in result.stdout  # the printed summary states it
    gt_lines = [line for line in (partial_gt_run.out / "latest" / "ground_truth.tum").read_text().splitlines()
                if not line.startswith("#")]  # fmt: skip
    assert len(gt_lines) == covered and not (partial_gt_run.out / "latest" / "ground_truth.kitti").exists()


def _out_and_back(n: int = 20) -> np.ndarray:
    """Keyframe poses driving 5 m steps along x and back: keyframe k revisits keyframe n-1-k."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = [5.0 * min(k, n - 1 - k) for k in range(n)]
    return poses


def _result(gt: list[np.ndarray | None], loops: list[tuple[int, int]]) -> RunResult:
    true = _out_and_back(len(gt))
    odom = true.copy()
    odom[:, 1, 3] += 0.2 * np.arange(len(gt))  # drift
    kfs = tuple(Keyframe(k, k, float(k), odom[k], g, None, None) for k, g in enumerate(gt))
    records = tuple(LoopRecord(LoopProposal(q, m, m, 0.9, 0.5, 0, 0.0, True, "accepted", "reverse"), factor_handle=i)
                    for i, (q, m) in enumerate(loops))  # fmt: skip
    return RunResult(kfs, records, np.arange(len(gt), dtype=float), odom, true.copy())


PARTIAL_GT_CASES = {
    # name: (keyframes without ground truth: index -> None or a NaN pose, expected judged loops, precision)
    "complete": ({}, 3, 2 / 3),
    "one_none": ({3: None}, 2, 1 / 2),
    "nan_and_none": ({3: None, 12: "nan"}, 2, 1 / 2),
    "most_missing": ({k: None for k in (0, 1, 2, 5, 7, 9, 10, 11, 13, 16, 17, 19)}, 2, 1 / 2),
    "none_at_all": ({k: None for k in range(20)}, None, None),
}


@pytest.mark.parametrize("case", sorted(PARTIAL_GT_CASES))
def test_evaluation_on_the_keyframes_with_ground_truth(case: str) -> None:
    missing, judged, precision = PARTIAL_GT_CASES[case]
    true = _out_and_back()
    gt = [
        None if missing.get(k, 0) is None else np.full((4, 4), np.nan) if k in missing else true[k] for k in range(20)
    ]
    # (16, 3) and (15, 4) close correct loops; (18, 6) is 25 m off
    run = _result(gt, [(16, 3), (15, 4), (18, 6)])
    config = load_config(overrides={"evaluation": {"loops": {"min_frame_gap": 5}}})
    metrics = evaluate(run, config.evaluation).metrics()
    covered = 20 - len(missing)
    assert metrics["ground_truth_coverage"] == pytest.approx(covered / 20)
    assert metrics["ground_truth_keyframes"] == covered
    if judged is None:
        assert metrics["ground_truth"] is False and "ate_odometry" not in metrics
        return
    assert metrics["ground_truth"] and metrics["ate_odometry"]["n"] == covered
    assert metrics["ate_optimised"]["rmse"] < 1e-9 < metrics["ate_odometry"]["rmse"]
    loops = metrics["loops"]
    assert loops["proposed"] == loops["in_graph"] == 3  # every proposal is still counted
    assert loops.get("judged_in_graph", loops["in_graph"]) == judged  # only loops with both ends covered are judged
    assert loops["precision"] == pytest.approx(precision)
