"""`run LOG --resume DIR`: what a resumed run keeps and what it may change.

A resumed run finishes the run its checkpoint holds, so it keeps that run's settings, prior map
and results folder: a setting changed halfway would make one result of two different runs. Only
where the weights are and which device runs them may change (they change no result); any other
option or SSMVPR_ setting is refused in one line before the checkpoint is read.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from ssmvpr_slam.checkpoint.loading import load_checkpoint
from ssmvpr_slam.checkpoint.record import CheckpointError
from ssmvpr_slam.checkpoint.saving import Checkpoint
from ssmvpr_slam.config.slam import SlamConfig, load_config, settings_variables
from ssmvpr_slam.results.run_folder import check_writable


@dataclass(frozen=True)
class Resume:
    """What `run_log` needs to go on from a checkpoint."""

    checkpoint: Checkpoint
    config: SlamConfig  # the checkpoint's, with the weights and device given
    prior_map: Path | None  # the map the run closed loops against, if any

    @property
    def name(self) -> str:
        """The name the run was given (`run`, `demo`), which names its results folder."""
        return self.checkpoint.meta.name


def check_resume_options(folder: Path, options: Mapping[str, object], environ: Mapping[str, str] | None = None) -> None:
    """Refuse what would change the checkpoint's settings. options: the command's options other
    than the weights and the device, by name (None or False: not given); environ: the
    environment (default os.environ), whose SSMVPR_ settings other than those two are refused."""
    given = [name for name, value in options.items() if value is not None and value is not False]
    if given:
        raise CheckpointError(f"--resume {folder}: {', '.join(given)} cannot be combined with it "
                              "(a resumed run keeps the settings of its checkpoint)")  # fmt: skip
    variables = settings_variables(None if environ is None else dict(environ))
    if variables:
        raise CheckpointError(f"--resume {folder}: environment variable(s) {', '.join(variables)} would change "
                              "the checkpoint's settings; unset them (a resumed run keeps the settings of its "
                              "checkpoint; only the weights and the device may change)")  # fmt: skip


def resumed_config(config_path: Path, run_folder: Path, weights: Path | None, device: str | None) -> SlamConfig:
    """The settings of the checkpoint (its `config.yaml`), results beside its run's folder, the
    weights and device given (None: as the checkpoint has them, or as the environment says)."""
    config = load_config(str(config_path))
    if weights is not None:
        config.vpr.backbone.weights = str(weights)
    if device is not None:
        config.vpr.backbone.device = device  # type: ignore[assignment]  # validated on assignment
    config.results.out_dir = str(run_folder.parent)
    return config


def prepare_resume(
    folder: Path, options: Mapping[str, object], weights: Path | None = None, device: str | None = None
) -> Resume:
    """Check the options, read the checkpoint in `folder` (a run's results folder or a checkpoint
    folder) and check its run's folder can still be written, all before any frame is read."""
    check_resume_options(folder, options)
    checkpoint = load_checkpoint(folder)
    check_writable(checkpoint.run_folder, "--resume")
    config = resumed_config(checkpoint.config_path, checkpoint.run_folder, weights, device)
    prior_map = Path(checkpoint.meta.prior_map) if checkpoint.meta.prior_map else None
    return Resume(checkpoint, config, prior_map)
