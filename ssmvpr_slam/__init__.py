"""ssmvpr-slam: streaming SSM-VPR loop closures with a GTSAM back end.

The core without I/O and the runner around it import from here (torch, gtsam and kiss-icp load
on first use):

    from ssmvpr_slam import SlamSystem, load_config, map_logs, run_log
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ssmvpr_common.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from ssmvpr_slam.app.runner import run_log
    from ssmvpr_slam.config.slam import SlamConfig, load_config
    from ssmvpr_slam.errors import SlamError
    from ssmvpr_slam.multi_session.runner import map_logs
    from ssmvpr_slam.run_result import RunResult
    from ssmvpr_slam.system import SlamSystem

__version__ = "0.1.0"

_EXPORTS = {
    "SlamConfig": "ssmvpr_slam.config.slam",
    "load_config": "ssmvpr_slam.config.slam",
    "SlamError": "ssmvpr_slam.errors",
    "RunResult": "ssmvpr_slam.run_result",
    "run_log": "ssmvpr_slam.app.runner",
    "map_logs": "ssmvpr_slam.multi_session.runner",
    "SlamSystem": "ssmvpr_slam.system",
}
__all__ = [
    "RunResult",
    "SlamConfig",
    "SlamError",
    "SlamSystem",
    "load_config",
    "map_logs",
    "run_log",
]


__getattr__ = lazy_exports("ssmvpr_slam", _EXPORTS)
