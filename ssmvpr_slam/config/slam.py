"""The application's configuration: one pydantic model composed of each package's models.

Loading follows kiss-icp: defaults, then a YAML preset or file, then environment variables
(`SSMVPR_<SECTION>__<FIELD>=...`, e.g. `SSMVPR_VPR__BACKBONE__DEVICE=cpu`), then explicit
command-line options. Unknown keys are errors, so a typo in a preset fails loudly.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import BaseModel, Field, ValidationError
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict, SettingsError

from frontend.config import FrontendConfig
from frontend.simulation.config import SimulationConfig
from loopclosure.config import DetectorConfig, SequenceMatchConfig, VPRConfig
from ssmvpr_common.settings_model import SettingsModel
from ssmvpr_common.text_files import read_text
from ssmvpr_slam.backend.config import BackendConfig
from ssmvpr_slam.config.map import MapConfig
from ssmvpr_slam.config.pipeline import PipelineConfig
from ssmvpr_slam.config.presets import PRESETS_DIR, available_presets
from ssmvpr_slam.config.retired import retired_key
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.evaluation.config import EvaluationConfig


class ConfigError(SlamError, ValueError):
    """A preset or config file that cannot be used; the message names it."""


class VPREvalConfig(SettingsModel):
    """How `vpr-eval` scores recognition, as the paper does."""

    tolerance: int = Field(default=2, ge=0, description="A match within ±tolerance frames of the truth is correct.")
    plot_tolerances: list[int] = Field(default=[1, 2, 3], description="Tolerances drawn in the PR plot.")
    recall_ns: list[int] = Field(default=[1, 5, 10, 20, 50], description="N values of the recall@N curve.")
    sequence_lengths: list[Annotated[int, Field(ge=1)]] = Field(
        default=[], description="Sequence lengths L evaluated beside single frames (1 reproduces single frames)."
    )
    sequence: SequenceMatchConfig = Field(
        default=SequenceMatchConfig(direction="forward"),
        description="The sequence matcher's settings (its length is replaced by each of sequence_lengths).",
    )


class ResultsConfig(SettingsModel):
    out_dir: str = Field(
        default="results", description="Folder each command makes its results folder in (--out overrides it)."
    )
    save_database: bool = Field(default=True, description="Save the place database with run and vpr-eval results.")
    plots: bool = Field(default=True, description="Write PNG plots with run, vpr-eval and loop-eval results.")
    mcap: bool = Field(
        default=True, description="Write trajectory.mcap (trajectories, loop edges, thumbnails) for Foxglove."
    )
    mcap_thumbnail_width: int = Field(
        default=160, ge=8, description="Width in pixels of the keyframe thumbnails in trajectory.mcap."
    )
    checkpoint_every_keyframes: int | None = Field(
        default=100, ge=1, description="Write a checkpoint after this many new keyframes (None: not by count)."
    )
    checkpoint_every_s: float | None = Field(
        default=300.0,
        gt=0,
        description="Write a checkpoint when this many seconds passed since the last (None: not by time).",
    )


class SlamConfig(BaseSettings):
    # allow_inf_nan=False here and in every section's models: a NaN or inf setting passes every bound
    # (NaN compares false) and means nothing; tests/slam/test_config.py tries inf in every float key
    model_config = SettingsConfigDict(env_prefix="SSMVPR_", env_nested_delimiter="__", extra="forbid",
                                      allow_inf_nan=False)  # fmt: skip

    vpr: VPRConfig = VPRConfig()
    vpr_eval: VPREvalConfig = VPREvalConfig()
    detector: DetectorConfig = DetectorConfig()
    frontend: FrontendConfig = FrontendConfig()
    simulation: SimulationConfig = SimulationConfig()
    backend: BackendConfig = BackendConfig()
    evaluation: EvaluationConfig = EvaluationConfig()
    pipeline: PipelineConfig = PipelineConfig()
    results: ResultsConfig = ResultsConfig()
    map: MapConfig = MapConfig()

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # environment beats the YAML file handed in as init kwargs
        return env_settings, init_settings


def _read_yaml(path: Path) -> dict[str, Any]:
    text = read_text(path, ConfigError)  # a file that cannot be read, or is not UTF-8 text: one line naming it
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"config {path} is not valid YAML: {exc}".splitlines()[0]) from None
    if not isinstance(data, dict):
        raise ConfigError(f"config {path} must be a mapping of sections, got {type(data).__name__}")
    return data


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_config(config: str | Path | None = None, overrides: dict[str, Any] | None = None) -> SlamConfig:
    """`config` is a preset name (see `configs/`), a YAML path, or None for the `default` preset.

    A YAML file may name a base preset with `preset: NAME`; its keys then override that preset's.
    """
    data: dict[str, Any] = {}
    source = "defaults"
    if config is None and (PRESETS_DIR / "default.yaml").is_file():
        config = "default"
    if config is not None:
        path = Path(config)
        if not path.is_file():
            path = _preset_path(str(config), "--config")
        data = _read_with_base(path)
        source = str(path)
    data = _merge(data, overrides or {})
    if (retired := retired_key(data)) is not None:
        raise ConfigError(f"config {source}: {retired}")
    try:
        return SlamConfig(**data)
    except SettingsError as exc:  # a nested SSMVPR_ variable whose value is not the JSON it must be
        raise ConfigError(_env_json_error(exc)) from None
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        variable = _env_variable(first["loc"])
        if variable is None:
            origin = f"config {source}"
        elif variable[1]:
            origin = f"environment variable {variable[0]}"
        else:
            origin = f"environment variable {variable[0]} (with config {source})"
        raise ConfigError(f"{origin}: {where}: {first['msg']} ({exc.error_count()} error(s))") from None


def _field_annotation(loc: list[str]) -> Any:
    """The annotation of the config field at `loc` (names case-insensitive), None if there is none."""
    model: Any = SlamConfig
    annotation: Any = None
    for part in loc:
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            return None
        fields = {name.lower(): info for name, info in model.model_fields.items()}
        if part.lower() not in fields:
            return None
        annotation = model = fields[part.lower()].annotation
    return annotation


def _env_json_error(exc: SettingsError) -> str:
    """Name the SSMVPR_ variable(s) that pydantic-settings could not parse as JSON."""
    found = re.search(r'field "([^"]+)"', str(exc))  # 'error parsing value for field "vpr" from ...'
    section = found.group(1) if found else ""
    prefix = f"SSMVPR_{section}".upper()
    mine = {k: v for k, v in os.environ.items() if k.upper() == prefix or k.upper().startswith(prefix + "__")}

    def not_json(value: str) -> bool:
        try:
            json.loads(value)
        except ValueError:
            return True
        return False

    def is_section(key: str) -> bool:
        annotation = _field_annotation(key.upper().removeprefix("SSMVPR_").split("__"))
        return isinstance(annotation, type) and issubclass(annotation, BaseModel)

    culprits = [k for k, v in mine.items() if not_json(v)] or sorted(mine)
    if not culprits:
        return f"environment: cannot parse the value for config section {section!r} ({exc})"
    key = max(culprits, key=is_section)  # a section set to a non-object is the likelier mistake
    where = key.upper().removeprefix("SSMVPR_").lower().replace("__", ".")
    if is_section(key):
        return (
            f"environment variable {key}={mine[key]!r}: not valid JSON; {where} is a section, "
            f"so give a JSON object or set one field as {key}__<FIELD>=value"
        )
    return f"environment variable {key}={mine[key]!r}: not valid JSON, which {where} needs (e.g. [1, 2])"


RESUME_MAY_CHANGE = (("VPR", "BACKBONE", "WEIGHTS"), ("VPR", "BACKBONE", "DEVICE"))
"""Settings a resumed run may take from the environment: where the weights are and what runs them
(as --weights and --device may); everything else is the checkpoint's."""


def settings_variables(environ: dict[str, str] | None = None) -> list[str]:
    """The SSMVPR_ variables that set a configuration field (SSMVPR_WEIGHTS, SSMVPR_CACHE and the
    like name files, not settings), leaving out those a resume may change."""
    sections = {name.upper() for name in SlamConfig.model_fields}
    found = []
    for key in sorted(os.environ if environ is None else environ):
        parts = tuple(key.upper().removeprefix("SSMVPR_").split("__"))
        if not key.upper().startswith("SSMVPR_") or parts[0] not in sections:
            continue
        if parts in RESUME_MAY_CHANGE:
            continue
        found.append(key)
    return found


def _env_variable(loc: tuple[Any, ...]) -> tuple[str, bool] | None:
    """The SSMVPR_ variable behind the error at `loc` (names are case-insensitive), and whether it
    alone set that value: the variable of the field, or of a list whose item failed. A variable
    that set a field within `loc` (a check across a section's fields failed) is returned as a
    suspect only: the config file may have set the other field."""
    path = [str(p).upper() for p in loc]
    suspect = None
    for key in os.environ:
        if not key.upper().startswith("SSMVPR_"):
            continue
        parts = key.upper().removeprefix("SSMVPR_").split("__")
        if parts == path[: len(parts)] and _holds(os.environ[key], loc[len(parts) :]):
            return key, True
        if path and parts[: len(path)] == path:
            suspect = key
    return None if suspect is None else (suspect, False)


def _holds(value: str, rest: tuple[Any, ...]) -> bool:
    """Whether a variable's value reaches the part `rest` below it: an item of its list, or a key
    of its JSON object (SSMVPR_VPR='{...}' set only what its JSON names)."""
    if not rest:
        return True
    try:
        node: Any = json.loads(value)
    except ValueError:
        return False
    for part in rest:
        if isinstance(node, list) and isinstance(part, int):  # an item, or one the list lacks
            if not 0 <= part < len(node):
                return True
            node = node[part]
        elif isinstance(node, dict):
            match = [k for k in node if str(k).lower() == str(part).lower()]
            if not match:
                return False
            node = node[match[0]]
        else:
            return False
    return True


def _read_with_base(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A YAML file merged over its `preset:` base, and that base over its own (fast -> default)."""
    data = _read_yaml(path)
    base = data.pop("preset", None)
    if base is None and path.resolve() != (PRESETS_DIR / "default.yaml").resolve():
        base = "default"  # a user file refines the default preset unless it names another
    if base is None:
        return data
    if (
        not isinstance(base, str)
        or not base
        or any(sep in base for sep in ("/", "\\"))
        or base.endswith((".yaml", ".yml"))
    ):
        raise ConfigError(f"config {path}: preset: {base!r}: a preset is a name ({', '.join(available_presets())}), "
                          "never a file; to build on a file of your own, copy its keys in")  # fmt: skip
    base_path = _preset_path(base, f"config {path}: preset:", chained=True)
    if base_path.resolve() in seen or base_path.resolve() == path.resolve():
        raise ConfigError(f"config {path}: preset {base!r} is part of a preset cycle")
    return _merge(_read_with_base(base_path, (*seen, path.resolve())), data)


def _preset_path(name: str, referrer: str, chained: bool = False) -> Path:
    """The preset's file; chained: named by a file's `preset:` key, which takes names only."""
    path = PRESETS_DIR / f"{name}.yaml"
    if not path.is_file():
        what = "is not a preset" if chained else "is neither a file nor a preset"
        raise ConfigError(f"{referrer}{'' if chained else ':'} {name!r} {what} ({', '.join(available_presets())})")
    return path


def dump_config(config: SlamConfig) -> str:
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def preset_config(name: str = "default") -> SlamConfig:
    """A preset as shipped: its file over the built-in defaults, no environment variable read
    (the baseline `config --diff` compares with)."""
    data = _read_with_base(_preset_path(name, "--config"))
    return SlamConfig(**data, _env_prefix="SSMVPR_UNUSED_PREFIX_")  # type: ignore[call-arg]


def config_diff(config: SlamConfig, baseline: SlamConfig) -> dict[str, Any]:
    """The keys of `config` whose values differ from `baseline`'s, nested as in the YAML."""

    def diff(a: Any, b: Any) -> Any:
        if isinstance(a, dict) and isinstance(b, dict):
            out = {k: d for k, v in a.items() if (d := diff(v, b.get(k, _MISSING))) is not _SAME}
            return out or _SAME
        return _SAME if a == b else a

    result = diff(config.model_dump(mode="json"), baseline.model_dump(mode="json"))
    return {} if result is _SAME else result


_SAME = object()
_MISSING = object()


def explain_config(config: SlamConfig) -> str:
    """Every key as `section.key: value  # description`, one per line (what `config --explain`
    prints), so a user can grep for a setting and read what it does."""
    lines: list[str] = []

    def walk(model: BaseModel, prefix: str) -> None:
        for name, info in type(model).model_fields.items():
            value = getattr(model, name)
            key = f"{prefix}{name}"
            if isinstance(value, BaseModel):
                walk(value, key + ".")
                continue
            shown = json.dumps(_plain(value))
            note = f"  # {info.description}" if info.description else ""
            lines.append(f"{key}: {shown}{note}")

    walk(config, "")
    return "\n".join(lines)


def _plain(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, Path):
        return str(value)
    return value


def resolve_weights_first(config: SlamConfig) -> None:
    """Find the VGG16 weights (or fetch them into the cache) and write their path into `config`,
    before any other work: a wrong path or a failed download ends a call in seconds, not after a
    simulation or a Ray start."""
    from loopclosure.weights import configured_weights

    path = configured_weights(config.vpr.backbone, progress=True)
    if path is not None:
        config.vpr.backbone.weights = str(path)
