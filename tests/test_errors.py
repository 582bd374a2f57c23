"""One exception root across the packages, without the libraries importing each other.

frontend and loopclosure are independent (ARCHITECTURE.md): each may import only itself and
the leaf ssmvpr_common; ssmvpr_slam imports all. Checked on the source, import by import."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from frontend.errors import FrontendError, FrontendInputError
from loopclosure.errors import LoopClosureError, LoopClosureInputError, WeightsNotFoundError
from ssmvpr_common.errors import SsmvprError
from ssmvpr_slam.checkpoint import CheckpointError
from ssmvpr_slam.config import ConfigError
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.results import OutputError

ROOT = Path(__file__).resolve().parents[1]
OURS = {"frontend", "loopclosure", "ssmvpr_slam", "ssmvpr_common"}
ALLOWED = {
    "ssmvpr_common": {"ssmvpr_common"},
    "frontend": {"frontend", "ssmvpr_common"},
    "loopclosure": {"loopclosure", "ssmvpr_common"},
    "ssmvpr_slam": OURS,
}


@pytest.mark.parametrize(
    ("error", "package_root", "builtin"),
    [
        (FrontendInputError, FrontendError, ValueError),
        (LoopClosureInputError, LoopClosureError, ValueError),
        (WeightsNotFoundError, LoopClosureError, RuntimeError),
        (ConfigError, SlamError, ValueError),
        (OutputError, SlamError, ValueError),
        (CheckpointError, SlamError, ValueError),
    ],
)
def test_every_error_has_its_package_root_and_the_common_one(error: type, package_root: type, builtin: type) -> None:
    assert issubclass(error, package_root) and issubclass(package_root, SsmvprError)
    assert issubclass(error, builtin)  # callers catching the builtin type still do


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_packages_import_only_what_the_layering_allows(package: str) -> None:
    wrong = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                top = name.split(".")[0]
                if top in OURS and top not in ALLOWED[package]:
                    wrong.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {name}")
    assert not wrong, wrong
