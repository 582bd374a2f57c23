"""Ray for `map`: a local instance, or a cluster that is checked before the map depends on it.

`ray.init` on an address where no Ray answers retries for good (a warning every 30 s), and
SIGTERM does not end it. So a cluster address is first tried by a child process bounded by
`map.ray_connect_timeout_s`; only an address that answered as a Ray cluster is joined.
Every exit path of `ray_session` shuts Ray down, so no Ray process of a local instance
outlives `map`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.errors import SlamError

_PROBE = """
import os, sys
os.environ.setdefault("RAY_AUTH_MODE", "disabled")
import ray
ray.init(address=sys.argv[1], include_dashboard=False, log_to_driver=False, configure_logging=False)
ray.shutdown()
"""


class RayClusterError(SlamError, ConnectionError):
    """`--ray-address` names no Ray cluster that answers."""


def _init_kwargs() -> dict[str, Any]:
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # a local instance for this process alone
    return {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}


def check_cluster(address: str, timeout_s: float) -> None:
    """Refuse, within `timeout_s`, an address where no Ray cluster answers."""
    try:
        probe = subprocess.run([sys.executable, "-c", _PROBE, address], capture_output=True, text=True,
                               timeout=timeout_s, check=False)  # fmt: skip
    except subprocess.TimeoutExpired:
        raise RayClusterError(
            f"--ray-address {address}: no Ray cluster answered within {timeout_s:g} s (map.ray_connect_timeout_s); "
            "is its head node running (`ray start --head`) and is this its GCS address (host:6379 by default)?"
        ) from None
    if probe.returncode != 0:
        lines = [line for line in probe.stderr.splitlines() if line.strip()]
        why = lines[-1][:200] if lines else f"exit status {probe.returncode}"
        raise RayClusterError(f"--ray-address {address}: cannot join that Ray cluster ({why})")


def start_ray(config: SlamConfig, address: str | None) -> bool:
    """Join the cluster at `address`, or start a local Ray; True when this call initialised Ray."""
    try:
        import ray
    except ImportError:
        raise SlamError("`map` runs on Ray: pip install 'ssmvpr-slam[map]' (or pip install ray)") from None
    if ray.is_initialized():
        return False
    if address == "auto":
        try:
            ray.init(address="auto", **_init_kwargs())
        except ConnectionError:
            raise RayClusterError(
                "--ray-address auto: no Ray cluster is running on this machine; start one (`ray start --head`) "
                "or drop --ray-address to run a local Ray for this map"
            ) from None
        return True
    if address:
        check_cluster(address, config.map.ray_connect_timeout_s)
        ray.init(address=address, **_init_kwargs())
        return True
    wanted = config.map.workers * (config.map.worker_cpus or 1.0)
    ray.init(num_cpus=int(np.ceil(max(wanted, float(os.cpu_count() or 1)))), **_init_kwargs())
    return True


@contextmanager
def ray_session(config: SlamConfig, address: str | None) -> Iterator[None]:
    """Ray up for the block, and down after it whatever ends it (when this call started it)."""
    owns = start_ray(config, address)
    try:
        yield
    finally:
        if owns:
            import ray

            ray.shutdown()
