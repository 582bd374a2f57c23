"""int8 VGG16 through ONNX Runtime: export the truncated net, calibrate it on reference images,
quantise it statically, run it.

Plain torch has no fast int8 convolution on x86 for this net, so int8 goes through a runtime made
for it (ONNX Runtime's MLAS kernels use AVX512-VNNI / AVX-VNNI). It is an optional extra
(`pip install "ssmvpr-slam[int8]"`); without it, asking for int8 is one clear error.

Quantisation is static: activation ranges come from a calibration set the user supplies (the
reference images, e.g. those the PCA codebooks are fitted on), weights are int8 per output
channel, activations uint8 (the u8s8 layout the VNNI instructions take). The quantised model is
cached on disk under a key of everything that shapes it (weights, layers, calibration images,
ONNX Runtime version), so only the first run of a setting pays the ~10 s of calibration. Every
calibration set makes its own model, so the cache keeps the `CACHE_KEEP` most recently used.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import logging
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from loopclosure.cpu import cpu_flags
from loopclosure.errors import LoopClosureInputError
from ssmvpr_common.atomic import atomic_write

log = logging.getLogger(__name__)

INSTALL_HINT = "precision 'int8' needs ONNX Runtime and onnx: pip install \"ssmvpr-slam[int8]\""
INPUT_NAME = "images"
OUTPUT_NAMES = ("stage1", "stage2")
CACHE_VERSION = 2  # bump when the export or quantisation recipe changes
CACHE_KEEP = 8  # quantised models kept in the cache (12 MB each); the least recently used go first


def require_onnxruntime() -> Any:
    """The onnxruntime module, or one line saying how to install the extra."""
    try:
        import onnx  # noqa: F401  (the quantiser needs it)
        import onnxruntime
    except ImportError:
        raise LoopClosureInputError(INSTALL_HINT) from None
    return onnxruntime


def int8_available() -> bool:
    try:
        require_onnxruntime()
    except LoopClosureInputError:
        return False
    return True


def cpu_has_vnni() -> bool:
    """u8s8 products saturate in AVX2's vpmaddubsw; ONNX Runtime advises reduce_range without VNNI."""
    flags = cpu_flags()
    if flags is None:
        return bool(getattr(torch.cpu, "_is_vnni_supported", lambda: False)())
    return bool({"avx512_vnni", "avx_vnni", "amx_int8"} & flags)


class _TapsModule(nn.Module):
    """The backbone with its taps fixed, so it exports as a plain two-output graph."""

    def __init__(self, net: nn.Module, i1: int, i2: int, pre_relu: bool) -> None:
        super().__init__()
        self.net, self.i1, self.i2, self.pre_relu = net, i1, i2, pre_relu

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        maps = self.net(x, {self.i1: self.pre_relu, self.i2: self.pre_relu})
        return maps[self.i1], maps[self.i2]


def export_onnx(net: nn.Module, i1: int, i2: int, pre_relu: bool, input_size: int, path: Path) -> Path:
    """torch.onnx export of the truncated net (batch axis dynamic); needs no network access.

    The TorchScript exporter is used: it ships with torch and needs no onnxscript."""
    module = _TapsModule(net, i1, i2, pre_relu).eval().float()
    example = torch.zeros(1, 3, input_size, input_size)
    kwargs: dict[str, Any] = {
        "input_names": [INPUT_NAME],
        "output_names": list(OUTPUT_NAMES),
        "dynamic_axes": {INPUT_NAME: {0: "batch"}, OUTPUT_NAMES[0]: {0: "batch"}, OUTPUT_NAMES[1]: {0: "batch"}},
        "opset_version": 17,
    }
    if "dynamo" in inspect.signature(torch.onnx.export).parameters:
        kwargs["dynamo"] = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(module, (example,), str(path), **kwargs)
    return path


class _Batches:
    """onnxruntime.quantization.CalibrationDataReader over preprocessed batches."""

    def __init__(self, batches: Sequence[np.ndarray]) -> None:
        self._it: Iterator[np.ndarray] = iter(batches)

    def get_next(self) -> dict[str, np.ndarray] | None:
        batch = next(self._it, None)
        return None if batch is None else {INPUT_NAME: batch}

    def rewind(self) -> None:  # part of the reader protocol; one pass is all MinMax needs
        pass


@contextlib.contextmanager
def _quiet_root_logger() -> Iterator[None]:
    """The quantiser logs advice through the root logger; keep it off the user's console."""
    root = logging.getLogger()
    level = root.level
    root.setLevel(logging.ERROR)
    try:
        yield
    finally:
        root.setLevel(level)


def quantize(fp32_model: Path, calibration: Sequence[np.ndarray], out: Path, reduce_range: bool) -> Path:
    """Static QDQ quantisation: MinMax ranges on `calibration` (preprocessed NCHW float32 batches).

    Stays float:
    - the first convolution (0.6 % of the FLOPs): quantising the normalised image and conv1_1
      made half of the error in the maps (relative L2 of conv4_2 3.8 % -> 2.4 % without it);
    - the ReLUs right after the tapped convs: ONNX Runtime gives a ReLU's input the ReLU's own
      (non-negative) range when nothing else consumes it inside the graph, which would clip the
      pre-ReLU maps returned as graph outputs (measured: cosine 0.25 instead of 0.999)."""
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    graph = onnx.load(str(fp32_model)).graph
    first_conv = next(n.name for n in graph.node if n.op_type == "Conv")
    keep_float = [first_conv] + [n.name for n in graph.node if n.op_type == "Relu" and n.input[0] in OUTPUT_NAMES]
    with _quiet_root_logger(), tempfile.TemporaryDirectory() as tmp:
        staged = Path(tmp) / "int8.onnx"
        quantize_static(
            str(fp32_model), str(staged), _Batches(calibration),  # type: ignore[arg-type]
            quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
            per_channel=True, reduce_range=reduce_range, calibrate_method=CalibrationMethod.MinMax,
            nodes_to_exclude=keep_float,
        )  # fmt: skip
        data = staged.read_bytes()
    atomic_write(out, lambda handle: handle.write(data))
    return out


def cache_key(state: dict[str, torch.Tensor], settings: dict[str, Any], calibration: Sequence[np.ndarray]) -> str:
    """Hex digest of everything that shapes the quantised model."""
    ort = require_onnxruntime()
    h = hashlib.sha256()
    h.update(repr((CACHE_VERSION, ort.__version__, torch.__version__, sorted(settings.items()))).encode())
    for name in sorted(state):
        h.update(name.encode())
        h.update(state[name].detach().cpu().contiguous().numpy().tobytes())
    for batch in calibration:
        h.update(np.ascontiguousarray(batch).tobytes())
    return h.hexdigest()[:24]


class Int8Session:
    """A quantised model in an ONNX Runtime CPU session: NCHW float32 in, the two maps out."""

    def __init__(self, model: Path, num_threads: int | None) -> None:
        ort = require_onnxruntime()
        options = ort.SessionOptions()
        options.intra_op_num_threads = num_threads or 0  # 0: one per physical core
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        # Idle workers sleep instead of spinning, so cube extraction and PCA right after a pass
        # get the cores (the machine is shared by the SLAM stages).
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self.model = model
        self.session = ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m1, m2 = self.session.run(list(OUTPUT_NAMES), {INPUT_NAME: np.ascontiguousarray(x, dtype=np.float32)})
        return m1, m2


def build_int8_session(
    net: nn.Module,
    taps: tuple[int, int, bool],
    input_size: int,
    calibration: Sequence[np.ndarray],
    cache_dir: Path | None,
    num_threads: int | None,
) -> Int8Session:
    """Export, calibrate, quantise (or take the cached model), open a session."""
    require_onnxruntime()
    if not calibration:
        raise LoopClosureInputError("int8 calibration needs at least one image")
    i1, i2, pre_relu = taps
    reduce_range = not cpu_has_vnni()
    settings = {"taps": (i1, i2, pre_relu), "input_size": input_size, "reduce_range": reduce_range}
    key = cache_key(net.state_dict(), settings, calibration)
    cached = cache_dir / f"vgg16_int8_{key}.onnx" if cache_dir is not None else None
    if cached is not None and cached.is_file():
        _mark_used(cached)  # first, so that a pruning process sees it as the newest
        try:
            session = Int8Session(cached, num_threads)
            log.info("int8 VGG16 from the cache: %s", cached)
            return session
        except Exception as exc:  # removed meanwhile by another process's pruning, or unreadable
            log.warning("int8 cache: %s could not be opened (%s); calibrating again", cached, exc)
    with tempfile.TemporaryDirectory() as tmp:
        fp32 = export_onnx(net, i1, i2, pre_relu, input_size, Path(tmp) / "fp32.onnx")
        n = sum(len(b) for b in calibration)
        log.info("calibrating int8 VGG16 on %d images", n)
        target = cached if cached is not None else Path(tmp) / "int8.onnx"
        quantize(fp32, calibration, target, reduce_range)
        session = Int8Session(target, num_threads)  # the session holds the model in memory
    if cached is not None:
        prune_cache(cached.parent, CACHE_KEEP)
    return session


def _mark_used(model: Path) -> None:
    """Make a cache hit the most recently used model (its modification time is the use order)."""
    with contextlib.suppress(OSError):  # a read-only cache still serves; it just is not reordered
        model.touch()


def prune_cache(cache_dir: Path, keep: int) -> list[Path]:
    """Delete all but the `keep` most recently used quantised models; returns what went.

    A model another process has open stays readable there until it closes it (POSIX)."""
    models = sorted(cache_dir.glob("vgg16_int8_*.onnx"), key=_used_at, reverse=True)
    removed = []
    for model in models[keep:]:
        with contextlib.suppress(OSError):  # gone already (another process pruned it), or not ours
            model.unlink()
            removed.append(model)
    if removed:
        log.info("int8 cache: removed %d least recently used model(s) from %s", len(removed), cache_dir)
    return removed


def _used_at(model: Path) -> float:
    try:
        return model.stat().st_mtime
    except OSError:
        return float("-inf")
