"""Errors a user can fix print as one red line and exit with status 2, never a traceback.

An option value a config model refuses names the option the user typed, with the config key it
sets, not the model's class (a user never sees the models).
"""

from __future__ import annotations

import errno
import functools
from collections.abc import Callable
from typing import Any

import typer
from rich.markup import escape

from ssmvpr_common.disk_full import DiskFullError, is_disk_full
from ssmvpr_slam.cli.common import err_console
from ssmvpr_slam.cli.finite_options import check_finite_options


def _user_errors() -> tuple[type[BaseException], ...]:
    from ssmvpr_common.errors import SsmvprError
    from ssmvpr_slam.backend.g2o_io import PoseGraphFileError

    # SsmvprError: each package's errors (FrontendInputError, LoopClosureInputError,
    # WeightsNotFoundError, ConfigError, OutputError, CheckpointError, ...)
    return (SsmvprError, FileNotFoundError, PoseGraphFileError)


# What the file system refuses (a full disk, a permission, a read-only or missing path) is input
# to name in one line; other OSErrors (a broken pipe, a child process, a timeout) are faults.
_FILE_SYSTEM_ERRNOS = frozenset(
    {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOENT, errno.ENOTDIR,
     errno.EISDIR, errno.EEXIST, errno.ENOTEMPTY, errno.ENAMETOOLONG, errno.EFBIG, errno.EMFILE, errno.EXDEV}
)  # fmt: skip


def _print_error(message: str) -> None:
    # escaped: a path or value with [brackets] must not be read as rich markup
    err_console.print(f"[bold red]error:[/bold red] {escape(message)}", highlight=False, soft_wrap=True)


@functools.cache
def option_of_field() -> dict[tuple[type[Any], str], str]:
    """The options whose values the config models check, by (model, field). Imported on the
    first refused value, not with the command line, so `--help` stays instant."""
    from frontend.config import FolderSourceConfig, OdometryConfig
    from frontend.simulation.config import SimulationConfig
    from loopclosure.config import BackboneConfig, FilteringConfig, SequenceMatchConfig
    from ssmvpr_slam.config.map import MapConfig
    from ssmvpr_slam.config.pipeline import PipelineConfig
    from ssmvpr_slam.config.slam import VPREvalConfig

    return {
        (OdometryConfig, "kind"): "--odometry (frontend.odometry.kind)",
        (BackboneConfig, "device"): "--device (vpr.backbone.device)",
        (VPREvalConfig, "sequence_lengths"): "--sequence/-L (vpr_eval.sequence_lengths)",
        (VPREvalConfig, "tolerance"): "--tolerance (vpr_eval.tolerance)",
        (SequenceMatchConfig, "direction"): "--direction (vpr_eval.sequence.direction)",
        (FilteringConfig, "num_candidates"): "--num-candidates/-n (vpr.filtering.num_candidates)",
        (SimulationConfig, "max_frames"): "--frames (simulation.max_frames)",
        (SimulationConfig, "seed"): "--seed (simulation.seed)",
        (PipelineConfig, "max_frames"): "--frames (pipeline.max_frames)",
        (PipelineConfig, "realtime_rate"): "--rate (pipeline.realtime_rate)",
        (FolderSourceConfig, "pose_role"): "--pose-role (frontend.source.folder.pose_role)",
        (MapConfig, "workers"): "--workers (map.workers)",
    }


def validation_title(model: type[Any]) -> str:
    """The title pydantic gives a model's validation errors: its configured title, else its class name."""
    return model.model_config.get("title") or model.__name__


def option_name(title: str, field: str) -> str | None:
    """The option behind a refused value: `title` is the ValidationError's (the model's, see
    `validation_title`), `field` the first part of its location; None for a value no option sets."""
    for (model, name), option in option_of_field().items():
        if name == field and validation_title(model) == title:
            return option
    return None


_ELSEWHERE = "free space there, or give --out (or --cache) a folder on another disk"


def _file_system_error(exc: OSError) -> str:
    """'PATH: Permission denied': the file first; a file too large says where results can go instead."""
    where = f"{exc.filename}: " if exc.filename else ""
    message = f"{where}{exc.strerror or exc}"
    if exc.errno == errno.EFBIG:
        message += f" while writing it; {_ELSEWHERE}"
    return message


def _disk_full_error(exc: OSError) -> str:
    """'PATH: disk full while writing it (...; 3.1 MiB free on /data); what to do': the advice
    the error carries (a run: resume its last checkpoint), else where results can go instead."""
    full = exc if isinstance(exc, DiskFullError) else DiskFullError.of(exc.filename, exc)
    return str(full) if full.advice else f"{full}; {_ELSEWHERE}"


def friendly_errors(func: Callable[..., Any]) -> Callable[..., Any]:
    """Known input problems -> one line on stderr and exit status 2, never a traceback."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            check_finite_options(func, kwargs)  # typer passes every option by name: --radius nan, --rate inf
            return func(*args, **kwargs)
        except DiskFullError as exc:  # a user error, with its own advice
            _print_error(_disk_full_error(exc))
            raise typer.Exit(2) from None
        except _user_errors() as exc:
            _print_error(str(exc))
            raise typer.Exit(2) from None
        except OSError as exc:
            if is_disk_full(exc):  # a write outside the atomic writers (ENOSPC, or a short write)
                _print_error(_disk_full_error(exc))
                raise typer.Exit(2) from None
            if exc.errno not in _FILE_SYSTEM_ERRNOS:  # a broken pipe, a child process, a timeout: a fault
                raise
            _print_error(_file_system_error(exc))
            raise typer.Exit(2) from None
        except Exception as exc:
            from pydantic import ValidationError

            if not isinstance(exc, ValidationError):
                raise
            # an option value a config model refuses (--device gpu, -n 0)
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"])
            field = where.split(".")[0]
            name = option_name(exc.title, field) or f"{exc.title}.{where}"
            message = str(first["msg"]).replace("'kiss_icp'", "'kiss-icp'") if field == "kind" else first["msg"]
            _print_error(f"invalid value for {name}: {message} (got {first.get('input')!r})")
            raise typer.Exit(2) from None

    return wrapper
