"""A map under construction that survives its call: finished sessions are kept for the next one.

`map` builds in a hidden staging folder under `--out` (`.map_<stamp>.*.partial`). Beside the
sessions' results it keeps its plan (a digest of the settings that shape a session's results,
and the map it extends) and the record of every finished session (its log's fingerprint,
written after the session). A call that was stopped, or killed outright, leaves that folder;
the next `map` on the same `--out` (or `map --resume DIR`) adopts it when the plan matches,
reuses each session whose log is unchanged and runs the rest. A left-over folder whose plan
differs is removed, and said so.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_slam.checkpoint.saving import log_fingerprint
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.results.run_folder import StagedResults
from ssmvpr_slam.results.staging_lock import LOCK_NAME, in_use, left_over

PLAN = "plan.json"
FINISHED = "finished_sessions.json"
CODEBOOKS = "codebooks.npz"
_KEPT = {PLAN, FINISHED, CODEBOOKS, LOCK_NAME, "sessions"}
# settings that change how fast a map is made, never what is in it
_NOT_IN_PLAN = {"workers", "worker_cpus", "worker_gpus", "task_retries", "ray_connect_timeout_s"}


class MapResumeError(SlamError, ValueError):
    """`map --resume DIR` on a folder that cannot be resumed."""


def map_plan(config: SlamConfig, add_to: Path | None) -> dict[str, Any]:
    """What a left-over map must share with this call for its sessions to be reused."""
    settings = config.model_dump(mode="json")
    settings["results"].pop("out_dir", None)
    for key in _NOT_IN_PLAN:
        settings["map"].pop(key, None)
    backbone = settings["vpr"]["backbone"]
    if backbone["weights"] not in (None, "random"):  # one file, however the call named it
        backbone["weights"] = str(Path(backbone["weights"]).expanduser().resolve())
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()
    return {"settings_sha256": digest, "add_to": None if add_to is None else str(add_to.resolve())}


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


class MapStaging:
    """The staging folder of one `map` call, new or adopted; `reused` names the sessions kept."""

    def __init__(self, staged: StagedResults, plan: dict[str, Any], adopted: bool) -> None:
        self.staged = staged
        self.path = staged.path
        self.adopted = adopted
        self.sessions_dir = self.path / "sessions"
        self.sessions_dir.mkdir(exist_ok=True)
        atomic_write_text(self.path / PLAN, json.dumps(plan, indent=2) + "\n")
        if not (self.path / FINISHED).exists():
            atomic_write_text(self.path / FINISHED, "[]\n")

    @classmethod
    def open(cls, out_dir: Path, plan: dict[str, Any], resume: Path | None, console: Console) -> MapStaging:
        """Adopt `resume`, or the newest left-over map of the same plan under `out_dir`; left-over
        maps of another plan are removed."""
        if resume is not None:
            _check_resumable(resume, plan)
            adopt: Path | None = resume
        else:
            adopt = None
            for folder in left_over(out_dir, "map"):
                if adopt is None and _read_json(folder / PLAN) == plan:
                    adopt = folder
                    continue
                shutil.rmtree(folder, ignore_errors=True)
                console.print(f"removed {escape(str(folder))}: a map left unfinished with other settings")
        if adopt is not None:
            for entry in adopt.iterdir():  # what an interrupted final write had begun goes
                if entry.name not in _KEPT:
                    shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
        base = out_dir if adopt is None else adopt.parent  # published beside where it was staged (one rename)
        return cls(StagedResults(base, "map", adopt=adopt), plan, adopted=adopt is not None)

    def finished(self) -> dict[str, dict[str, Any]]:
        """Finished sessions on record, by name, whose results are still there."""
        records = _read_json(self.path / FINISHED) or []
        return {r["name"]: r for r in records if (self.path / r["folder"]).is_dir()}

    def reusable(self, jobs: list[tuple[int, str, str]]) -> dict[str, dict[str, Any]]:
        """The jobs a finished session of the same log (unchanged since) already did."""
        finished = self.finished()
        reused = {}
        for _, name, log in jobs:
            record = finished.get(name)
            if record is None or record["log"] != str(Path(log).resolve()):
                continue
            try:
                if record["fingerprint"] == log_fingerprint(log):
                    reused[name] = record
            except OSError:
                continue  # the log is gone: its session runs (and fails by name) as any other
        return reused

    def record_finished(self, record: dict[str, Any], log: str) -> None:
        """Put a finished session on record (after its results folder was published)."""
        records = [r for r in (_read_json(self.path / FINISHED) or []) if r["name"] != record["name"]]
        entry = {**record, "log": str(Path(log).resolve()), "fingerprint": log_fingerprint(log)}
        atomic_write_text(self.path / FINISHED, json.dumps([*records, entry], indent=2) + "\n")

    def keep(self) -> Path:
        """Leave the folder for the next call (its finished sessions are kept)."""
        return self.staged.keep()


def _check_resumable(folder: Path, plan: dict[str, Any]) -> None:
    if not (folder / PLAN).is_file():
        raise MapResumeError(f"--resume {folder}: not a map left unfinished (no {PLAN}); pass the folder `map` named")
    if in_use(folder):
        raise MapResumeError(f"--resume {folder}: another `map` is still writing it")
    earlier = _read_json(folder / PLAN)
    if earlier != plan:
        what = "the map it extends (--map)" if earlier and earlier.get("add_to") != plan["add_to"] else "the settings"
        raise MapResumeError(f"--resume {folder}: {what} differ from that map's; give the same ones, or start afresh "
                             "without --resume")  # fmt: skip
