"""VGG16 in plain torch (torchvision's layer indices), truncated after the layers SSM-VPR reads.

torchvision is not importable beside the CPU torch build this project targets, so the
network is spelled out here; the state-dict keys match torchvision's `vgg16().features`
so its official weights (and anything converted to that layout) load unchanged.

Precision (`BackboneConfig.precision`): torch fp32 is the reference; bf16 runs the same net with
bf16 weights and activations after an fp32 conv1_1 (oneDNN's AVX512-BF16 / AMX kernels on a CPU);
int8 runs a statically quantised export through ONNX Runtime (loopclosure.int8_runtime, an
optional extra). Every path
returns float32 NCHW numpy maps, so nothing downstream knows which one ran.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from loopclosure.config import BackboneConfig, VPRConfig
from loopclosure.cpu import cpu_flags
from loopclosure.errors import LoopClosureInputError

if TYPE_CHECKING:
    from loopclosure.int8_runtime import Int8Session

log = logging.getLogger(__name__)

# (name, index in torchvision's vgg16().features, out channels); pools sit between blocks.
_CONVS: list[tuple[str, int, int]] = [
    ("conv1_1", 0, 64), ("conv1_2", 2, 64),
    ("conv2_1", 5, 128), ("conv2_2", 7, 128),
    ("conv3_1", 10, 256), ("conv3_2", 12, 256), ("conv3_3", 14, 256),
    ("conv4_1", 17, 512), ("conv4_2", 19, 512), ("conv4_3", 21, 512),
    ("conv5_1", 24, 512), ("conv5_2", 26, 512), ("conv5_3", 28, 512),
]  # fmt: skip
_POOLS = (4, 9, 16, 23)
CONV_INDEX = {name: idx for name, idx, _ in _CONVS}
LAYER_CHANNELS = {name: channels for name, _, channels in _CONVS}


def cube_dims(config: VPRConfig) -> dict[str, int]:
    """Length of a cube vector at each stage ('stage1', 'stage2'): the tapped layer's channels
    times the cube's area, what that stage's PCA codebook takes."""
    return {
        "stage1": LAYER_CHANNELS[config.backbone.stage1_layer] * config.filtering.cubes.cube_size**2,
        "stage2": LAYER_CHANNELS[config.backbone.stage2_layer] * config.spatial.cubes.cube_size**2,
    }


_TORCHVISION_MEAN = (0.485, 0.456, 0.406)
_TORCHVISION_STD = (0.229, 0.224, 0.225)
_CAFFE_BGR_MEAN = (103.939, 116.779, 123.68)


def resolve_device(requested: str) -> torch.device:
    """'auto' takes CUDA when torch sees a GPU, so the same config runs on laptops and servers."""
    if requested == "cuda" and not torch.cuda.is_available():
        raise LoopClosureInputError("backbone.device='cuda' but torch sees no CUDA device")
    if requested == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(requested)


def cpu_has_fast_bf16() -> bool:
    """Whether the CPU computes bf16 products natively (AVX512-BF16 or AMX-BF16).

    Read from /proc/cpuinfo's flags: torch.backends.cpu.get_cpu_capability() says only
    'AVX512' and cannot tell a Zen 4 (bf16) from a Skylake-X (none). Where /proc/cpuinfo is
    missing (macOS, Windows), torch's own cpuinfo probe answers."""
    flags = cpu_flags()
    if flags is not None:
        return bool({"avx512_bf16", "amx_bf16"} & flags)
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(torch.cpu, name, lambda: False)()) for name in probes)


def resolve_precision(requested: str, device: torch.device) -> str:
    """'auto' -> bf16 on a CPU with native bf16, bf16 (else fp16) on CUDA, fp32 otherwise."""
    if requested == "auto":
        if device.type == "cuda":
            return "bf16" if torch.cuda.is_bf16_supported() else "fp16"
        return "bf16" if cpu_has_fast_bf16() else "fp32"
    if requested == "int8" and device.type != "cpu":
        raise LoopClosureInputError(
            f"backbone.precision='int8' runs on the CPU (ONNX Runtime); set backbone.device='cpu' (resolved: {device})"
        )
    return requested


_TORCH_DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


class VGG16Features(nn.Module):
    """`features` of VGG16 up to `last_layer`, returning the requested conv maps."""

    def __init__(self, last_layer: str) -> None:
        super().__init__()
        last_index = CONV_INDEX[last_layer]
        layers: list[nn.Module] = []
        in_ch = 3
        conv_iter = iter(_CONVS)
        index = 0
        while index <= last_index:
            if index in _POOLS:
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
                index += 1
                continue
            _, conv_idx, out_ch = next(conv_iter)
            assert conv_idx == index
            # in place: an out-of-place ReLU costs 16% of a bf16 pass (a new map to allocate and write)
            layers += [nn.Conv2d(in_ch, out_ch, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            in_ch = out_ch
            index += 2
        self.features = nn.Sequential(*layers[: last_index + 2])

    def forward(self, x: torch.Tensor, taps: dict[int, bool]) -> dict[int, torch.Tensor]:
        """Run once; `taps` maps a conv index to True for its pre-ReLU output, False for post-ReLU."""
        wanted = {(conv if pre else conv + 1): conv for conv, pre in taps.items()}
        out: dict[int, torch.Tensor] = {}
        for index, layer in enumerate(self.features):
            weight = getattr(layer, "weight", None)
            if weight is not None and x.dtype != weight.dtype:  # mixed precision: conv1_1 fp32, the rest bf16
                x = x.to(weight.dtype)
            x = layer(x)
            if index in wanted:
                last = len(out) + 1 == len(wanted)
                pre_relu = wanted[index] == index  # the ReLU next would overwrite it in place
                out[wanted[index]] = x.clone() if pre_relu and not last else x
                if last:
                    break
        return out


class Backbone:
    """One forward pass giving the stage-I and stage-II conv maps of a batch of images."""

    def __init__(
        self,
        config: BackboneConfig,
        state_dict: dict[str, torch.Tensor] | None,
        calibration_images: np.ndarray | None = None,
    ) -> None:
        """`calibration_images` (uint8, as __call__ takes) calibrate int8; without them int8 reads
        `config.int8_calibration`, and without that it calibrates on the first
        `int8_calibration_images` images it is given, answering in fp32 until then (a SLAM run's
        first keyframes, as its PCA is fitted on them). Other precisions ignore them."""
        self.config = config
        self.device = resolve_device(config.device)
        self.precision = resolve_precision(config.precision, self.device)
        if config.num_threads is not None:
            torch.set_num_threads(config.num_threads)
        last = max((config.stage1_layer, config.stage2_layer), key=lambda n: CONV_INDEX[n])
        self.net = VGG16Features(last)
        if state_dict is None:
            if config.weights != "random":
                raise LoopClosureInputError("no VGG16 weights given; random weights need vpr.backbone.weights: random")
            log.warning("VGG16 has RANDOM weights: recognition results are meaningless")
        else:
            wanted = self.net.state_dict().keys()
            missing = [k for k in wanted if k not in state_dict]
            if missing:
                raise LoopClosureInputError(f"VGG16 weights lack {missing[0]} (and {len(missing) - 1} more keys)")
            self.net.load_state_dict({k: state_dict[k] for k in wanted})
        self.net.eval().to(self.device)
        self._dtype = _TORCH_DTYPES.get(self.precision, torch.float32)
        self._int8: Int8Session | None = None
        self._calibrating: list[np.ndarray] | None = None  # int8 from the stream: images seen so far
        self._stream_calibration: np.ndarray | None = None  # int8 from the stream: the images it used
        self._i1 = CONV_INDEX[config.stage1_layer]
        self._i2 = CONV_INDEX[config.stage2_layer]
        self._taps = {self._i1: config.pre_relu, self._i2: config.pre_relu}
        if config.preprocessing == "torchvision":
            self._mean = torch.tensor(_TORCHVISION_MEAN).view(1, 3, 1, 1) * 255.0
            self._std = torch.tensor(_TORCHVISION_STD).view(1, 3, 1, 1) * 255.0
        else:
            self._mean = torch.tensor(_CAFFE_BGR_MEAN).view(1, 3, 1, 1)
            self._std = torch.ones(1, 3, 1, 1)
        self._mean, self._std = self._mean.to(self.device), self._std.to(self.device)
        if self.precision == "int8":
            if calibration_images is None and not config.int8_calibration:
                self._require_onnxruntime()
                self.net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # fp32 until calibrated
                self._calibrating = []
                log.info("int8: calibrating on the first %d images; fp32 until then", config.int8_calibration_images)
            else:
                self._int8 = self._build_int8(calibration_images)
        else:
            # NHWC: oneDNN's fast convolutions (the measured gain: tools/bench_backbone.py, docs/benchmarks.md)
            self.net.to(dtype=self._dtype, memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stub lacks memory_format
            # conv1_1 stays fp32 (0.6 % of the FLOPs): a bf16 image and conv1_1 made two thirds of
            # bf16's error (relative L2 of conv4_2 and conv5_2: 1.0 % -> 0.35 % with it in fp32).
            self.net.features[0].float()
        log.info("VGG16 backbone: %s on %s (requested %s)", self.precision, self.device, config.precision)

    @staticmethod
    def _require_onnxruntime() -> None:
        from loopclosure.int8_runtime import require_onnxruntime

        require_onnxruntime()  # the missing extra is reported before any image is read

    def _build_int8(self, images: np.ndarray | None) -> Int8Session:
        from loopclosure.int8_runtime import build_int8_session
        from loopclosure.weights import default_cache_dir

        self._require_onnxruntime()
        if images is None:
            images = self._calibration_from_config()
        else:
            self._check_images(images)
        batches = [self._to_tensor(images[i : i + 4]).numpy() for i in range(0, len(images), 4)]
        taps = (self._i1, self._i2, self.config.pre_relu)
        return build_int8_session(
            self.net, taps, self.config.input_size, batches, default_cache_dir() / "int8", self.config.num_threads
        )

    def _calibration_from_config(self) -> np.ndarray:
        """`int8_calibration_images` images spread evenly over the `int8_calibration` folder."""
        from loopclosure.backbone_input import as_rgb, list_images, read_image, resize_square
        from loopclosure.sampling import evenly_spaced

        folder = self.config.int8_calibration
        assert folder  # without one, __init__ calibrates on the stream instead
        files = list_images(Path(folder).expanduser())
        chosen = [files[i] for i in evenly_spaced(len(files), self.config.int8_calibration_images)]
        size = self.config.input_size
        return np.stack([resize_square(as_rgb(read_image(p), str(p)), size) for p in chosen])

    def _check_images(self, images: np.ndarray) -> None:
        size = self.config.input_size
        if images.ndim != 4 or images.shape[1:] != (size, size, 3) or images.dtype != np.uint8:
            raise LoopClosureInputError(
                f"backbone expects uint8 images of shape (B, {size}, {size}, 3), got {images.dtype} {images.shape}"
            )

    def _to_tensor(self, images: np.ndarray) -> torch.Tensor:
        """uint8 RGB (B, S, S, 3) -> normalised (B, 3, S, S) on the device."""
        x = torch.from_numpy(np.ascontiguousarray(images)).to(self.device)
        x = x.permute(0, 3, 1, 2).float()
        if self.config.preprocessing == "caffe":
            x = x.flip(1)  # RGB -> BGR, 0-255, mean subtracted
        return (x - self._mean) / self._std

    @torch.inference_mode()
    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feature maps (B, C, H, W) as float32 C-contiguous numpy for stage I and stage II,
        whatever the precision."""
        maps1, maps2 = self.maps(images)
        return maps1.cpu().numpy(), maps2.cpu().numpy()

    @torch.inference_mode()
    def maps(self, images: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """The stage-I and stage-II maps as float32 C-contiguous (B, C, H, W) tensors where the
        network left them (the GPU's memory on CUDA; int8's on the CPU), for work that can stay
        there (loopclosure.torch_projection)."""
        self._check_images(images)
        x = self._to_tensor(images)
        if self._int8 is not None:
            maps1, maps2 = self._int8(x.cpu().numpy())
            return torch.from_numpy(maps1), torch.from_numpy(maps2)
        maps = self.net(x.contiguous(memory_format=torch.channels_last), self._taps)
        if self._calibrating is not None:
            self._calibrate_on(images)
        return maps[self._i1].to(torch.float32).contiguous(), maps[self._i2].to(torch.float32).contiguous()

    @torch.inference_mode()
    def feature_map(self, image: np.ndarray, layer: str, pre_relu: bool = False) -> np.ndarray:
        """One conv map (C, h, w) float32 of a uint8 RGB image at its own size (not the square
        input_size): two-view verification needs the image's geometry, which the anisotropic
        square resize distorts. Runs the torch network in every precision (int8's session is built
        for the square input only); `layer` must be one the network computes. Post-ReLU by
        default: what dense matching was measured with (docs/loop_verification.md)."""
        if layer not in CONV_INDEX or CONV_INDEX[layer] >= len(self.net.features):
            raise LoopClosureInputError(f"feature_map: the backbone does not compute layer {layer!r}")
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise LoopClosureInputError(f"feature_map expects a uint8 (H, W, 3) image, got {image.dtype} {image.shape}")
        x = torch.from_numpy(np.ascontiguousarray(image)).to(self.device)[None].permute(0, 3, 1, 2).float()
        if self.config.preprocessing == "caffe":
            x = x.flip(1)
        x = (x - self._mean) / self._std  # the network casts it to each layer's precision
        index = CONV_INDEX[layer]
        maps = self.net(x.contiguous(memory_format=torch.channels_last), {index: pre_relu})
        return maps[index][0].to(torch.float32).contiguous().cpu().numpy()

    def _calibrate_on(self, images: np.ndarray) -> None:
        """Keep the images until there are enough, then build the int8 session from them."""
        assert self._calibrating is not None
        self._calibrating.extend(np.array(image) for image in images)
        if len(self._calibrating) >= self.config.int8_calibration_images:
            chosen = np.stack(self._calibrating[: self.config.int8_calibration_images])
            self._int8 = self._build_int8(chosen)  # a failure raises here, and the next call tries again
            self._calibrating = None
            self._stream_calibration = chosen
            log.info("int8: calibrated on the first %d images", len(chosen))

    @property
    def calibrates_on_stream(self) -> bool:
        """int8 whose calibration images come from the images it is given (no folder, none passed)."""
        return self._stream_calibration is not None or self._calibrating is not None

    @property
    def calibrating_on_stream(self) -> bool:
        """int8 still taking its calibration images from the images it is given: the order they
        come in shapes the model, so they must come in the stream's order."""
        return self._calibrating is not None

    def stream_calibration(self) -> tuple[np.ndarray, bool] | None:
        """(the stream images int8 calibration has taken, whether it has calibrated on them), or
        None when it does not calibrate on the stream. Once calibrated these are the
        `int8_calibration_images` images the model was built from; before, those seen so far
        (rear images included, when a keyframe brought one). A checkpoint keeps them: a resumed
        run must quantise with the model the run had, not calibrate again on the images after
        the resume (another model, and fp32 answers until then: codes the map was not built with)."""
        if self._stream_calibration is not None:
            return self._stream_calibration, True
        if self._calibrating is None:
            return None
        size = self.config.input_size
        seen = np.stack(self._calibrating) if self._calibrating else np.zeros((0, size, size, 3), np.uint8)
        return seen, False

    def resume_stream_calibration(self, images: np.ndarray, calibrated: bool) -> None:
        """Continue from `stream_calibration()` of an earlier backbone of the same config: the
        same int8 model (from the cache, or calibrated again on the same images), or, if that one
        had not seen enough images yet, the same images kept and the calibration still to come."""
        if self._calibrating is None or self._calibrating:
            raise LoopClosureInputError(
                "int8 stream calibration can only be resumed by a fresh int8 backbone that calibrates on "
                f"the stream (precision {self.precision}, int8_calibration {self.config.int8_calibration!r})"
            )
        images = np.asarray(images)
        self._check_images(images)
        wanted = self.config.int8_calibration_images
        if calibrated != (len(images) >= wanted) or (calibrated and len(images) != wanted):
            state = "calibrated on" if calibrated else "collecting, with"
            raise LoopClosureInputError(
                f"int8 stream calibration {state} {len(images)} images, but int8_calibration_images is {wanted}: "
                "resume with the run's settings"
            )
        self._calibrate_on(images)  # keeps them, and builds the model once there are enough


def load_backbone(config: BackboneConfig, progress: bool = False) -> Backbone:
    """Resolve weights as configured (explicit path, env, cache, download) and build the net."""
    from loopclosure.weights import configured_weights, load_state_dict

    path = configured_weights(config, progress)
    return Backbone(config, None if path is None else load_state_dict(path))
