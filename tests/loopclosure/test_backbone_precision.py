"""Backbone precisions: each agrees with the torch fp32 reference, `auto` resolves as documented.

Tolerances (cosine similarity of each image's conv map with fp32's, real weights, real photos):
bf16 >= 0.999 (measured 0.99995 at 224 px), int8 >= 0.995 (measured 0.9991-0.9997). int8 is
calibrated on Gardens Point's reference images and checked on its query images.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from loopclosure import backbone as backbone_module
from loopclosure import int8_runtime
from loopclosure.backbone import Backbone, resolve_precision
from loopclosure.backbone_input import list_images, read_image, resize_square
from loopclosure.config import BackboneConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.int8_runtime import int8_available

SIZE = 96  # fully convolutional: agreement at 96 px means the same as at 224, in a third of the time
MIN_COSINE = {"bf16": 0.999, "int8": 0.995}


def _cosines(ref: np.ndarray, got: np.ndarray) -> np.ndarray:
    a, b = ref.reshape(len(ref), -1).astype(np.float64), got.reshape(len(got), -1).astype(np.float64)
    return (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


@pytest.fixture(scope="module")
def real_sd(weights_path):
    from loopclosure.weights import load_state_dict

    return load_state_dict(weights_path)


@pytest.fixture(scope="module")
def queries(gardens_dir) -> np.ndarray:
    files = list_images(gardens_dir / "query")[:3]
    return np.stack([resize_square(read_image(f), SIZE) for f in files])


@pytest.fixture(scope="module")
def reference_maps(real_sd, queries) -> tuple[np.ndarray, np.ndarray]:
    return Backbone(_config("fp32"), real_sd)(queries)


def _config(precision: str, **kw) -> BackboneConfig:
    return BackboneConfig(weights="x", device="cpu", input_size=SIZE, precision=precision, **kw)


def _check_agreement(got: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray], precision: str) -> None:
    for g, r in zip(got, ref):
        assert g.dtype == np.float32 and g.flags.c_contiguous and g.shape == r.shape
        assert _cosines(r, g).min() >= MIN_COSINE[precision]
        assert (g < 0).any()  # pre-ReLU maps keep their negative part


# ---- auto ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "flags, expected",
    [
        ({"avx512f", "avx512_bf16"}, "bf16"),  # Zen 4/5, Cooper Lake
        ({"avx512f", "amx_bf16", "amx_tile"}, "bf16"),  # Sapphire Rapids
        ({"avx512f", "avx512_vnni"}, "fp32"),  # Skylake-X / Cascade Lake: no bf16 products
        ({"avx2", "fma"}, "fp32"),
    ],
)
def test_auto_on_cpu_follows_the_cpuinfo_flags(monkeypatch, flags, expected):
    monkeypatch.setattr(backbone_module, "cpu_flags", lambda: frozenset(flags))
    assert resolve_precision("auto", torch.device("cpu")) == expected
    # an explicit choice is never overridden
    assert resolve_precision("fp32", torch.device("cpu")) == "fp32"
    assert resolve_precision("bf16", torch.device("cpu")) == "bf16"


@pytest.mark.parametrize(
    "avx512_bf16, amx, expected", [(True, False, "bf16"), (False, True, "bf16"), (False, False, "fp32")]
)
def test_auto_without_proc_cpuinfo_asks_torch(monkeypatch, avx512_bf16, amx, expected):
    monkeypatch.setattr(backbone_module, "cpu_flags", lambda: None)
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: avx512_bf16, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: amx, raising=False)
    assert resolve_precision("auto", torch.device("cpu")) == expected


@pytest.mark.parametrize("bf16_ok, expected", [(True, "bf16"), (False, "fp16")])
def test_auto_on_cuda(monkeypatch, bf16_ok, expected):
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: bf16_ok)
    assert resolve_precision("auto", torch.device("cuda")) == expected


def test_int8_is_refused_on_cuda():
    with pytest.raises(LoopClosureInputError, match="int8.*device='cpu'"):
        resolve_precision("int8", torch.device("cuda"))


def test_auto_backbone_runs_what_it_resolved(monkeypatch):
    monkeypatch.setattr(backbone_module, "cpu_flags", lambda: frozenset({"avx2"}))
    backbone = Backbone(BackboneConfig(weights="random", device="cpu", input_size=32, precision="auto"), None)
    assert backbone.precision == "fp32"
    assert all(p.dtype == torch.float32 for p in backbone.net.parameters())


def test_the_default_is_the_fp32_reference():
    assert BackboneConfig().precision == "fp32"


def test_precision_from_the_environment(monkeypatch):
    from ssmvpr_slam.config.slam import load_config

    monkeypatch.setenv("SSMVPR_VPR__BACKBONE__PRECISION", "bf16")
    assert load_config().vpr.backbone.precision == "bf16"
    monkeypatch.setenv("SSMVPR_VPR__BACKBONE__PRECISION", "fp64")
    with pytest.raises(Exception, match="precision"):
        load_config()


# ---- bf16 ----------------------------------------------------------------------------------


def test_bf16_agrees_with_fp32(real_sd, queries, reference_maps):
    backbone = Backbone(_config("bf16"), real_sd)
    assert backbone.precision == "bf16"
    assert backbone.net.features[2].weight.dtype == torch.bfloat16  # conv1_1 (index 0) stays fp32
    _check_agreement(backbone(queries), reference_maps, "bf16")


# ---- int8 ----------------------------------------------------------------------------------


def test_int8_without_the_extra_is_one_clear_line(monkeypatch, real_sd):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails as if not installed
    with pytest.raises(LoopClosureInputError, match=r'pip install "ssmvpr-slam\[int8\]"'):
        Backbone(_config("int8", int8_calibration="/nonexistent"), real_sd)


def test_int8_without_a_folder_calibrates_on_the_first_images_in_fp32_meanwhile(
    monkeypatch, tmp_path, real_sd, queries, reference_maps, gardens_dir
):
    pytest.importorskip("onnxruntime")
    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path))
    stream = np.stack([resize_square(read_image(f), SIZE) for f in list_images(gardens_dir / "ref")[:4]])
    stale = tmp_path / "int8" / "vgg16_int8_stale.onnx"  # an older setting's model, beyond the cache's size
    stale.parent.mkdir()
    stale.write_bytes(b"old")
    os.utime(stale, (1e9, 1e9))
    monkeypatch.setattr(int8_runtime, "CACHE_KEEP", 1)
    backbone = Backbone(_config("int8", int8_calibration_images=4), real_sd)
    assert backbone.precision == "int8" and list(tmp_path.glob("int8/*.onnx")) == [stale]
    fp32 = Backbone(_config("fp32"), real_sd)
    for k in (0, 1):  # the first images (one, then a batch of three) are answered by the fp32 net
        part = stream[:1] if k == 0 else stream[1:]
        for got, want in zip(backbone(part), fp32(part)):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-3)
    assert len(list(tmp_path.glob("int8/*.onnx"))) == 1  # calibrated once it had seen four
    assert not stale.exists()  # pruned: the cache keeps the CACHE_KEEP most recently used
    after = backbone(queries)
    _check_agreement(after, reference_maps, "int8")
    assert not np.allclose(after[0], reference_maps[0], rtol=1e-4, atol=1e-3)  # int8 answers now, not fp32
    # the same images as calibration_images make the same model: the cache has no second one
    Backbone(_config("int8"), real_sd, calibration_images=stream)
    assert len(list(tmp_path.glob("int8/*.onnx"))) == 1


def test_int8_calibrated_on_references_agrees_with_fp32(
    monkeypatch, tmp_path, real_sd, queries, reference_maps, gardens_dir
):
    pytest.importorskip("onnxruntime")
    from loopclosure import int8_runtime

    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path))
    config = _config("int8", int8_calibration=str(gardens_dir / "ref"), int8_calibration_images=6)
    backbone = Backbone(config, real_sd)
    assert backbone.precision == "int8"
    _check_agreement(backbone(queries), reference_maps, "int8")
    assert len(list((tmp_path / "int8").glob("*.onnx"))) == 1

    # the same setting reopens the cached model without calibrating again ...
    def no_quantize(*args, **kwargs):
        raise AssertionError("quantised again despite the cache")

    monkeypatch.setattr(int8_runtime, "quantize", no_quantize)
    again = Backbone(config, real_sd)(queries)
    np.testing.assert_array_equal(again[0], backbone(queries)[0])
    # ... and other calibration images make another model
    monkeypatch.undo()
    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path))
    Backbone(config, real_sd, calibration_images=queries)
    assert len(list((tmp_path / "int8").glob("*.onnx"))) == 2


def test_an_unreadable_cached_int8_model_is_calibrated_again(monkeypatch, tmp_path, real_sd, queries, caplog):
    """A cache entry cut short (a full disk) or pruned by another process is not fatal."""
    pytest.importorskip("onnxruntime")
    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path))
    config = _config("int8")
    first = Backbone(config, real_sd, calibration_images=queries)(queries)
    (model,) = (tmp_path / "int8").glob("*.onnx")
    model.write_bytes(b"not an onnx model")
    again = Backbone(config, real_sd, calibration_images=queries)
    assert "could not be opened" in caplog.text and "calibrating again" in caplog.text
    np.testing.assert_array_equal(again(queries)[0], first[0])
    assert model.stat().st_size > 1_000_000  # rewritten whole


# ---- the benchmark -------------------------------------------------------------------------


@pytest.mark.slow
def test_bench_backbone_prints_one_json(tmp_path):
    """tools/bench_backbone.py end to end at tiny settings (random weights, 64 px)."""
    script = Path(__file__).resolve().parents[2] / "tools" / "bench_backbone.py"
    precisions = "fp32,bf16,int8"
    cmd = [sys.executable, str(script), "--weights", "random", "--input-size", "64", "--batch-sizes", "1,2",
           "--repeats", "1", "--no-gemm", "--precisions", precisions, "--calibration-images", "2"]  # fmt: skip
    env = {**os.environ, "SSMVPR_CACHE": str(tmp_path)}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, check=False, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["gflop_per_image"] > 0 and out["machine"]["loadavg_start"] is not None
    # each instruction chain's peak, whichever is faster: that is the machine's (a 2-vCPU machine of
    # this kind ran VDPBF16PS at half the fp32 FMA's GFLOP/s), not the tool's to promise
    assert min(out["isa_peak_gflops"][kind] for kind in ("fp32", "bf16", "int8")) > 0
    fp32 = out["precisions"]["fp32"]
    assert fp32["agreement_with_fp32"]["stage1"]["cosine_min"] > 0.99999
    assert fp32["batch_2"]["ms_per_image"] > 0 and fp32["physical_limit_ms_per_image"] > 0
    int8 = out["precisions"]["int8"]
    assert ("skipped" in int8) != int8_available()


# ---- int8 calibrated on the stream, across a checkpoint ----------------------------------------


def test_stream_calibration_resumes_with_the_same_model(monkeypatch, tmp_path, real_sd, queries, gardens_dir):
    """What a checkpoint keeps (`stream_calibration`) rebuilds the model the run had, whether
    the run had calibrated already or was still collecting images."""
    pytest.importorskip("onnxruntime")
    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path))
    config = _config("int8", int8_calibration_images=4)
    stream = np.stack([resize_square(read_image(f), SIZE) for f in list_images(gardens_dir / "ref")[:4]])
    run = Backbone(config, real_sd)
    empty, calibrated = run.stream_calibration()
    assert run.calibrates_on_stream and empty.shape == (0, SIZE, SIZE, 3) and not calibrated
    run(stream[:2])
    halfway, calibrated = run.stream_calibration()
    np.testing.assert_array_equal(halfway, stream[:2])
    assert not calibrated
    run(stream[2:])  # the fourth image: calibrated now
    whole, calibrated = run.stream_calibration()
    np.testing.assert_array_equal(whole, stream)
    assert calibrated
    want = run(queries)

    after_calibration = Backbone(config, real_sd)
    after_calibration.resume_stream_calibration(whole, True)
    np.testing.assert_array_equal(after_calibration(queries)[0], want[0])  # int8 at once, the same model

    during_calibration = Backbone(config, real_sd)
    during_calibration.resume_stream_calibration(halfway, False)
    during_calibration(stream[2:])  # the rest of the run's calibration images, after the resume
    np.testing.assert_array_equal(during_calibration(queries)[0], want[0])
    assert len(list(tmp_path.glob("int8/*.onnx"))) == 1

    with pytest.raises(LoopClosureInputError, match="fresh int8 backbone"):
        run.resume_stream_calibration(halfway, False)  # one that has its own calibration already
    with pytest.raises(LoopClosureInputError, match="fresh int8 backbone"):
        Backbone(_config("fp32"), real_sd).resume_stream_calibration(halfway, False)
    other_count = Backbone(_config("int8", int8_calibration_images=3), real_sd)
    with pytest.raises(LoopClosureInputError, match="calibrated on 4 images, but int8_calibration_images is 3"):
        other_count.resume_stream_calibration(whole, True)  # another setting would make another model
    with pytest.raises(LoopClosureInputError, match="uint8 images"):
        Backbone(config, real_sd).resume_stream_calibration(halfway.astype(np.float32), False)
    assert Backbone(_config("fp32"), real_sd).stream_calibration() is None
    folder = Backbone(_config("int8", int8_calibration=str(gardens_dir / "ref"), int8_calibration_images=4), real_sd)
    assert folder.stream_calibration() is None and not folder.calibrates_on_stream  # the folder is read again


def test_a_restored_detector_encodes_with_the_runs_int8_model(monkeypatch, tmp_path, real_sd, corridor_dir, caplog):
    """A SLAM run's int8 backbone calibrates on its first keyframes; the detector's state keeps
    those images (through a .npz file, as a checkpoint writes it), so the places added after a
    resume are the codes an uninterrupted run adds. Without them the resumed detector answers
    fp32, then calibrates on the images after the resume: another model."""
    pytest.importorskip("onnxruntime")
    import io

    from loopclosure.config import DetectorConfig, VPRConfig
    from loopclosure.database import PlaceDatabase
    from loopclosure.detector import LoopDetector
    from loopclosure.encoder import Encoder

    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path))
    vpr = VPRConfig.model_validate({
        "backbone": {"weights": "x", "device": "cpu", "input_size": 112, "precision": "int8",
                     "int8_calibration_images": 4},
        "filtering": {"pca": {"dim": 8}}, "spatial": {"pca": {"dim": 8}},
    })  # fmt: skip
    settings = DetectorConfig(pca_warmup_keyframes=9)
    images = [read_image(f) for f in list_images(corridor_dir / "ref")[:16]]

    def new_detector() -> LoopDetector:
        return LoopDetector(vpr, settings, Encoder(vpr, Backbone(vpr.backbone, real_sd)))

    whole = new_detector()
    for k, image in enumerate(images):
        whole.process(image, k)
    cut = 11
    first = new_detector()
    for k, image in enumerate(images[:cut]):
        first.process(image, k)
    buffer = io.BytesIO()
    np.savez(buffer, **first.state_arrays())
    buffer.seek(0)
    with np.load(buffer, allow_pickle=False) as data:
        state = {name: data[name] for name in data.files}
    assert state["int8_stream_calibration"].shape == (4, 112, 112, 3) and bool(state["int8_stream_calibrated"])
    first.database.save(tmp_path / "db")

    resumed = new_detector()
    resumed.load_state_arrays(state, PlaceDatabase.load(tmp_path / "db"))
    legacy = new_detector()  # a checkpoint from before the calibration images were kept
    with caplog.at_level("WARNING"):
        legacy.load_state_arrays({k: v for k, v in state.items() if not k.startswith("int8_stream")},
                                 PlaceDatabase.load(tmp_path / "db"))  # fmt: skip
    assert "does not hold the images int8 was calibrated on" in caplog.text
    for k in range(cut, len(images)):
        resumed.process(images[k], k)
        legacy.process(images[k], k)
    want = np.asarray(whole.database.stage1)[cut:]
    np.testing.assert_array_equal(np.asarray(resumed.database.stage1)[cut:], want)
    # the legacy detector: fp32 for 4 keyframes, then int8 calibrated on them, not the run's
    got = np.asarray(legacy.database.stage1)[cut:]
    assert legacy.encoder.backbone.stream_calibration()[1]
    assert not np.array_equal(got[:4], want[:4]) and not np.array_equal(got[4:], want[4:])

    refused = new_detector()  # a state the backbone refuses leaves the detector untouched
    with pytest.raises(LoopClosureInputError, match="int8_calibration_images"):
        refused.load_state_arrays({**state, "int8_stream_calibrated": np.array(False)},
                                  PlaceDatabase.load(tmp_path / "db"))  # fmt: skip
    assert refused.database is None and not refused.ready
