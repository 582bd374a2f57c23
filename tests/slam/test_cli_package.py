"""The command line as a package (`ssmvpr_slam.cli`): importing it sets the OpenMP wait policy
before anything could load torch and loads nothing heavy (`--help` stays instant), and an option
value a config model refuses is named by the option, looked up by the model class itself."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from pydantic import BaseModel, ValidationError

from ssmvpr_slam.cli.errors import friendly_errors, option_name, option_of_field, validation_title

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "gtsam", "kiss_icp", "faiss", "cv2", "numpy", "pydantic", "ray", "matplotlib")


def _fresh(code: str, **env: str) -> str:
    environ = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"} | env
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT, env=environ
    )
    return done.stdout.strip()


def test_importing_the_command_line_sets_the_wait_policy_and_loads_nothing_heavy() -> None:
    probe = ("import os, sys; from ssmvpr_slam.cli import app; "
             f"print(os.environ['OMP_WAIT_POLICY'], *sorted({{m.split('.')[0] for m in sys.modules}} & {set(HEAVY)!r}))")  # fmt: skip
    assert _fresh(probe) == "PASSIVE"
    assert _fresh(probe, OMP_WAIT_POLICY="ACTIVE") == "ACTIVE"  # an explicit policy wins


def test_every_option_of_the_table_names_a_field_of_its_model() -> None:
    table = option_of_field()
    for model, field in table:
        assert field in model.model_fields, (model, field)
    titles = {(validation_title(model), field) for model, field in table}
    assert len(titles) == len(table)  # no two entries a validation error could confuse


@pytest.mark.parametrize(("model", "field"), list(option_of_field()), ids=lambda v: getattr(v, "__name__", v))
def test_a_refused_value_is_named_by_its_option(
    model: type[BaseModel], field: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ValidationError) as refused:
        model.model_validate({field: "not a value"})
    assert option_name(refused.value.title, field) == option_of_field()[(model, field)]

    @friendly_errors
    def command() -> None:
        raise refused.value

    with pytest.raises(typer.Exit) as exited:
        command()
    assert exited.value.exit_code == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith(f"error: invalid value for {option_of_field()[(model, field)]}: "), line
    assert "'not a value'" in line and model.__name__ not in line


def test_a_model_with_a_title_of_its_own_is_found_by_it_and_others_are_not_named() -> None:
    class Titled(BaseModel):
        model_config = {"title": "Shown"}
        x: int = 0

    with pytest.raises(ValidationError) as refused:
        Titled.model_validate({"x": "y"})
    assert refused.value.title == validation_title(Titled) == "Shown"
    assert option_name("Shown", "x") is None and option_name("MapConfig", "no_such_field") is None
    assert option_name("MapConfig", "workers") == "--workers (map.workers)"
