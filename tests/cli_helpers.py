"""What the command-line tests share: invoking the CLI and checking a one-line user error.

Test modules import this as ``cli_helpers`` (tests/conftest.py puts this folder on sys.path,
which pytest's importlib mode does not do by itself)."""

from __future__ import annotations

import os

import pytest
from typer.testing import CliRunner

from ssmvpr_slam.cli import app


@pytest.fixture(autouse=True)
def clean_ssmvpr_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """No SSMVPR_ variable of the caller's shell leaks into a test (import it into a module to use it)."""
    for key in list(os.environ):
        if key.upper().startswith("SSMVPR_"):
            monkeypatch.delenv(key)


def invoke(*args: object, env: dict[str, str] | None = None):  # noqa: ANN201
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


def assert_user_error(result, *fragments: str) -> str:  # noqa: ANN001
    """Exit 2, exactly one `error:` line on stderr holding every fragment, no traceback."""
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert isinstance(result.exception, SystemExit)
    assert "Traceback" not in result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, result.stderr
    for fragment in fragments:
        assert fragment in errors[0], (fragment, errors[0])
    return errors[0]
