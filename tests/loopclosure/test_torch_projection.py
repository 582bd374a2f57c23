"""loopclosure.torch_projection: cubes and PCA where the maps are (the GPU's memory on CUDA),
against the host's numpy reference (loopclosure.cubes + PCAProjection.transform).

Run here on the CPU: the same torch code runs on CUDA, where `vpr.backbone.projection: auto`
takes it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from loopclosure.backbone import Backbone
from loopclosure.backbone_input import list_images, read_image
from loopclosure.config import BackboneConfig, CubeConfig, FilteringConfig, PCAConfig, SpatialConfig, VPRConfig
from loopclosure.cubes import extract_cubes
from loopclosure.database import PlaceDatabase
from loopclosure.encoder import Encoder, PlaceCodes, RawCubes
from loopclosure.errors import LoopClosureInputError
from loopclosure.pca import Codebooks, fit_pca
from loopclosure.torch_projection import TorchProjection, uses_torch_projection
from loopclosure.two_stage import TwoStageRanker
from loopclosure.weights import load_state_dict


def _host_codes(config: VPRConfig, codebooks: Codebooks, maps1: np.ndarray, maps2: np.ndarray):
    stage1 = extract_cubes(maps1, config.filtering.cubes)
    stage1 = stage1.reshape(stage1.shape[0], -1, stage1.shape[-1])
    return codebooks.stage1.transform(stage1), codebooks.stage2.transform(extract_cubes(maps2, config.spatial.cubes))


@pytest.mark.parametrize("whiten", [False, True])
@pytest.mark.parametrize("normalise_locations", [True, False])
def test_small_maps_give_the_hosts_codes(whiten, normalise_locations):
    """Odd map sides, strides that leave a margin, whitening on and off, both output norms."""
    rng = np.random.default_rng(3)
    config = VPRConfig(
        filtering=FilteringConfig(cubes=CubeConfig(cube_size=3, stride=2, l2_normalize_locations=normalise_locations),
                                  pca=PCAConfig(dim=6, whiten=whiten)),
        spatial=SpatialConfig(cubes=CubeConfig(cube_size=2, stride=3, l2_normalize_locations=normalise_locations),
                              pca=PCAConfig(dim=5, whiten=whiten, l2_normalize_output=False)),
    )  # fmt: skip
    maps1 = rng.standard_normal((3, 8, 7, 7), dtype=np.float32)
    maps2 = rng.standard_normal((3, 4, 11, 10), dtype=np.float32)
    fit1 = extract_cubes(maps1, config.filtering.cubes).reshape(-1, 8 * 9)
    fit2 = extract_cubes(maps2, config.spatial.cubes).reshape(-1, 4 * 4)
    codebooks = Codebooks(fit_pca(fit1, config.filtering.pca), fit_pca(fit2, config.spatial.pca))

    stage1, stage2 = TorchProjection(config, codebooks, torch.device("cpu"))(
        torch.from_numpy(maps1), torch.from_numpy(maps2)
    )
    want1, want2 = _host_codes(config, codebooks, maps1, maps2)
    assert stage1.shape == want1.shape == (3, 9, 6) and stage2.shape == want2.shape == (3, 4, 3, 5)
    assert stage1.dtype == stage2.dtype == np.float32
    assert stage1.flags.c_contiguous and stage2.flags.c_contiguous  # laid out as the host's, for the products after
    np.testing.assert_allclose(stage1, want1, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(stage2, want2, rtol=1e-5, atol=1e-5)


def test_codebooks_of_other_cubes_are_refused():
    config = VPRConfig()
    rng = np.random.default_rng(0)
    small = Codebooks(fit_pca(rng.standard_normal((200, 120), dtype=np.float32), PCAConfig(dim=100)),
                      fit_pca(rng.standard_normal((200, 120), dtype=np.float32), PCAConfig(dim=100)))  # fmt: skip
    projection = TorchProjection(config, small, torch.device("cpu"))
    with pytest.raises(LoopClosureInputError, match="PCA expects vectors of 120 dims, got 25088"):
        projection(torch.zeros(1, 512, 14, 14), torch.zeros(1, 512, 28, 28))


def test_auto_takes_torch_on_cuda_only():
    def resolved(projection: str, device: str) -> bool:
        return uses_torch_projection(VPRConfig(backbone=BackboneConfig(projection=projection)), torch.device(device))

    assert resolved("auto", "cuda") and not resolved("auto", "cpu")
    assert resolved("torch", "cpu") and resolved("torch", "cuda")
    assert not resolved("numpy", "cuda") and not resolved("numpy", "cpu")


@pytest.fixture(scope="module")
def gardens(weights_path, gardens_dir):
    """Real VGG16 maps of Gardens Point mini (night references, day queries), one pass each,
    and PCA fitted on the references' cubes, on the host as a stream fits it."""
    config = VPRConfig(backbone=BackboneConfig(weights=str(weights_path), device="cpu", projection="torch"))
    backbone = Backbone(config.backbone, load_state_dict(weights_path))
    encoder = Encoder(config, backbone)
    refs = np.stack([encoder.prepare(read_image(p), p.name) for p in list_images(gardens_dir / "ref")])
    queries = np.stack([encoder.prepare(read_image(p), p.name) for p in list_images(gardens_dir / "query")])
    ref_maps = [m.numpy() for m in backbone.maps(refs)]
    query_maps = [m.numpy() for m in backbone.maps(queries)]
    stage1 = extract_cubes(ref_maps[0], config.filtering.cubes)
    raw = RawCubes(stage1.reshape(len(refs), -1, stage1.shape[-1]), extract_cubes(ref_maps[1], config.spatial.cubes))
    codebooks = encoder.fit_codebooks_from_raw([raw])
    return config, encoder, codebooks, refs, ref_maps, query_maps


def test_real_maps_give_the_hosts_codes_and_rankings(gardens):
    """The codes agree to float rounding, and stage I + II rank every day query's candidates
    among the night places in the same order either way."""
    config, _, codebooks, _, ref_maps, query_maps = gardens
    projection = TorchProjection(config, codebooks, torch.device("cpu"))
    rankings = []
    for codes_of in (lambda m: _host_codes(config, codebooks, *m), lambda m: projection(*map(torch.from_numpy, m))):
        ref1, ref2 = codes_of(ref_maps)
        query1, query2 = codes_of(query_maps)
        rankings.append((ref1, ref2, query1, query2))
    for host, device in zip(rankings[0], rankings[1]):
        scale = np.abs(host).max()
        np.testing.assert_allclose(device, host, rtol=0, atol=2e-5 * scale)

    def ranked(ref1, ref2, query1, query2):  # noqa: ANN001, ANN202
        database = PlaceDatabase(codebooks)
        database.add(PlaceCodes(ref1, ref2))
        ranker = TwoStageRanker(config, database)
        return [ranker.query(PlaceCodes(query1[q : q + 1], query2[q : q + 1])).ranked_places.tolist()
                for q in range(len(query1))]  # fmt: skip

    host_ranks, device_ranks = ranked(*rankings[0]), ranked(*rankings[1])
    assert host_ranks == device_ranks
    assert sum(ranks[0] == q for q, ranks in enumerate(host_ranks)) >= 4  # it recognises (chance: 1 of 10)


def test_encoder_takes_the_torch_path_when_configured(gardens):
    """`Encoder.codes` with projection torch reads the maps where they are (Backbone.maps) and
    gives what projecting the host's cubes gives."""
    config, encoder, codebooks, refs, *_ = gardens
    calls = []
    original = encoder.backbone.maps

    def spy(images):  # noqa: ANN001, ANN202
        calls.append(len(images))
        return original(images)

    encoder.backbone.maps = spy  # type: ignore[method-assign]
    try:
        codes = encoder.codes(list(refs[:2]))
    finally:
        del encoder.backbone.maps
    assert calls == [2]
    want = encoder.project(encoder.raw_cubes(list(refs[:2])))
    np.testing.assert_allclose(codes.stage1, want.stage1, rtol=0, atol=2e-5)
    np.testing.assert_allclose(codes.stage2, want.stage2, rtol=0, atol=2e-5 * np.abs(want.stage2).max())
    numpy_encoder = Encoder(config.model_copy(update={"backbone": config.backbone.model_copy(update={
        "projection": "numpy"})}), encoder.backbone, codebooks)  # fmt: skip
    np.testing.assert_array_equal(numpy_encoder.codes(list(refs[:2])).stage2, want.stage2)
