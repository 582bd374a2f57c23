"""Every parameter of SSM-VPR, as pydantic models; the defaults are the ECMR 2019 paper's.

The application composes these with its own sections and loads YAML presets over them;
this package only needs the models, so it stays usable on its own.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ssmvpr_common.settings_model import SettingsModel


class BackboneConfig(SettingsModel):
    """VGG16 truncated after the deepest layer SSM-VPR reads."""

    weights: str | None = Field(
        default=None,
        description="Path to a torchvision-layout VGG16 state dict, 'random' (tests only), "
        "or None to resolve automatically (SSMVPR_WEIGHTS, cache, download).",
    )
    allow_download: bool = Field(
        default=True,
        description="Download the ImageNet VGG16 weights when no path, SSMVPR_WEIGHTS or cached file gives them.",
    )
    device: Literal["auto", "cpu", "cuda"] = Field(
        default="auto", description="Where VGG16 runs; auto is cuda when torch sees a GPU, else cpu."
    )
    input_size: int = Field(
        default=224, ge=32, description="Side in pixels of the square every image is resized to (no crop)."
    )
    preprocessing: Literal["torchvision", "caffe"] = Field(
        default="torchvision",
        description="Input normalisation: torchvision (RGB, ImageNet mean/std) or caffe (BGR, 0-255, mean subtracted).",
    )
    pre_relu: bool = Field(default=True, description="Take activations before the ReLU, as the authors' code does.")
    stage1_layer: Literal["conv4_2", "conv4_3", "conv5_1", "conv5_2", "conv5_3"] = Field(
        default="conv5_2", description="VGG16 layer whose map is cut into the stage-I (filtering) cubes."
    )
    stage2_layer: Literal["conv3_3", "conv4_1", "conv4_2", "conv4_3"] = Field(
        default="conv4_2", description="VGG16 layer whose map is cut into the stage-II (spatial) cubes."
    )
    batch_size: int = Field(
        default=8, ge=1, description="Images per VGG16 forward pass when encoding or fitting PCA on many images."
    )
    num_threads: int | None = Field(default=None, ge=1, description="torch CPU threads; None keeps torch's default.")
    projection: Literal["auto", "numpy", "torch"] = Field(
        default="auto",
        description="Where a stream's maps become codes (cubes, then PCA): numpy on the host, the reference, or "
        "torch on the backbone's device, so that only the codes leave a GPU (the same codes to float rounding, "
        "docs/streaming.md). auto: torch where the backbone runs on CUDA, numpy elsewhere (on 2 CPU cores torch "
        "saved 3 ms of a 288 ms stage). PCA is fitted on the host either way.",
    )
    # fp32 stays the default: bf16 moved Corridor's single-frame PR-AUC by 0.010 (one query of 111),
    # more than the 0.005 allowed, though its sequence (L=3) PR-AUC moved by 0.0002 (docs/benchmarks.md, "Speed").
    precision: Literal["auto", "fp32", "bf16", "int8"] = Field(
        default="fp32",
        description="fp32: torch fp32, the reference (reproducible results). auto: bf16 on a CPU with "
        "AVX512-BF16 or AMX (/proc/cpuinfo flags), bf16 (else fp16) on CUDA, fp32 otherwise. int8: ONNX "
        "Runtime (extra 'int8') calibrated on int8_calibration (or on the first images). Outputs are float32 maps in every case.",
    )
    int8_calibration: str | None = Field(
        default=None,
        description="Folder of reference images (e.g. those PCA is fitted on) that calibrate precision int8. "
        "None: the first int8_calibration_images images the backbone is given calibrate it (fp32 until then).",
    )
    int8_calibration_images: int = Field(
        default=32, ge=1, description="Images taken evenly from int8_calibration, or the first ones without it."
    )


class CubeConfig(SettingsModel):
    """How a conv map is cut into cubes: LxLxC windows at a stride, each flattened."""

    cube_size: int = Field(ge=1, description="L: side of a cube, in conv-map cells.")
    stride: int = Field(ge=1, description="Step, in conv-map cells, between neighbouring cubes.")
    l2_normalize_locations: bool = Field(
        default=True, description="L2-normalise each location's channel vector before cutting cubes (the paper's)."
    )


class PCAConfig(SettingsModel):
    dim: int = Field(default=100, ge=1, description="Dimensions a cube vector is projected to.")
    whiten: bool = Field(default=False, description="Divide each PCA component by its standard deviation.")
    l2_normalize_output: bool = Field(
        default=True, description="Unit-length codes make nearest-neighbour and best-cell search cosine."
    )
    max_fit_samples: int = Field(default=40000, ge=1, description="Cube vectors kept (seeded subsample) for fitting.")
    max_fit_images: int = Field(default=300, ge=1, description="Images whose feature maps are held for fitting.")
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="Of the subsample and of sklearn (0 .. 2**32 - 1).")


class FilteringConfig(SettingsModel):
    """Stage I: histogram voting over nearest stage-I vectors."""

    cubes: CubeConfig = CubeConfig(cube_size=7, stride=2)
    pca: PCAConfig = PCAConfig(dim=100)
    num_candidates: int = Field(default=50, ge=1, description="N: places kept for spatial matching.")
    neighbours_per_vector: int | None = Field(
        default=None, ge=1, description="Nearest database vectors per query vector; None uses N as the paper does."
    )
    # The nearest-vector search behind the votes (loopclosure/ann_index.py). exact and numpy give
    # the same votes bit for bit (tested); ivf/hnsw are approximate (docs/benchmarks.md, "Speed": recall@N).
    index: Literal["auto", "exact", "ivf", "hnsw", "numpy"] = Field(
        default="auto",
        description="exact: faiss brute-force inner products; ivf: faiss IVF (trained k-means lists), "
        "hnsw: faiss HNSW graph (no training, slow to build); auto: exact up to ann_threshold_places, "
        "ivf beyond (exact at any size when the exact search runs on a GPU); numpy: the reference "
        "brute force without faiss.",
    )
    exact_backend: Literal["auto", "faiss", "torch"] = Field(
        default="auto",
        description="exact search: faiss's brute force on the CPU, or torch matrix products on torch_device "
        "(a GPU keeps a copy of every stage-I vector and scans them all per query; the same votes, bit for "
        "bit, as the exact re-scoring decides in both); auto: torch where torch sees a GPU and torch_device "
        "is not cpu, faiss otherwise.",
    )
    torch_device: Literal["auto", "cpu", "cuda"] = Field(
        default="auto", description="exact_backend torch: where it runs; auto is cuda when torch sees a GPU, else cpu."
    )
    torch_storage: Literal["auto", "float32", "float16"] = Field(
        default="auto",
        description="exact_backend torch: the device copy's precision; auto is float16 on a GPU (a scan reads "
        "half the bytes; the proposal margin widens by float16's rounding, so the votes stay exact) and "
        "float32 on the CPU.",
    )
    torch_block_rows: int | None = Field(
        default=None,
        ge=1,
        description="exact_backend torch: stage-I vectors multiplied per block, so a query holds one block of "
        "similarities on the device, not the whole map's (1M places are 16M vectors: 1 GB per query); "
        "None: as many as 256 MB of similarities hold on the CPU, 1 GB on a GPU of 64 GB or more "
        "(1/64 of a smaller one's memory).",
    )
    ann_threshold_places: int = Field(
        default=50_000, ge=1, description="auto: places from which IVF replaces exact search on the CPU."
    )
    ivf_nlist: int | None = Field(
        default=None, ge=1, description="IVF lists; None: 4*sqrt(vectors) as a power of two in [64, 16384]."
    )
    ivf_nprobe: int = Field(
        default=64,
        ge=1,
        description="IVF lists searched per query vector: more finds more of the exact candidates, slower "
        "(docs/benchmarks.md).",
    )
    ivf_codes: Literal["flat", "sq8"] = Field(
        default="flat",
        description="Vectors in the IVF lists: float32 (flat) or 8-bit per dimension (sq8, 4x smaller; "
        "its approximate similarities are re-scored exactly from the database, fetch more with ann_candidates_factor).",
    )
    ivf_train_vectors: int = Field(
        default=40, ge=1, description="Training sample per IVF list (k-means on that many times nlist vectors)."
    )
    ivf_retrain_growth: float = Field(
        default=4.0, gt=1.0,
        description="Retrain (new k-means, all vectors re-added) when the map has grown this many times "
        "since the last training: lists trained on the first streets go on fitting a grown city.",
    )  # fmt: skip
    hnsw_m: int = Field(default=32, ge=4, description="HNSW links per vector.")
    hnsw_ef_construction: int = Field(default=80, ge=1, description="HNSW build breadth (faiss efConstruction).")
    hnsw_ef_search: int = Field(default=128, ge=1, description="HNSW search breadth (at least k is used).")
    ann_candidates_factor: float = Field(
        default=1.0,
        ge=1.0,
        description="ivf/hnsw: neighbours fetched per query vector, times k, then re-scored exactly.",
    )
    faiss_threads: int = Field(
        default=1,
        ge=1,
        description="Threads of a stage-I search on the CPU: faiss's OpenMP threads, or torch's for exact_backend "
        "torch on the CPU (2 cores shared: 1).",
    )

    @property
    def k_neighbours(self) -> int:
        return self.neighbours_per_vector or self.num_candidates


class SpatialConfig(SettingsModel):
    """Stage II: anchor row/column consistency on the conv4_2 grid."""

    cubes: CubeConfig = CubeConfig(cube_size=3, stride=2)
    # Unnormalised stage-II codes: the best cell is found by L2, which normalising hurt (docs/method.md).
    pca: PCAConfig = PCAConfig(dim=100, l2_normalize_output=False)
    chunk_candidates: int = Field(default=64, ge=1, description="Candidates scored per batched matmul.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        default="auto",
        description="Where stage II runs: cpu is numpy (the reference), cuda torch with every candidate in one "
        "batch; auto follows the backbone (cuda when it runs on a GPU).",
    )


class DatabaseConfig(SettingsModel):
    """How place codes are stored: float, or int8 with one float32 scale per vector (x ~ q * s,
    s = max|x| / 127): 19.2 kB per place instead of 40.2 kB (docs/benchmarks.md, "Speed")."""

    stage1_dtype: Literal["float16", "float32", "int8"] = Field(
        default="float32", description="Storage type of the stage-I codes."
    )
    stage2_dtype: Literal["float16", "float32", "int8"] = Field(
        default="float16", description="Storage type of the stage-II codes."
    )


class FrameCorrelationConfig(SettingsModel):
    """The RAS 2020 prior: candidates near the last recognitions get extra votes."""

    enabled: bool = Field(
        default=False, description="Use the prior in vpr-eval (the default of --sequential); SLAM runs never use it."
    )
    history: int = Field(default=2, ge=1, description="How many previous recognitions boost candidates.")
    radius: int = Field(default=2, ge=0, description="Frames around a previous match (shifted by the step) boosted.")
    boost: float = Field(default=0.5, ge=0.0, description="Added to a boosted candidate's normalised stage-I score.")
    recover: bool = Field(
        default=True,
        description="A recognition that won only through the boost boosts nothing later, so a wrong lock dies "
        "after `history` queries instead of feeding itself. False: the authors' prior as released.",
    )


class VPRConfig(SettingsModel):
    """The complete SSM-VPR recogniser."""

    backbone: BackboneConfig = BackboneConfig()
    filtering: FilteringConfig = FilteringConfig()
    spatial: SpatialConfig = SpatialConfig()
    database: DatabaseConfig = DatabaseConfig()
    frame_correlation: FrameCorrelationConfig = FrameCorrelationConfig()

    @model_validator(mode="after")
    def _layers_fit(self) -> VPRConfig:
        for name, cubes in (("filtering", self.filtering.cubes), ("spatial", self.spatial.cubes)):
            layer = self.backbone.stage1_layer if name == "filtering" else self.backbone.stage2_layer
            side = feature_side(layer, self.backbone.input_size)
            if cubes.cube_size > side:
                raise ValueError(
                    f"{name}.cubes.cube_size={cubes.cube_size} exceeds the {side}x{side} {layer} map "
                    f"at input_size={self.backbone.input_size}"
                )
        return self


LAYER_DOWNSAMPLING = {
    "conv3_3": 4,
    "conv4_1": 8,
    "conv4_2": 8,
    "conv4_3": 8,
    "conv5_1": 16,
    "conv5_2": 16,
    "conv5_3": 16,
}


def feature_side(layer: str, input_size: int) -> int:
    """Side of a square VGG16 map at `layer` (each max-pool halves, flooring)."""
    side = input_size
    for _ in range({4: 2, 8: 3, 16: 4}[LAYER_DOWNSAMPLING[layer]]):
        side //= 2
    return side


def grid_side(map_side: int, cubes: CubeConfig) -> int:
    return (map_side - cubes.cube_size) // cubes.stride + 1


class VerifierConfig(SettingsModel):
    """Two-view verification on the backbone's own features (loopclosure/pair_verifier.py); the
    thresholds are those measured on the shared real pairs (docs/loop_verification.md)."""

    layer: Literal["conv3_3", "conv4_1", "conv4_2", "conv4_3"] = Field(
        default="conv4_2", description="VGG16 layer whose cells are matched (mutual nearest neighbours)."
    )
    width: int | None = Field(
        default=480, ge=64, description="Images are resized to this many pixels wide (aspect kept) before the "
        "backbone; None: as given. conv4_2 then has a cell every 8 px."
    )  # fmt: skip
    min_image_width: int = Field(
        default=160, ge=0, description="Images narrower than this (as given) are not judged: upscaled, they have "
        "no detail for geometry, and on Nordland-64's 64x32 frames 15 % of wrong pairs verified (0: judge all)."
    )  # fmt: skip
    grey: bool = Field(
        default=True, description="Match the images' luminance (in all three channels): across day and night "
        "colour is a difference, not a cue."
    )  # fmt: skip
    max_distance_ratio: float = Field(
        default=1.0, gt=0.0, le=1.0, description="Lowe's test on the descriptor distances of a mutual match; 1: off."
    )
    threshold_cells: float = Field(
        default=0.75, gt=0.0, description="RANSAC inlier threshold in cells of the layer (a match's position is "
        "its cell's centre)."
    )  # fmt: skip
    confidence: float = Field(default=0.999, gt=0.0, lt=1.0, description="MAGSAC confidence.")
    max_iterations: int = Field(default=10000, ge=100, description="MAGSAC iterations at most.")
    min_inliers: int = Field(default=140, ge=8, description="Fewer inliers than this: not verified.")
    min_inlier_ratio: float = Field(
        default=0.34, ge=0.0, le=1.0, description="Inliers over mutual matches below this: not verified."
    )
    homography_share: float = Field(
        default=0.8, gt=0.0, description="With intrinsics: a homography explaining this share of the essential "
        "matrix's inliers, and a rotation, means no baseline (the rotation is read from it)."
    )  # fmt: skip
    rotation_tolerance: float = Field(
        default=0.1, gt=0.0, lt=1.0, description="The normalised homography counts as a rotation if its smallest "
        "singular value is at least 1 - this of its largest."
    )  # fmt: skip


class SequenceMatchConfig(SettingsModel):
    """Sequence matching on stage-II scores (SeqSLAM's idea on SSM-VPR scores).

    The score of query q -> place r averages s(q-k, r -/+ k) over k = 0..L-1: one frame can
    look like many places, a run of frames rarely matches a run of places by accident.
    """

    length: int = Field(default=1, ge=1, description="L: frames per sequence; 1 is single-frame recognition.")
    direction: Literal["forward", "reverse", "both"] = Field(
        default="forward",
        description="forward: r-k follows q-k (same driving direction); reverse: r+k; both: the better.",
    )
    speeds: list[float] = Field(
        default=[1.0],
        min_length=1,
        description="Places advanced per query step along a sequence (SeqSLAM's slopes), e.g. [0.75, 1, 1.25] "
        "tolerates speed changes between the visits. Each extra slope adds about L spatial scores per candidate.",
    )
    sequence_candidates: int | None = Field(
        default=10,
        ge=1,
        description="Only the best K stage-II candidates (plus the continued sequences) get sequence terms; "
        "None: all N (docs/benchmarks.md measures K against all).",
    )
    continuations: int = Field(
        default=3, ge=0, description="The previous query's best sequences continued as candidates (per direction)."
    )
    aggregation: Literal["mean", "median"] = Field(
        default="mean", description="How the L terms of a sequence combine (median resists one occluded frame)."
    )
    missing: Literal["zero", "skip", "shrink"] = Field(
        default="zero",
        description="A term that does not exist (before the stream or the database, a place the earlier query "
        "could not match) counts as score 0 (zero), is left out of the aggregate (skip), or is left out and "
        "the aggregate of n terms weighed by sqrt(n / L) (shrink: a short line's noise then matches a full one's).",
    )

    @model_validator(mode="after")
    def _positive_speeds(self) -> SequenceMatchConfig:
        if any(not (0.0 < v <= 4.0) for v in self.speeds):
            raise ValueError(f"speeds must lie in (0, 4], got {self.speeds}")
        return self


class SequenceGateConfig(SettingsModel):
    """The sequence prior as a gate: a closure needs L consistent recognitions in a row."""

    enabled: bool = Field(
        default=False,
        description="Also require the top-1 gate after the sequence score accepted (an extra check; it costs recall).",
    )
    length: int = Field(default=3, ge=1, description="L: the closure and its L-1 predecessors must agree.")
    tolerance: int = Field(default=2, ge=0, description="±frames a predecessor's match may deviate.")
    allow_reverse: bool = Field(default=True, description="Accept revisits travelled in the opposite direction.")


class CalibratedDecisionConfig(SettingsModel):
    """The decision score that transfers between worlds (detector.decision: calibrated).

    A keyframe's scores are centred on its own field (the mean stage-II score of its stage-I
    candidates) before they are added up along a sequence. The winner's centred sequence score
    is then compared with what wrong matches score *in this stream*: the runner-ups (each
    query's best sequence away from its winner and from places already joined to it by an
    accepted loop). z = (winner - median of the last `history` runner-ups) / their spread
    (twice the median absolute deviation); while the stream has few runner-ups a prior in
    field spreads bounds both from below. Absolute stage-II levels differ by texture, camera and light (a night
    walk's right matches score like a simulated city's aliases); a lead over the stream's own
    runner-ups does not (docs/loop_decisions.md)."""

    accept: float = Field(
        default=6.0, description="z from which a proposal is accepted (chosen on Gardens Point, Nordland, Corridor "
        "and the simulated demo together)."
    )  # fmt: skip
    propose: float = Field(default=3.0, description="z below which nothing is proposed (no row in loop_closures.csv).")
    min_single: float = Field(
        default=0.0,
        description="The keyframe's own centred score against the place, in runner-up spreads, needed to accept: "
        "a sequence that has just ended must not carry a loop onto a keyframe that no longer looks like the place.",
    )
    history: int = Field(default=300, ge=5, description="Runner-ups the stream's wrong-match model keeps (newest).")
    min_history: int = Field(
        default=5, ge=3, description="Runner-ups before the stream's own model counts (the prior alone before)."
    )
    prior_median: float = Field(
        default=0.5, ge=0.0, description="The prior's median runner-up, in field spreads (the interquartile range "
        "of a keyframe's stage-II scores over its stage-I candidates)."
    )  # fmt: skip
    prior_spread: float = Field(default=0.6, ge=0.0, description="The prior's runner-up spread, in field spreads.")
    prior_runner_ups: int = Field(
        default=40, ge=0, description="Runner-ups of the stream's own up to which the prior's bounds hold in full; "
        "beyond, they weigh prior_runner_ups / runner-ups seen (0: no prior, decide from min_history on)."
    )  # fmt: skip
    min_field: int = Field(
        default=10, ge=1, description="Places a keyframe must be able to match (stage-I candidates) to decide."
    )
    runner_up_window: int = Field(
        default=3, ge=0, description="Places within this many of the winner (or of a place joined to it) are not "
        "its runner-up: neighbours of the right place score like it."
    )  # fmt: skip
    link_accepted: bool = Field(
        default=True,
        description="An accepted loop joins its two places: a third visit's match to the second is not measured "
        "against the first (the same place), only against other places.",
    )

    @model_validator(mode="after")
    def _order(self) -> CalibratedDecisionConfig:
        if self.propose > self.accept:
            raise ValueError(f"propose ({self.propose}) must not exceed accept ({self.accept})")
        if self.min_history > self.history:
            raise ValueError(f"min_history ({self.min_history}) must not exceed history ({self.history})")

        return self


class RearCameraConfig(SettingsModel):
    """A backward-looking camera, queried against the forward camera's places (never added).

    At a street driven the other way it looks where the forward camera looked on the earlier
    visit, so its sequences run the other way along the places (`direction: reverse`). Its
    calibrated decision has a runner-up model of its own (its scores run lower: the other lane).
    The absolute thresholds apply with `detector.decision: absolute` only (chosen on the
    simulator's demo traverse)."""

    enabled: bool = Field(default=True, description="Query with the rear image when a keyframe has one.")
    keep_codes: bool = Field(
        default=False,
        description="Keep each keyframe's rear-image codes beside the places (saved with the database as rear/): "
        "a later session driving a street the other way is recognised against them (`map` sets it; a checkpoint "
        "does not hold them, so a resumed run keeps those of the keyframes after the resume only).",
    )
    direction: Literal["forward", "reverse", "both"] = Field(
        default="reverse", description="Sequence direction of the rear camera's matches (reverse: the street "
        "driven the other way)."
    )  # fmt: skip
    accept: float | None = Field(default=None, description="Calibrated accept z; None: the forward camera's.")
    min_score: float = Field(
        default=0.2,
        ge=0.0,
        le=1.0,
        description="decision absolute: rear sequence score below which nothing is proposed.",
    )
    accept_score: float = Field(
        default=0.27,
        ge=0.0,
        le=1.0,
        description="decision absolute: rear sequence score from which a proposal is accepted.",
    )
    min_single_score: float = Field(
        default=0.2,
        ge=0.0,
        le=1.0,
        description="decision absolute: the rear image's own stage-II score needed to accept.",
    )


class DetectorConfig(SettingsModel):
    """Streaming loop-closure detection over keyframes."""

    exclusion_keyframes: int = Field(default=30, ge=0, description="The most recent keyframes are never candidates.")
    exclusion_distance: float = Field(
        default=15.0,
        ge=0.0,
        description="Keyframes within this travelled distance (m) of the query are never candidates.",
    )
    decision: Literal["calibrated", "absolute"] = Field(
        default="calibrated",
        description="calibrated: accept on the winner's lead over this stream's runner-ups (`calibrated`), which "
        "holds on real and simulated streams alike; absolute: on raw sequence scores against min_score, "
        "accept_score and min_single_score (thresholds of the simulator, kept to reproduce earlier runs).",
    )
    calibrated: CalibratedDecisionConfig = CalibratedDecisionConfig()
    min_score: float = Field(
        default=0.3, ge=0.0, le=1.0,
        description="decision absolute: sequence score below which nothing is proposed.",
    )  # fmt: skip
    accept_score: float | None = Field(
        default=0.45,
        ge=0.0,
        le=1.0,
        description="decision absolute: sequence score from which a proposal is accepted (None: min_score).",
    )
    min_single_score: float = Field(
        default=0.25, ge=0.0, le=1.0,
        description="decision absolute: the keyframe's own stage-II score against the match needed to accept.",
    )  # fmt: skip
    sequence: SequenceMatchConfig = SequenceMatchConfig(
        length=8, direction="forward", sequence_candidates=20, missing="shrink"
    )
    gate: SequenceGateConfig = SequenceGateConfig()
    pca_warmup_keyframes: int = Field(
        default=30, ge=2, description="Without codebooks, fit PCA on the first keyframes, then start querying "
        "(earlier at a seam, `LoopDetector.break_sequence`, when the keyframes so far suffice). No longer than "
        "exclusion_keyframes, it costs a stream nothing: those keyframes could not be matched yet anyway."
    )  # fmt: skip
    codebooks: str | None = Field(
        default=None, description="Codebooks (.npz from fit-pca) to use from the first keyframe."
    )
    camera_hfov_deg: float = Field(
        default=90.0, gt=0.0, lt=180.0, description="Turns a grid column shift into a yaw guess."
    )
    rear: RearCameraConfig = RearCameraConfig()

    @property
    def accept_threshold(self) -> float:
        return self.min_score if self.accept_score is None else self.accept_score

    @property
    def rear_accept(self) -> float:
        """The rear camera's calibrated accept z."""
        return self.calibrated.accept if self.rear.accept is None else self.rear.accept
