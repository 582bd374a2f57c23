"""loopclosure.backbone: VGG16 maps checked against an independent functional VGG16 oracle.

The oracle comparisons run the torch fp32 reference (precision="fp32"); the reduced precisions
are checked against it in test_backbone_precision.py.

The real-weight tests run at a small input size (the network is fully convolutional, so the
oracle comparison means the same at 64 px as at 224) and share one loaded state dict.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from loopclosure.backbone import Backbone, VGG16Features, load_backbone
from loopclosure.backbone_input import read_image, resize_square
from loopclosure.config import BackboneConfig
from loopclosure.errors import LoopClosureInputError, WeightsNotFoundError

# Standard VGG16 configuration 'D' (Simonyan & Zisserman); torchvision numbers the modules of
# `features` in order, each conv followed by its ReLU, each 'M' one max-pool.
VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
LAYER_NAMES = ["conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3",
               "conv4_1", "conv4_2", "conv4_3", "conv5_1", "conv5_2", "conv5_3"]  # fmt: skip
TV_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
TV_STD = np.array([0.229, 0.224, 0.225], np.float32)
CAFFE_BGR_MEAN = np.array([103.939, 116.779, 123.68], np.float32)


def _preprocess(images: np.ndarray, preprocessing: str) -> torch.Tensor:
    x = images.astype(np.float32)
    if preprocessing == "torchvision":
        x = (x / 255.0 - TV_MEAN) / TV_STD
    else:  # Caffe: BGR order, 0..255, per-channel mean subtracted, no scaling
        x = x[..., ::-1] - CAFFE_BGR_MEAN
    return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)))


def _oracle_maps(images: np.ndarray, sd: dict, preprocessing: str, pre_relu: bool) -> dict[str, torch.Tensor]:
    """Every conv map of VGG16 computed with torch.nn.functional from the state dict."""
    x = _preprocess(images, preprocessing)
    out: dict[str, torch.Tensor] = {}
    index = 0
    names = iter(LAYER_NAMES)
    with torch.no_grad():
        for item in VGG16_CFG:
            if item == "M":
                x = F.max_pool2d(x, 2, 2)
                index += 1
                continue
            y = F.conv2d(x, sd[f"features.{index}.weight"], sd[f"features.{index}.bias"], padding=1)
            x = F.relu(y)
            out[next(names)] = y if pre_relu else x
            index += 2
    return out


@pytest.fixture(scope="module")
def real_sd(weights_path):
    from loopclosure.weights import load_state_dict

    return load_state_dict(weights_path)


@pytest.fixture(scope="module")
def small_images(gardens_dir) -> np.ndarray:
    """Two real photos (day query, night reference) at 64 px."""
    return np.stack([resize_square(read_image(gardens_dir / sub / "3.jpg"), 64) for sub in ("query", "ref")])


def _random_sd(seed: int = 0) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    return VGG16Features("conv5_2").state_dict()


@pytest.fixture(scope="module")
def random_backbone_64() -> Backbone:
    return Backbone(BackboneConfig(weights="random", device="cpu", input_size=64), None)


# ---- shapes and ReLU taps (random weights) ------------------------------------------------


def test_default_layers_have_paper_shapes_at_224():
    backbone = Backbone(BackboneConfig(weights="random", device="cpu"), None)
    images = np.random.default_rng(0).integers(0, 256, (2, 224, 224, 3), dtype=np.uint8)
    m1, m2 = backbone(images)
    assert m1.shape == (2, 512, 14, 14)  # conv5_2
    assert m2.shape == (2, 512, 28, 28)  # conv4_2
    assert m1.dtype == np.float32 and m2.dtype == np.float32
    assert np.isfinite(m1).all() and np.isfinite(m2).all()


def test_pre_relu_has_negatives_and_post_relu_is_its_positive_part():
    sd = _random_sd()
    images = np.random.default_rng(1).integers(0, 256, (1, 64, 64, 3), dtype=np.uint8)
    cfg = BackboneConfig(weights="x", device="cpu", input_size=64, precision="fp32")
    pre = Backbone(cfg.model_copy(update={"pre_relu": True}), sd)(images)
    post = Backbone(cfg.model_copy(update={"pre_relu": False}), sd)(images)
    for a, b in zip(pre, post):
        assert (a < 0).any()
        assert (b >= 0).all()
        np.testing.assert_array_equal(b, np.maximum(a, 0))
    assert pre[0].shape == (1, 512, 4, 4) and pre[1].shape == (1, 512, 8, 8)


def test_random_weights_need_no_files():
    backbone = load_backbone(BackboneConfig(weights="random", device="cpu", input_size=32))
    m1, m2 = backbone(np.zeros((1, 32, 32, 3), np.uint8))
    assert m1.shape == (1, 512, 2, 2) and m2.shape == (1, 512, 4, 4)


# ---- real weights ------------------------------------------------------------------------


def test_first_conv_on_constant_image_matches_manual_dot_product(real_sd):
    """A constant image makes conv1_1 at an interior pixel bias + sum_c x_c * sum(w[o, c]);
    at the corner only the 2x2 lower-right part of the kernel sees the image (zero padding)."""
    backbone = Backbone(BackboneConfig(weights="x", device="cpu", input_size=32, precision="fp32"), real_sd)
    rgb = np.array([200, 100, 50], np.uint8)
    image = np.broadcast_to(rgb, (1, 32, 32, 3)).copy()
    x = _preprocess(image, "torchvision")
    with torch.no_grad():
        out = backbone.net(x, {0: True})[0][0].numpy()  # (64, 32, 32)
    w = real_sd["features.0.weight"].numpy().astype(np.float64)
    b = real_sd["features.0.bias"].numpy().astype(np.float64)
    xc = (rgb / 255.0 - TV_MEAN.astype(np.float64)) / TV_STD.astype(np.float64)
    interior = b + np.einsum("ochw,c->o", w, xc)
    corner = b + np.einsum("ochw,c->o", w[:, :, 1:, 1:], xc)
    np.testing.assert_allclose(out[:, 10, 17], interior, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out[:, 0, 0], corner, rtol=1e-4, atol=1e-4)
    # and the same through conv2d on the full image
    ref = F.conv2d(x, real_sd["features.0.weight"], real_sd["features.0.bias"], padding=1)[0].numpy()
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def oracle(real_sd, small_images):
    """Oracle maps per (preprocessing, pre_relu), each preprocessing computed once."""
    cache: dict[tuple[str, bool], dict[str, torch.Tensor]] = {}

    def get(preprocessing: str, pre_relu: bool) -> dict[str, torch.Tensor]:
        if (preprocessing, pre_relu) not in cache:
            pre = _oracle_maps(small_images, real_sd, preprocessing, True)
            cache[preprocessing, True] = pre
            cache[preprocessing, False] = {k: F.relu(v) for k, v in pre.items()}
        return cache[preprocessing, pre_relu]

    return get


@pytest.fixture(scope="module")
def backbone_maps(real_sd, small_images):
    cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def get(preprocessing: str, pre_relu: bool, stage1: str = "conv5_2", stage2: str = "conv4_2"):
        key = (preprocessing, pre_relu, stage1, stage2)
        if key not in cache:
            config = BackboneConfig(
                weights="x", device="cpu", input_size=64, preprocessing=preprocessing, pre_relu=pre_relu,
                stage1_layer=stage1, stage2_layer=stage2, precision="fp32",
            )  # fmt: skip
            cache[key] = Backbone(config, real_sd)(small_images)
        return cache[key]

    return get


@pytest.mark.parametrize(
    "preprocessing, pre_relu, stage1, stage2",
    [
        ("torchvision", True, "conv5_2", "conv4_2"),  # the paper's default
        ("caffe", True, "conv5_2", "conv4_2"),
        ("torchvision", False, "conv5_3", "conv3_3"),
    ],
)
def test_maps_match_functional_vgg16_oracle(oracle, backbone_maps, preprocessing, pre_relu, stage1, stage2):
    m1, m2 = backbone_maps(preprocessing, pre_relu, stage1, stage2)
    want_maps = oracle(preprocessing, pre_relu)
    for got, name in ((m1, stage1), (m2, stage2)):
        want = want_maps[name].numpy()
        assert got.shape == want.shape
        scale = float(np.abs(want).max())
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * scale)
    if pre_relu:
        assert (m1 < 0).any() and (m2 < 0).any()
    else:
        assert (m1 >= 0).all() and (m2 >= 0).all()


def test_caffe_and_torchvision_preprocessing_differ(backbone_maps):
    for a, b in zip(backbone_maps("torchvision", True), backbone_maps("caffe", True)):
        assert a.shape == b.shape
        assert np.abs(a - b).mean() > 0.05 * np.abs(a).mean()


def test_load_backbone_from_explicit_path(weights_path, real_sd):
    config = BackboneConfig(weights=str(weights_path), device="cpu", input_size=32, precision="fp32")
    backbone = load_backbone(config)
    loaded = backbone.net.state_dict()
    assert set(loaded) == {
        f"features.{i}.{p}" for i in (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26) for p in ("weight", "bias")
    }
    for key, value in loaded.items():
        assert torch.equal(value, real_sd[key])


def test_load_backbone_missing_path_is_reported(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(WeightsNotFoundError, match="nope.pth"):
        load_backbone(BackboneConfig(weights=str(missing), device="cpu", allow_download=False))


# ---- errors ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "images",
    [
        np.zeros((1, 64, 64), np.uint8),  # no channel axis
        np.zeros((64, 64, 3), np.uint8),  # no batch axis
        np.zeros((1, 63, 64, 3), np.uint8),  # wrong size
        np.zeros((1, 64, 64, 4), np.uint8),  # RGBA not converted
        np.zeros((1, 3, 64, 64), np.uint8),  # channels first
        np.zeros((1, 64, 64, 3), np.float32),  # float
        np.zeros((1, 64, 64, 3), np.uint16),
    ],
)
def test_wrong_input_is_refused(random_backbone_64, images):
    with pytest.raises(LoopClosureInputError, match=r"\(B, 64, 64, 3\)"):
        random_backbone_64(images)


def test_no_weights_without_random_opt_in_is_refused():
    with pytest.raises(LoopClosureInputError, match="random"):
        Backbone(BackboneConfig(weights=None, device="cpu"), None)


def test_missing_key_in_state_dict_is_named():
    sd = _random_sd()
    del sd["features.19.weight"]
    with pytest.raises(LoopClosureInputError, match=r"features\.19\.weight"):
        Backbone(BackboneConfig(weights="x", device="cpu"), sd)


def test_state_dict_too_shallow_for_the_layers():
    torch.manual_seed(0)
    sd = VGG16Features("conv4_2").state_dict()  # no conv4_3 .. conv5_2
    with pytest.raises(LoopClosureInputError, match=r"features\.21\.weight.*5 more"):
        Backbone(BackboneConfig(weights="x", device="cpu"), sd)


def test_shallower_layers_need_only_their_weights():
    torch.manual_seed(0)
    sd = VGG16Features("conv4_2").state_dict()
    config = BackboneConfig(weights="x", device="cpu", input_size=32, stage1_layer="conv4_2", stage2_layer="conv3_3")
    m1, m2 = Backbone(config, sd)(np.zeros((1, 32, 32, 3), np.uint8))
    assert m1.shape == (1, 512, 4, 4) and m2.shape == (1, 256, 8, 8)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_requested_without_cuda():
    with pytest.raises(LoopClosureInputError, match="cuda"):
        Backbone(BackboneConfig(weights="random", device="cuda"), None)
