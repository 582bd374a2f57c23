"""The `ssmvpr-slam` command line (typer + rich), in the style of kiss-icp's `kiss_icp_pipeline`.

A command parses its options and calls the module that does its work; the commands are grouped
by what they are for: `slam` (run, demo, simulate), `mapping` (map), `evaluation` (vpr-eval,
loop-eval, optimize), `tools` (fit-pca, weights, config); `common` and `errors` hold what they
share. Heavy imports (torch, gtsam, kiss-icp) happen inside the commands so `--help` is instant.
Errors a user can fix print as one red line and exit with status 2.
"""

from __future__ import annotations

import os
import sys

# Before torch (imported inside the commands) loads its OpenMP runtime: idle OpenMP threads sleep
# instead of spinning. kiss-icp's threads, faiss's and the backbone's share the cores of one
# process, and spinning threads take the cores from each other (docs/benchmarks.md, "Thread
# settings"). An explicit OMP_WAIT_POLICY in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from ssmvpr_slam.cli import evaluation, mapping, slam, tools  # noqa: F401  (importing them registers the commands)
from ssmvpr_slam.cli.common import app

# the order `ssmvpr-slam --help` lists the commands in (the weights group comes after them)
_ORDER = ("vpr-eval", "loop-eval", "simulate", "run", "map", "demo", "fit-pca", "config", "optimize")
app.registered_commands.sort(key=lambda command: _ORDER.index(command.name) if command.name in _ORDER else len(_ORDER))


def main() -> None:  # pragma: no cover - console script entry
    sys.exit(app())


__all__ = ["app", "main"]
