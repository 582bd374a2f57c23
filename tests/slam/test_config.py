"""ssmvpr_slam.config.slam.load_config: presets from configs/, YAML files over a `preset:` base,
SSMVPR_<SECTION>__<FIELD> environment overrides, and errors that name their source."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

import ssmvpr_slam.config.slam as config_module
from loopclosure.config import DetectorConfig
from ssmvpr_slam.backend.config import LidarRegistrationConfig
from ssmvpr_slam.config.slam import ConfigError, SlamConfig, available_presets, dump_config, load_config


@pytest.fixture(autouse=True)
def _no_ssmvpr_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """A developer's SSMVPR_* variables must not leak into these tests."""
    import os

    for key in list(os.environ):
        if key.upper().startswith("SSMVPR_"):
            monkeypatch.delenv(key)


def test_presets_are_listed() -> None:
    assert {"default", "fast", "ras2020"} <= set(available_presets())


def test_no_argument_loads_the_default_preset() -> None:
    cfg = load_config()
    assert cfg == load_config("default")
    vpr = cfg.vpr
    assert vpr.filtering.num_candidates == 50
    assert (vpr.filtering.cubes.cube_size, vpr.filtering.cubes.stride) == (7, 2)
    assert (vpr.spatial.cubes.cube_size, vpr.spatial.cubes.stride) == (3, 2)
    assert (vpr.backbone.stage1_layer, vpr.backbone.stage2_layer) == ("conv5_2", "conv4_2")
    assert vpr.filtering.pca.dim == vpr.spatial.pca.dim == 100
    assert not vpr.frame_correlation.enabled
    gate = cfg.detector.gate
    assert (gate.length, gate.tolerance, gate.allow_reverse) == (3, 2, True)
    assert not gate.enabled  # loops are decided on sequence scores; the top-1 gate is optional
    sequence = cfg.detector.sequence
    assert (sequence.length, sequence.direction, sequence.sequence_candidates) == (8, "forward", 20)
    assert sequence.missing == "shrink"  # a line cut short by a seam or the database's start weighs sqrt(n / L)
    assert cfg.detector.rear.direction == "reverse"  # a street driven the other way
    assert cfg.detector.decision == "calibrated"
    calibrated = cfg.detector.calibrated
    assert (calibrated.accept, calibrated.min_history, calibrated.prior_runner_ups) == (6.0, 5, 40)
    assert (calibrated.prior_median, calibrated.prior_spread, calibrated.min_field) == (0.5, 0.6, 10)
    assert cfg.detector.pca_warmup_keyframes == cfg.detector.exclusion_keyframes == 30  # a warm-up that costs nothing
    assert cfg.detector.min_score == 0.3 and cfg.detector.accept_threshold == 0.45  # decision: absolute
    assert cfg.backend.registration.lidar.min_inlier_ratio == 0.8


def test_the_models_defaults_are_the_default_preset() -> None:
    """A library user who builds the models directly (DetectorConfig(), SlamConfig()) gets the
    same tuned values as the CLI, which loads configs/default.yaml."""
    assert SlamConfig() == load_config()
    assert DetectorConfig() == load_config().detector
    assert LidarRegistrationConfig() == load_config().backend.registration.lidar


def test_ras2020_changes_cubes_and_inherits_the_rest_from_default() -> None:
    default, ras = load_config("default"), load_config("ras2020")
    assert (ras.vpr.filtering.cubes.cube_size, ras.vpr.filtering.cubes.stride) == (9, 1)
    assert (ras.vpr.spatial.cubes.cube_size, ras.vpr.spatial.cubes.stride) == (3, 1)
    assert ras.vpr.frame_correlation.enabled
    assert ras.vpr.filtering.pca.whiten and ras.vpr.filtering.pca.dim == 125
    # not in ras2020.yaml: comes from default.yaml, not from the models' defaults
    assert ras.detector == default.detector and ras.detector.min_score == 0.3
    assert ras.vpr.filtering.num_candidates == 50
    assert ras.backend == default.backend


def test_fast_preset_inherits_default() -> None:
    fast = load_config("fast")
    assert fast.vpr.filtering.num_candidates == 30  # the calibrated decision needs a field of candidates
    assert fast.vpr.database.stage1_dtype == "float16"
    assert fast.vpr.backbone.precision == "auto"
    assert (
        fast.frontend.odometry.kiss_icp.convergence_criterion,
        fast.frontend.odometry.kiss_icp.voxel_size,
        fast.frontend.odometry.kiss_icp.max_points_per_voxel,
    ) == (1e-3, 1.5, 5)
    assert fast.vpr.filtering.cubes == load_config().vpr.filtering.cubes
    assert fast.detector.min_score == 0.3
    assert fast.backend.registration.lidar.loop_spacing_keyframes == 4
    assert load_config().backend.registration.lidar.loop_spacing_keyframes == 1  # the default registers every loop


def test_yaml_file_over_a_preset_base(tmp_path: Path) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text("preset: ras2020\ndetector:\n  gate: {length: 5}\nvpr:\n  filtering: {num_candidates: 20}\n")
    cfg = load_config(path)
    assert cfg.detector.gate.length == 5
    assert cfg.detector.gate.tolerance == 2  # sibling keys of the override survive (deep merge)
    assert cfg.vpr.filtering.num_candidates == 20
    assert cfg.vpr.filtering.cubes.cube_size == 9  # from ras2020
    assert cfg.detector.min_score == 0.3  # from default, below ras2020


def test_yaml_file_over_a_preset_that_has_its_own_base(tmp_path: Path) -> None:
    # fast.yaml itself says `preset: default`; the chain must resolve, not leak a `preset` key
    path = tmp_path / "mine.yaml"
    path.write_text("preset: fast\ndetector: {min_score: 0.35}\n")
    cfg = load_config(path)
    assert cfg.detector.min_score == 0.35
    assert cfg.vpr.filtering.num_candidates == 30  # fast
    assert cfg.backend.registration.lidar.min_inlier_ratio == 0.8  # default, under fast


def test_yaml_without_preset_refines_the_default_preset(tmp_path: Path) -> None:
    path = tmp_path / "bare.yaml"
    path.write_text("detector: {min_score: 0.4}\n")
    cfg = load_config(path)
    assert cfg.detector.min_score == 0.4
    # the tuned value of configs/default.yaml
    assert cfg.backend.registration.lidar.min_inlier_ratio == load_config().backend.registration.lidar.min_inlier_ratio


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("vpr:\n  filtering:\n    num_candidate: 3\n", "vpr.filtering.num_candidate"),
        ("preset: fast\nvpr:\n  filtering:\n    num_candidate: 3\n", "vpr.filtering.num_candidate"),
        ("detectr: {min_score: 0.3}\n", "detectr"),
        ("detector: {min_score: 2.0}\n", "detector.min_score"),
    ],
)
def test_bad_key_or_value_names_file_and_key(tmp_path: Path, text: str, where: str) -> None:
    path = tmp_path / "typo.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message and where in message
    assert "\n" not in message
    assert "(1 error(s))" in message  # the typo is the only problem (no stray `preset` key)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [("vpr: [1, 2\n", "not valid YAML"), ("- 1\n- 2\n", "must be a mapping"), ("preset: nope\n", "'nope'")],
)
def test_unusable_yaml_names_the_file(tmp_path: Path, text: str, fragment: str) -> None:
    path = tmp_path / "broken.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=fragment) as info:
        load_config(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_unknown_preset_lists_presets() -> None:
    with pytest.raises(ConfigError) as info:
        load_config("no_such_preset")
    message = str(info.value)
    assert "'no_such_preset'" in message
    for name in available_presets():
        assert name in message


def test_preset_cycle_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "a.yaml").write_text("preset: b\n")
    (tmp_path / "b.yaml").write_text("preset: a\n")
    monkeypatch.setattr(config_module, "PRESETS_DIR", tmp_path)
    with pytest.raises(ConfigError, match="cycle"):
        load_config("a")


def test_environment_overrides_a_preset(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SSMVPR_VPR__FILTERING__NUM_CANDIDATES", "15")
    monkeypatch.setenv("SSMVPR_DETECTOR__GATE__ALLOW_REVERSE", "false")
    cfg = load_config()
    assert cfg.vpr.filtering.num_candidates == 15
    assert cfg.detector.gate.allow_reverse is False
    # only those fields: their siblings keep the preset's values
    assert cfg.vpr.filtering.cubes.cube_size == 7
    assert cfg.detector.gate.length == 3 and cfg.detector.min_score == 0.3
    # and it beats a YAML file's value too
    ras = load_config("ras2020")
    assert ras.vpr.filtering.num_candidates == 15 and ras.vpr.filtering.cubes.cube_size == 9


def test_environment_beats_a_yaml_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text("preset: default\ndetector: {min_score: 0.3}\n")
    monkeypatch.setenv("SSMVPR_DETECTOR__MIN_SCORE", "0.7")
    assert load_config(path).detector.min_score == pytest.approx(0.7)


@pytest.mark.parametrize(
    ("name", "value", "where"),
    [
        ("SSMVPR_VPR__FILTERING__NUM_CANDIDATES", "abc", "vpr.filtering.num_candidates"),
        ("SSMVPR_VPR__FILTERING__NUM_CANDIDATE", "3", "vpr.filtering.num_candidate"),
    ],
)
def test_bad_environment_override_names_the_variable(
    monkeypatch: pytest.MonkeyPatch, name: str, value: str, where: str
) -> None:
    monkeypatch.setenv(name, value)
    with pytest.raises(ConfigError) as info:
        load_config()
    assert f"environment variable {name}" in str(info.value) and where in str(info.value)


def test_overrides_argument_and_dump_roundtrip(tmp_path: Path) -> None:
    cfg = load_config(overrides={"detector": {"exclusion_keyframes": 7}})
    assert cfg.detector.exclusion_keyframes == 7 and cfg.detector.exclusion_distance == 15.0
    path = tmp_path / "dumped.yaml"
    path.write_text(dump_config(cfg))
    assert load_config(path) == cfg
    assert isinstance(cfg, SlamConfig)


def test_pyproject_ships_every_package_and_the_presets() -> None:
    """pyproject lists packages by hand (the presets are mapped in from configs/): a new
    subpackage missing from that list would be left out of the wheel."""
    import tomllib

    from setuptools import find_packages

    root = Path(__file__).resolve().parents[2]
    tool = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = find_packages(str(root), include=["ssmvpr_slam*", "ssmvpr_common*", "frontend*", "loopclosure*"])
    assert set(tool["packages"]) == set(found) | {"ssmvpr_slam.config.presets"}
    assert tool["package-dir"] == {"ssmvpr_slam.config.presets": "configs"}
    assert tool["package-data"]["ssmvpr_slam.config.presets"] == ["*.yaml"]
    assert (root / "configs" / "default.yaml").is_file()


def test_the_simulated_traverse_is_the_demos_whatever_else_changes(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """`simulate`, `demo` and `config` show one traverse: a seed changed by a file or an SSMVPR_
    variable used to drop the demo's dusk lap (its schedule lived outside SimulationConfig)."""
    from frontend.simulation import SimulationConfig, default_demo_config

    demo = ["day", "day", "dusk"]
    assert load_config().simulation == default_demo_config() == SimulationConfig()
    assert load_config().simulation.appearance_schedule == demo
    assert load_config(overrides={"simulation": {"seed": 2}}).simulation.appearance_schedule == demo
    own = tmp_path / "seed2.yaml"
    own.write_text("simulation: {seed: 2}\n")
    assert load_config(own).simulation.appearance_schedule == demo
    monkeypatch.setenv("SSMVPR_SIMULATION__SEED", "2")
    assert load_config().simulation.seed == 2 and load_config().simulation.appearance_schedule == demo


@pytest.mark.parametrize(
    ("variable", "value", "where"),
    [
        ("SSMVPR_FRONTEND__ODOMETRY__KISS_ICP__MIN_RANGE", "200", "frontend.odometry.kiss_icp"),  # min < max check
        ("SSMVPR_VPR__BACKBONE__INPUT_SIZE", "100", "vpr"),  # cube size against the feature map
        ("SSMVPR_DETECTOR__SEQUENCE__SPEEDS", "[0]", "detector.sequence"),  # a list item
    ],
)
def test_a_section_check_names_the_variable_that_set_a_field_in_it(
    monkeypatch: pytest.MonkeyPatch, variable: str, value: str, where: str
) -> None:
    """Checks across a section's fields report the section: they had blamed configs/default.yaml,
    which the variable overrode."""
    monkeypatch.setenv(variable, value)
    with pytest.raises(ConfigError, match=rf"^environment variable {variable}\b.*: {where}: "):
        load_config()


def test_a_section_variable_is_blamed_only_for_what_its_json_sets(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """SSMVPR_VPR='{...}' sets only the fields its JSON names: a bad value from the config file in
    the same section is the file's (a review found the variable blamed for it)."""
    own = tmp_path / "device.yaml"
    own.write_text("vpr:\n  backbone:\n    device: gpu\n")
    monkeypatch.setenv("SSMVPR_VPR", '{"filtering": {"num_candidates": 30}}')
    with pytest.raises(ConfigError, match=rf"^config {own}: vpr.backbone.device: "):
        load_config(own)
    monkeypatch.setenv("SSMVPR_VPR", '{"backbone": {"device": "gpu"}}')
    with pytest.raises(ConfigError, match="^environment variable SSMVPR_VPR: vpr.backbone.device: "):
        load_config()
    monkeypatch.delenv("SSMVPR_VPR")
    monkeypatch.setenv("SSMVPR_SIMULATION__CITY__HOUSE_WIDTH_RANGE_M", "[12]")  # a pair given one value
    with pytest.raises(ConfigError, match="^environment variable SSMVPR_SIMULATION__CITY__HOUSE_WIDTH_RANGE_M: "):
        load_config()


def test_a_preset_chain_naming_a_file_says_presets_are_names(tmp_path: Path) -> None:
    """Before: "'cfg/cyc2.yaml' is neither a file nor a preset" while the file was there."""
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "cyc2.yaml").write_text("results: {plots: false}\n")
    user = tmp_path / "cfg" / "cyc1.yaml"
    user.write_text(f"preset: {tmp_path / 'cfg' / 'cyc2.yaml'}\n")
    with pytest.raises(ConfigError, match=r"preset: '.*cyc2\.yaml': a preset is a name \(.*fast.*\), never a file"):
        load_config(str(user))
    user.write_text("preset: nosuch\n")
    with pytest.raises(ConfigError, match=r"cyc1\.yaml: preset: 'nosuch' is not a preset \("):
        load_config(str(user))


def _float_locations(value: object, path: tuple[object, ...] = ()) -> list[tuple[object, ...]]:
    """Where a float sits in a dumped config: one location per key (its first float), list items
    and mappings walked, so every float setting is tried once."""
    if isinstance(value, float):
        return [path]
    if isinstance(value, dict):
        return [loc for key, item in value.items() for loc in _float_locations(item, (*path, key))]
    if isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            found = _float_locations(item, (*path, index))
            if found:
                return found[:1] if not isinstance(item, dict) else found
    return []


def _optional_floats_unset(model: type, path: tuple[object, ...] = ()) -> list[tuple[object, ...]]:
    """`float | None` keys whose default is None: no float in the dump to find them by."""
    import typing

    from pydantic import BaseModel

    found = []
    for name, info in model.model_fields.items():  # type: ignore[attr-defined]
        args = typing.get_args(info.annotation)
        nested = [a for a in (info.annotation, *args) if isinstance(a, type) and issubclass(a, BaseModel)]
        if nested and info.annotation is nested[0]:
            found += _optional_floats_unset(nested[0], (*path, name))
        elif float in args and info.default is None:
            found.append((*path, name))
    return found


def _setting(defaults: dict, path: tuple[object, ...], value: float) -> dict:
    """The smallest config file that sets the float at `path` to `value`: the sections down to
    it, and a list that holds it whole, with that one item replaced."""
    import copy

    keys = [p for p in path if isinstance(p, str)]
    cut = next((i for i, p in enumerate(path) if not isinstance(p, str)), len(path))
    whole: object = defaults
    for key in path[:cut]:
        whole = whole[key]  # type: ignore[index]
    whole = copy.deepcopy(whole)
    if cut == len(path):
        whole = value
    else:
        node = whole
        for key in path[cut:-1]:
            node = node[key]  # type: ignore[index]
        node[path[-1]] = value  # type: ignore[index]
    for key in reversed(keys[:cut]):
        whole = {key: whole}
    return whole  # type: ignore[return-value]


def test_every_float_setting_refuses_nan_and_infinity_naming_its_key(tmp_path: Path) -> None:
    """A NaN or infinite setting passes every bound (NaN compares false) and means nothing; a
    config file saying `.inf` or `.nan` anywhere is refused with its key. No default is infinite."""
    import yaml

    defaults = load_config().model_dump(mode="json")
    locations = _float_locations(defaults) + _optional_floats_unset(SlamConfig)
    assert len(locations) > 200 and {p[0] for p in locations} == set(SlamConfig.model_fields)  # every section
    accepted = []
    for k, path in enumerate(locations):
        value = float("nan") if k % 2 else float("inf")
        file = tmp_path / "finite.yaml"
        file.write_text(yaml.safe_dump(_setting(defaults, path, value)))
        try:
            load_config(file)
        except ConfigError as error:
            key = ".".join(str(p) for p in path)
            assert str(file) in str(error) and key in str(error), (key, str(error))
            continue
        accepted.append(path)
    assert not accepted


def test_every_settings_model_follows_the_one_policy() -> None:
    """Every section of the settings, in every package, is a `SettingsModel`: unknown keys refused,
    assignments checked, no NaN or infinity (the simulation's scene frozen on top)."""
    from pydantic import BaseModel

    from ssmvpr_common.settings_model import SettingsModel

    def sections(model: type[BaseModel], key: str) -> list[tuple[str, type[BaseModel]]]:
        found = []
        for name, info in model.model_fields.items():
            kind = info.annotation
            if isinstance(kind, type) and issubclass(kind, BaseModel):
                found += [(f"{key}{name}", kind), *sections(kind, f"{key}{name}.")]
        return found

    models = sections(SlamConfig, "")
    assert len(models) > 40
    outside = [key for key, kind in models if not issubclass(kind, SettingsModel)]
    assert outside == []
    config = load_config()
    with pytest.raises(ValidationError):
        config.backend.registration.lidar.max_num_threads = -1  # checked when set, as when loaded
    with pytest.raises(ValidationError):
        config.simulation.city.block_size_m = 10.0  # the scene is frozen


@pytest.mark.parametrize("cores", [2, 4, 16])
def test_the_stages_in_flight_resolve_by_the_cores_and_encoding_ahead_needs_overlap(
    monkeypatch: pytest.MonkeyPatch, cores: int
) -> None:
    """`auto` puts the stages side by side where the process has 4 cores or more; the encoder's
    thread takes the front end's queued keyframes, so it never runs without overlap."""
    import ssmvpr_slam.config.pipeline as pipeline_config

    monkeypatch.setattr(pipeline_config, "_cores", lambda: cores)
    auto = load_config().pipeline
    assert auto.overlapped == auto.registers_in_worker == auto.encodes_ahead == (cores >= 4)
    forced = load_config(overrides={"pipeline": {"overlap": False, "encode_ahead": True}}).pipeline
    assert not forced.encodes_ahead
    on = load_config(overrides={"pipeline": {"overlap": True, "encode_ahead": True}}).pipeline
    assert on.encodes_ahead
