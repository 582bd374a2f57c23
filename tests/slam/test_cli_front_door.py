"""The command line as a newcomer meets it: `--version`, choices and examples in every `--help`,
`config --diff` / `--explain`, and one results folder per call with a latest link per command."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import get_args

import pytest
import yaml
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401

from frontend.config import FolderSourceConfig, OdometryConfig
from loopclosure.config import BackboneConfig, SequenceMatchConfig
from loopclosure.weights import FetchSource
from ssmvpr_slam.backend.graph_optimizer import KERNEL_NAMES
from ssmvpr_slam.cli import app
from ssmvpr_slam.config.in_front import IN_FRONT, setting
from ssmvpr_slam.config.presets import available_presets
from ssmvpr_slam.config.slam import load_config

COMMANDS = [["run"], ["demo"], ["simulate"], ["vpr-eval"], ["loop-eval"], ["optimize"], ["fit-pca"], ["config"],
            ["weights", "fetch"], ["weights", "path"]]  # fmt: skip


def _help(*command: str) -> str:
    result = invoke(*command, "--help", env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    return result.output


def _choices(annotation: object) -> str:
    return "[" + "|".join(str(a).replace("_", "-") for a in get_args(annotation)) + "]"


def test_version() -> None:
    result = invoke("--version")
    assert result.exit_code == 0 and re.fullmatch(r"ssmvpr-slam \d+\.\d+\.\d+\S*\n", result.output), result.output


def test_every_command_has_examples_and_no_bare_string_option() -> None:
    for command in COMMANDS:
        text = _help(*command)
        assert "<str>" not in text, command  # a string option shows its choices or what it takes
        if command[0] != "weights":
            assert "Examples:" in text and f"ssmvpr-slam {command[0]}" in text.split("Examples:")[1], command


def test_the_choices_shown_are_the_ones_the_config_accepts() -> None:
    # the metavars are written by hand in the CLI: they must follow the models' Literal types
    device = _choices(BackboneConfig.model_fields["device"].annotation)
    assert device == "[auto|cpu|cuda]"
    shown = {
        ("run",): [_choices(OdometryConfig.model_fields["kind"].annotation),
                   _choices(FolderSourceConfig.model_fields["pose_role"].annotation), device],
        ("vpr-eval",): [_choices(SequenceMatchConfig.model_fields["direction"].annotation), device],
        ("optimize",): ["[" + "|".join(KERNEL_NAMES) + "]"],
        ("weights", "fetch"): [_choices(FetchSource)],
    }  # fmt: skip
    for command, choices in shown.items():
        text = _help(*command)
        for choice in choices:
            assert choice in text, (command, choice)
    presets = available_presets()
    assert {"default", "fast"} <= set(presets)
    assert f"({', '.join(presets)})" in _help("run")


def test_config_diff_shows_what_a_preset_and_the_environment_change() -> None:
    result = invoke("config", "--diff")
    assert result.exit_code == 0 and "unchanged" in result.output
    result = invoke("config", "--diff", "-c", "fast", env={"SSMVPR_DETECTOR__CALIBRATED__ACCEPT": "5"})
    assert result.exit_code == 0, result.output
    changed = yaml.safe_load(result.output)
    assert changed["vpr"]["filtering"]["num_candidates"] == 30  # the fast preset
    assert changed["detector"] == {"calibrated": {"accept": 5.0}}  # the environment, and nothing else of it


def _explained(*args: str, env: dict[str, str] | None = None) -> dict[str, str]:
    result = invoke("config", "--explain", *args, env={"COLUMNS": "400", **(env or {})})
    assert result.exit_code == 0, result.output
    return {line.split(":")[0]: line for line in result.output.splitlines() if not line.startswith("#")}


def test_config_explain_shows_the_settings_users_tune_with_unit_value_and_default() -> None:
    lines = _explained(env={"SSMVPR_DETECTOR__CALIBRATED__ACCEPT": "5"})
    assert list(lines) == [key for key, _ in IN_FRONT] and 15 <= len(lines) <= 25
    assert lines["detector.calibrated.accept"].startswith(
        "detector.calibrated.accept: 5.0  [spreads]  (default: 6.0)  # "
    )
    assert lines["frontend.keyframes.min_distance_m"].startswith(
        "frontend.keyframes.min_distance_m: 1.0  [m]  (default: 1.0)"
    )
    assert lines["vpr.backbone.device"].startswith('vpr.backbone.device: "auto"  (default: "auto")  # Where VGG16 runs')


def test_config_explain_all_gives_every_key_its_description() -> None:
    lines = _explained("--all")
    assert len(lines) > 300 and set(key for key, _ in IN_FRONT) < set(lines)
    assert "detector.calibrated.accept" in lines and "#" in lines["detector.calibrated.accept"]
    assert lines["vpr.backbone.device"].startswith('vpr.backbone.device: "auto"')
    assert_user_error(invoke("config", "--all"), "--all goes with --explain")


def test_every_setting_in_front_is_one_the_settings_have() -> None:
    config = load_config()
    for key, _ in IN_FRONT:
        setting(config, key)  # KeyError for a key renamed or removed since
    with pytest.raises(KeyError):
        setting(config, "detector.no_such_key")


@pytest.mark.parametrize(
    ("yaml", "says"),
    [
        ("backend:\n  registration:\n    lidar:\n      max_threads: 2\n",
         "backend.registration.lidar.max_threads was renamed backend.registration.lidar.max_num_threads"),
        ("frontend:\n  pose_files:\n    value_digits: 12\n", "frontend.pose_files.value_digits was removed"),
        ("evaluation:\n  trajectory:\n    association_max_dt: 0.1\n", "association_max_dt was removed"),
    ],
)  # fmt: skip
def test_a_retired_setting_in_a_users_file_is_named_with_what_became_of_it(
    tmp_path: Path, yaml: str, says: str
) -> None:
    (tmp_path / "old.yaml").write_text(yaml)
    assert_user_error(invoke("config", "-c", tmp_path / "old.yaml"), str(tmp_path / "old.yaml"), says)


def _ring_graph(tmp_path: Path) -> Path:
    graph = tmp_path / "square.g2o"
    vertices = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    lines = [f"VERTEX_SE2 {i} {x} {y} {t}" for i, (x, y, t) in enumerate(vertices)]
    info = "100 0 0 100 0 100"
    lines += [f"EDGE_SE2 {i} {i + 1} 1 0 1.5707963 {info}" for i in range(3)]
    lines.append(f"EDGE_SE2 3 0 1 0 1.5707963 {info}")  # the loop
    graph.write_text("\n".join(lines) + "\n")
    return graph


def test_two_optimize_calls_keep_both_results(tmp_path: Path) -> None:
    graph, out = _ring_graph(tmp_path), tmp_path / "results"
    for _ in range(2):
        result = invoke("optimize", graph, "--out", out)
        assert result.exit_code == 0, result.output
    folders = sorted(p for p in out.iterdir() if p.name.startswith("optimize_"))
    assert len(folders) == 2 and all((f / "optimised.g2o").is_file() for f in folders)
    assert (out / "latest-optimize").resolve() == folders[-1].resolve() == (out / "latest").resolve()
    assert json.loads((out / "latest-optimize" / "metrics.json").read_text())["loop_candidates"] == 1


@pytest.mark.parametrize("command", ["run", "vpr_eval", "loop_eval", "optimize"])
def test_each_command_has_its_own_latest_link(tmp_path: Path, command: str) -> None:
    from ssmvpr_slam.results.run_folder import staged_results_dir

    with staged_results_dir(tmp_path, "run") as first:
        (first.path / "x").write_text("run")
    with staged_results_dir(tmp_path, command) as second:
        (second.path / "x").write_text(command)
    own = tmp_path / f"latest-{command.replace('_', '-')}"
    assert own.resolve() == second.final.resolve() and (tmp_path / "latest").resolve() == second.final.resolve()
    assert (tmp_path / "latest-run" / "x").read_text() == "run"  # an eval does not move the run's link


def test_the_app_lists_every_command() -> None:
    text = _help()
    for command in ("run", "demo", "simulate", "vpr-eval", "loop-eval", "optimize", "fit-pca", "config", "weights"):
        assert command in text
    assert app.info.name == "ssmvpr-slam"
