"""Every float option of every command refuses NaN and infinity in one line naming the option,
through one check (`ssmvpr_slam.cli.finite_options`, run by `cli.errors.friendly_errors`), before any
work. Before: `loop-eval --radius nan` passed the `radius <= 0` check (NaN compares false) and
ran to an all-n/a result with exit status 0.

The options are found by walking the app's commands, so a float option added later is tried too."""

from __future__ import annotations

import inspect
import typing
from collections.abc import Iterator
from pathlib import Path

import pytest
import typer
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401
from typer.models import ArgumentInfo

from ssmvpr_slam.cli import app
from ssmvpr_slam.cli.finite_options import option_name


def _commands(typer_app: typer.Typer, prefix: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], object]]:
    for command in typer_app.registered_commands:
        assert command.callback is not None
        yield (*prefix, command.name or command.callback.__name__.replace("_", "-")), command.callback
    for group in typer_app.registered_groups:
        assert group.typer_instance is not None and group.name
        yield from _commands(group.typer_instance, (*prefix, group.name))


def _holds_float(annotation: object) -> bool:
    """float, float | None, list[float]: the value typed, without typer's Annotated metadata."""
    if annotation is float:
        return True
    metadata = getattr(annotation, "__metadata__", None)
    args = typing.get_args(annotation)[:1] if metadata is not None else typing.get_args(annotation)
    return any(_holds_float(arg) for arg in args)


def _is_argument(parameter: inspect.Parameter) -> bool:
    return any(isinstance(m, ArgumentInfo) for m in getattr(parameter.annotation, "__metadata__", ()))


def _float_options() -> list[tuple[tuple[str, ...], str, list[str]]]:
    """(command words, option, the command's arguments as placeholders)."""
    found = []
    for words, callback in _commands(app):
        parameters = list(inspect.signature(callback, eval_str=True).parameters.values())  # type: ignore[arg-type]
        placeholders = ["nowhere"] * sum(_is_argument(p) for p in parameters)
        for parameter in parameters:
            if not _is_argument(parameter) and _holds_float(parameter.annotation):
                found.append((words, option_name(callback, parameter.name), placeholders))  # type: ignore[arg-type]
    return found


FLOAT_OPTIONS = _float_options()


def test_the_walk_finds_the_float_options_we_know_of() -> None:
    known = {("loop-eval", "--radius"), ("loop-eval", "--spacing"), ("loop-eval", "--gt-threshold"),
             ("run", "--rate"), ("optimize", "--gt-radius")}  # fmt: skip
    assert known <= {(" ".join(words), option) for words, option, _ in FLOAT_OPTIONS}


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN", "Infinity"])
@pytest.mark.parametrize(("words", "option", "arguments"), FLOAT_OPTIONS, ids=lambda x: str(x))
def test_a_float_option_refuses_nan_and_infinity(
    tmp_path: Path, words: tuple[str, ...], option: str, arguments: list[str], value: str
) -> None:
    out = tmp_path / "out"
    # --out where the command has one: the refusal comes before any folder is made
    extra = ["--out", out] if words[0] in ("loop-eval", "run", "optimize", "vpr-eval", "map", "demo") else []
    result = invoke(*words, *arguments, option, value, *extra)
    line = assert_user_error(result, f"invalid value for {option}: not a finite number")
    assert value.lower().replace("infinity", "inf") in line.lower()
    assert not out.exists()
