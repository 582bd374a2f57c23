"""VGG16 in plain torch (torchvision's layer indices), truncated after the layers SSM-VPR reads.

torchvision is not importable beside the CPU torch build this project targets, so the
network is spelled out here; the state-dict keys match torchvision's `vgg16().features`
so its official weights (and anything converted to that layout) load unchanged.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
from torch import nn

from loopclosure.config import BackboneConfig
from loopclosure.errors import LoopClosureInputError

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
            layers += [nn.Conv2d(in_ch, out_ch, kernel_size=3, padding=1), nn.ReLU(inplace=False)]
            in_ch = out_ch
            index += 2
        self.features = nn.Sequential(*layers[: last_index + 2])

    def forward(self, x: torch.Tensor, taps: dict[int, bool]) -> dict[int, torch.Tensor]:
        """Run once; `taps` maps a conv index to True for its pre-ReLU output, False for post-ReLU."""
        wanted = {(conv if pre else conv + 1): conv for conv, pre in taps.items()}
        out: dict[int, torch.Tensor] = {}
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index in wanted:
                out[wanted[index]] = x
                if len(out) == len(wanted):
                    break
        return out


class Backbone:
    """One forward pass giving the stage-I and stage-II conv maps of a batch of images."""

    def __init__(self, config: BackboneConfig, state_dict: dict[str, torch.Tensor] | None) -> None:
        self.config = config
        self.device = resolve_device(config.device)
        if config.num_threads is not None:
            torch.set_num_threads(config.num_threads)
        last = max((config.stage1_layer, config.stage2_layer), key=lambda n: CONV_INDEX[n])
        self.net = VGG16Features(last)
        if state_dict is None:
            if config.weights != "random":
                raise LoopClosureInputError("no VGG16 weights given; random weights need backbone.weights='random'")
            log.warning("VGG16 has RANDOM weights: recognition results are meaningless")
        else:
            wanted = self.net.state_dict().keys()
            missing = [k for k in wanted if k not in state_dict]
            if missing:
                raise LoopClosureInputError(f"VGG16 weights lack {missing[0]} (and {len(missing) - 1} more keys)")
            self.net.load_state_dict({k: state_dict[k] for k in wanted})
        self.net.eval().to(self.device)
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

    def _to_tensor(self, images: np.ndarray) -> torch.Tensor:
        """uint8 RGB (B, S, S, 3) -> normalised (B, 3, S, S) on the device."""
        x = torch.from_numpy(np.ascontiguousarray(images)).to(self.device)
        x = x.permute(0, 3, 1, 2).float()
        if self.config.preprocessing == "caffe":
            x = x.flip(1)  # RGB -> BGR, 0-255, mean subtracted
        return (x - self._mean) / self._std

    @torch.inference_mode()
    def __call__(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feature maps (B, C, H, W) as float32 numpy for stage I and stage II."""
        size = self.config.input_size
        if images.ndim != 4 or images.shape[1:] != (size, size, 3) or images.dtype != np.uint8:
            raise LoopClosureInputError(
                f"backbone expects uint8 images of shape (B, {size}, {size}, 3), got {images.dtype} {images.shape}"
            )
        maps = self.net(self._to_tensor(images), self._taps)
        return maps[self._i1].float().cpu().numpy(), maps[self._i2].float().cpu().numpy()


def load_backbone(config: BackboneConfig, progress: bool = False) -> Backbone:
    """Resolve weights as configured (explicit path, env, cache, download) and build the net."""
    if config.weights == "random":
        return Backbone(config, None)
    from loopclosure.weights import load_state_dict, resolve_weights

    path = resolve_weights(
        Path(config.weights).expanduser() if config.weights else None,
        allow_download=config.allow_download,
        progress=progress,
    )
    return Backbone(config, load_state_dict(path))
