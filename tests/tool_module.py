"""A script of tools/ imported as a module, for the tests that call its functions
(tests/conftest.py puts this folder on sys.path)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def load_tool(name: str) -> ModuleType:
    """tools/<name>.py, registered under `name` (its dataclasses look their module up there)."""
    if str(TOOLS) not in sys.path:  # a tool imports the folder's private helpers (`_mcap_conversion`)
        sys.path.append(str(TOOLS))
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
