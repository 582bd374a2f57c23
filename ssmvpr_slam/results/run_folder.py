"""Results folders: one timestamped folder per call and `latest` links, as kiss-icp does.

Every command's folder is `<command>_<stamp>` under the base folder (`--out`, default
`results/`); `latest` points at the newest of any command and `latest-<command>` at the
newest of that command (`latest-run`, `latest-vpr-eval`, `latest-loop-eval`, `latest-optimize`).

A results folder is written as one unit: everything goes into a hidden staging folder beside
the target, which is renamed into place when complete; only then does `latest` move (a new
link under a temp name, then ``os.replace``). A crash or an abandoned write leaves the
previous results and the previous `latest` as they were, never a half-written folder.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import signal
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import Any

from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.results.staging_lock import StagingLock, remove_left_over
from ssmvpr_slam.stop_signals import stop_signals_handled

log = logging.getLogger(__name__)

LATEST = "latest"


class OutputError(SlamError, ValueError):
    """An output path that cannot be written (a file where a folder is wanted, no permission...)."""


def _created_parents(path: Path) -> list[Path]:
    """The missing folders from the nearest existing ancestor down to `path`, outermost first."""
    missing = []
    for folder in (path, *path.parents):
        if folder.exists() or folder.is_symlink():
            break
        missing.append(folder)
    return missing[::-1]


def _check_writable(folder: Path, option: str, shown: Path) -> None:
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise OutputError(f"{option} {shown}: cannot write in {folder} ({exc.strerror or exc})") from None


def check_writable(folder: Path, what: str) -> None:
    """Refuse, before any work, a folder whose results could not be written (read-only, full
    quota): a resume writes checkpoints into the run's folder and its results beside it."""
    for place in (folder, folder.parent):
        _check_writable(place, what, folder)


def _make_folder(folder: Path, option: str, shown: Path) -> None:
    for part in (folder, *folder.parents):
        if part.exists() and not part.is_dir():
            what = "is a file" if part == shown else f"{part} is a file"
            raise OutputError(f"{option} {shown}: {what}, not a folder")
        if part.is_dir():
            break
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{option} {shown}: cannot create the folder ({exc.strerror or exc})") from None


def _remove_if_empty(created: list[Path]) -> None:
    for folder in reversed(created):  # innermost first
        try:
            folder.rmdir()
        except OSError:
            break  # not empty (something was written) or already gone


@contextmanager
def output_dir(path: str | Path, option: str = "--out") -> Iterator[Path]:
    """Create and check an output folder before any work starts.

    A file, or a folder that cannot be written, is an `OutputError` naming it. If the work in
    the block fails, folders this created and left empty are removed again, so a refused run
    leaves nothing behind."""
    folder = Path(path)
    with _made_writable(folder, option, folder):
        yield folder


@contextmanager
def output_file(path: str | Path, option: str = "--out") -> Iterator[Path]:
    """Check an output file's place before any work starts: not a folder, its folder writable.

    Like `output_dir`, missing parent folders are created, and removed again if the block fails
    before anything was written into them."""
    target = Path(path)
    if target.is_dir():
        raise OutputError(f"{option} {target}: is a folder; give a file name")
    with _made_writable(target.parent, option, target):
        yield target


@contextmanager
def _made_writable(folder: Path, option: str, named: Path) -> Iterator[None]:
    """`folder` made (with its missing parents) and checked writable, errors naming `named`; the
    folders this created are removed again, if still empty, when the block fails."""
    created = _created_parents(folder)
    _make_folder(folder, option, named)
    try:
        _check_writable(folder, option, named)
        yield
    except BaseException:
        _remove_if_empty(created)
        raise


class StagedResults:
    """A results folder under construction: write into `path`, then `publish()`.

    target: the folder to publish as (a run's folder that holds only its checkpoints so far);
    default a new `name_<stamp>` folder."""

    def __init__(self, base: str | Path, name: str, target: Path | None = None, adopt: Path | None = None) -> None:
        """adopt: a staging folder a killed call left (`map` goes on with its finished sessions);
        otherwise what killed calls of `name` left in `base` is removed (and logged)."""
        self.base = Path(base)
        self.name = name
        self.stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
        self.target = target
        self.base.mkdir(parents=True, exist_ok=True)
        if adopt is None:
            for folder in remove_left_over(self.base, name):
                log.warning("removed %s, left unfinished by an earlier call that was killed", folder)
        # hidden, so globs for finished folders (run_*) never see a partial one
        self.path = adopt or Path(tempfile.mkdtemp(prefix=f".{name}_{self.stamp}.", suffix=".partial", dir=self.base))
        try:
            self.lock = StagingLock(self.path)  # while it is held, no later call takes the folder for left over
        except OSError as exc:
            raise OutputError(f"{self.path}: another call is writing it ({exc.strerror or exc})") from None
        self.final: Path | None = None

    def publish(self) -> Path:
        """Rename the complete folder into place, then point `latest` at it."""
        self.lock.release()
        os.chmod(self.path, _default_dir_mode())  # mkdtemp makes 0700
        if self.target is not None:
            self.final = _replace_folder(self.path, self.target)
            point_latest(self.base, self.final.name, self.name)
            return self.final
        suffix = 0
        while True:
            final = self.base / (f"{self.name}_{self.stamp}" + (f"_{suffix}" if suffix else ""))
            if not final.exists() and not final.is_symlink():
                try:
                    os.rename(self.path, final)
                    break
                except OSError:  # taken meanwhile (another run finished in the same second)
                    if not final.exists():
                        raise
            suffix += 1
        self.final = final
        point_latest(self.base, final.name, self.name)
        return final

    def discard(self) -> None:
        self.lock.release()
        shutil.rmtree(self.path, ignore_errors=True)

    def keep(self) -> Path:
        """Leave the folder for a later call to adopt (its lock dropped as by a killed call)."""
        self.lock.release(keep_file=True)
        return self.path


def _replace_folder(complete: Path, target: Path) -> Path:
    """Move `complete` to `target`, replacing what is there (a run's checkpoints). The old
    folder is renamed aside first and removed last: a crash in between leaves it, whole,
    under a hidden name beside the target."""
    if not target.exists():
        os.rename(complete, target)
        return target
    aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".replaced", dir=target.parent))
    aside.rmdir()
    os.rename(target, aside)
    os.rename(complete, target)
    shutil.rmtree(aside, ignore_errors=True)
    return target


class RunFolder:
    """The folder a run's checkpoints go to, named (`name_<stamp>`) and made at the first one;
    the final results then replace it under the same name. Given `existing` (a resumed run),
    that folder is used."""

    def __init__(self, base: str | Path, name: str, existing: Path | None = None) -> None:
        self.base = Path(base) if existing is None else existing.parent
        self.name = name
        self.stamp = datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
        self.path: Path | None = existing

    def ensure(self) -> Path:
        """The folder, made now if it does not exist yet (never one another run made)."""
        if self.path is not None:
            return self.path
        self.base.mkdir(parents=True, exist_ok=True)
        suffix = 0
        while True:
            path = self.base / (f"{self.name}_{self.stamp}" + (f"_{suffix}" if suffix else ""))
            try:
                path.mkdir()
            except FileExistsError:
                suffix += 1
                continue
            self.path = path
            return path


def _default_dir_mode() -> int:
    """Permissions a plain ``mkdir`` would give."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o777 & ~umask


def latest_link(command: str) -> str:
    """The name of a command's own latest link: `latest-run`, `latest-vpr-eval`, ..."""
    return f"{LATEST}-{command.replace('_', '-')}"


def point_latest(base: Path, name: str, command: str | None = None) -> None:
    """Switch `base/latest` (and `base/latest-<command>`) to `name` atomically (a temp link
    renamed over the old one)."""
    for link_name in (LATEST, *((latest_link(command),) if command else ())):
        link = base / link_name
        if link.exists() and not link.is_symlink():
            log.warning("%s is not a link; left as it is (results are in %s)", link, base / name)
            continue
        switch_link(link, name)


def switch_link(link: Path, name: str) -> None:
    """Point the symlink `link` at `name` (relative, in its folder) atomically."""
    base = link.parent
    fd, tmp_name = tempfile.mkstemp(prefix=f".{link.name}.", dir=base)
    os.close(fd)
    tmp_link = Path(tmp_name)
    tmp_link.unlink()
    try:
        tmp_link.symlink_to(name, target_is_directory=True)
        os.replace(tmp_link, link)
    except BaseException:
        tmp_link.unlink(missing_ok=True)
        raise


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """While results are written, a first Ctrl-C / SIGTERM waits for the write to finish; a
    second abandons it (the staging folder is dropped, `latest` untouched)."""
    received: list[int] = []

    def handler(signum: int, _frame: object) -> None:
        received.append(signum)
        if len(received) == 1:
            log.warning("%s: finishing writing the results; send it again to abandon them",
                        signal.Signals(signum).name)  # fmt: skip
            return
        raise KeyboardInterrupt

    with stop_signals_handled(handler):
        yield


@contextmanager
def staged_results_dir(base: str | Path, name: str, target: Path | None = None) -> Iterator[StagedResults]:
    """Write a results folder as one unit: `staged.path` inside the block, `staged.final` after.

    Any exception (or a second interrupt) in the block drops the staging folder and leaves the
    previous `latest` (and `target`, if given) as it was."""
    staged = StagedResults(base, name, target)
    with interrupts_deferred():
        try:
            yield staged
        except BaseException:
            staged.discard()
            raise
        staged.publish()


def write_json(path: Path, data: Any) -> None:
    """Strict JSON (no NaN or Infinity, which most readers refuse): a value that is not a finite
    number (an ATE of a diverged graph, a ratio over zero) is written as null."""
    atomic_write_text(path, json.dumps(_finite(data), indent=2, allow_nan=False, default=_plain) + "\n")


def _finite(value: Any) -> Any:
    """`value` with every non-finite float (numpy's too) replaced by None, containers walked."""
    import numpy as np

    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(item) for item in value]
    if isinstance(value, np.ndarray):
        return _finite(value.tolist())
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def _plain(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
