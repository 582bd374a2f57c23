"""One exception root across the packages (the layering that keeps the libraries apart is
import-linter's contracts: tests/test_architecture.py)."""

from __future__ import annotations

import pytest

from frontend.errors import FrontendError, FrontendInputError
from loopclosure.errors import LoopClosureError, LoopClosureInputError, WeightsNotFoundError
from ssmvpr_common.disk_full import DiskFullError
from ssmvpr_common.errors import SsmvprError
from ssmvpr_slam.checkpoint.saving import CheckpointError
from ssmvpr_slam.config.slam import ConfigError
from ssmvpr_slam.errors import OptionError, SlamError
from ssmvpr_slam.results.run_folder import OutputError


@pytest.mark.parametrize(
    ("error", "package_root", "builtin"),
    [
        (FrontendInputError, FrontendError, ValueError),
        (LoopClosureInputError, LoopClosureError, ValueError),
        (WeightsNotFoundError, LoopClosureError, RuntimeError),
        (ConfigError, SlamError, ValueError),
        (OutputError, SlamError, ValueError),
        (CheckpointError, SlamError, ValueError),
        (OptionError, SlamError, ValueError),
        (DiskFullError, SsmvprError, OSError),  # a write that failed, whichever package wrote
    ],
)
def test_every_error_has_its_package_root_and_the_common_one(error: type, package_root: type, builtin: type) -> None:
    assert issubclass(error, package_root) and issubclass(package_root, SsmvprError)
    assert issubclass(error, builtin)  # callers catching the builtin type still do
