"""Every float option of every command is a finite number: one check for all of them.

`nan` passes any `x <= 0` check a command makes (every comparison with NaN is false), so
`loop-eval --radius nan` ran to an all-n/a result with exit status 0; `inf` passes them too and
means nothing as metres or a rate. The check runs on the parsed values of whichever command is
called (from `cli.errors.friendly_errors`, which wraps each one), before its work starts, so a float
option added later is covered without a check of its own.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from typing import Any

from ssmvpr_slam.errors import OptionError


def check_finite_options(command: Callable[..., Any], values: Mapping[str, object]) -> None:
    """Refuse, naming the option as typed, a float value (or list item) of `command`'s
    parameters that is NaN or infinite."""
    for parameter, value in values.items():
        items = value if isinstance(value, (list, tuple)) else (value,)
        for item in items:
            if isinstance(item, float) and not math.isfinite(item):
                name = option_name(command, parameter)
                raise OptionError(f"invalid value for {name}: not a finite number (got {item!r})")


def option_name(command: Callable[..., Any], parameter: str) -> str:
    """The long option a typer command's parameter is given with: the first `--` name its
    `typer.Option` declares (`gt_radius` -> `--gt-radius`), else the one typer derives."""
    from typer.models import OptionInfo

    derived = "--" + parameter.replace("_", "-")
    try:
        declared = inspect.signature(command, eval_str=True).parameters.get(parameter)
    except (NameError, TypeError, ValueError):  # annotations that do not resolve: typer's default name
        return derived
    if declared is None:
        return derived
    infos = [m for m in getattr(declared.annotation, "__metadata__", ()) if isinstance(m, OptionInfo)]
    if isinstance(declared.default, OptionInfo):
        infos.append(declared.default)
    for info in infos:
        # in Annotated, typer.Option("--name", "-n") keeps its first name where a default would be
        names = [info.default, *(info.param_decls or ())]
        for name in names:
            if isinstance(name, str) and name.startswith("--"):
                return name.split("/")[0]  # "--check/--no-check": the option, not its negation
    return derived
