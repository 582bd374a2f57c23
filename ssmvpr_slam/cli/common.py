"""What the commands share: the Typer apps, the consoles, the options several commands take
(--config, --weights, --device, --out) and the step from those options to a configuration.

Imports stay light (typer, rich, the preset names): `--help` loads this and nothing heavier.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console

from ssmvpr_slam.config.presets import available_presets

if TYPE_CHECKING:
    from ssmvpr_slam.config.slam import SlamConfig

app = typer.Typer(
    name="ssmvpr-slam",
    help="Streaming SSM-VPR loop closures with a GTSAM back end.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
weights_app = typer.Typer(help="VGG16 weights: fetch into the cache, show where they resolve.", no_args_is_help=True)
app.add_typer(weights_app, name="weights")
# soft_wrap: a line longer than the terminal (or than 80 columns when piped) is not broken, so that
# `| grep` finds a path or a figure whole; tables still fit the width
console = Console(stderr=False, soft_wrap=True)
err_console = Console(stderr=True, soft_wrap=True)

ConfigOpt = Annotated[
    str | None,
    typer.Option(
        "--config", "-c", metavar="PRESET|FILE",
        help=f"A preset ({', '.join(available_presets())}) or a YAML file; `ssmvpr-slam config --diff -c NAME` "
        "shows what it changes.",
    ),
]  # fmt: skip
WeightsOpt = Annotated[
    Path | None,
    typer.Option(help="VGG16 weights (torchvision layout state dict); default $SSMVPR_WEIGHTS, the cache, a download."),
]
# choices are shown as metavars and checked by the config models, whose errors are one line naming the option
DeviceOpt = Annotated[str | None, typer.Option(metavar="[auto|cpu|cuda]", help="Device of the VGG16 backbone.")]
OutOpt = Annotated[
    Path | None,
    typer.Option("--out", help="Results base folder (default results/): a new folder per call, and latest-<command>."),
]


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            shown = version("ssmvpr-slam")
        except PackageNotFoundError:  # a checkout on PYTHONPATH, not installed
            shown = "unknown (not installed)"
        typer.echo(f"ssmvpr-slam {shown}")
        raise typer.Exit


@app.callback()
def _main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Streaming SSM-VPR loop closures with a GTSAM back end."""


def examples(*lines: str) -> str:
    """An examples epilog for `--help` (W: the VGG16 weights file)."""
    return "Examples:\n\n" + "\n\n".join(f"  {line}" for line in lines)


def make_config(
    config: str | None, weights: Path | None = None, device: str | None = None, out: Path | None = None
) -> SlamConfig:
    """The configuration of `--config` (preset + file + environment) with the common options applied."""
    from ssmvpr_slam.config.slam import load_config

    cfg = load_config(config)
    if weights is not None:
        cfg.vpr.backbone.weights = str(weights)
    if device is not None:
        cfg.vpr.backbone.device = device  # type: ignore[assignment]
    if out is not None:
        cfg.results.out_dir = str(out)
    return cfg


def out_option(out: Path | None) -> str:
    """How an error names the results folder: the option if given, else the config key."""
    return "--out" if out is not None else "results.out_dir"


def odometry_kind(name: str) -> str:
    """CLI spelling (kiss-icp) to the config's (kiss_icp); anything else is left for validation."""
    return name.replace("-", "_")


def validated_update(model: Any, updates: dict[str, Any]) -> Any:
    """Like model_copy(update=...), but the new values are validated (e.g. --frames 0)."""
    return type(model).model_validate({**model.model_dump(), **updates})
