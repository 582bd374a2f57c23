"""The README's commands: every `ssmvpr-slam` subcommand it shows exists (its --help exits 0) and
takes the options shown with it, its first Python example runs as written, and every docs page
it links to is there."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def shown_lines() -> list[tuple[str, list[str]]]:
    """(subcommand, the options written after it) for every `ssmvpr-slam` line of a bash block."""
    found = []
    for block in re.findall(r"```bash\n(.*?)```", README, re.S):
        for line in block.splitlines():
            command = line.split("#")[0]
            match = re.search(r"\bssmvpr-slam ([a-z][a-z-]*)(.*)", command)
            if match:
                options = re.findall(r"(?<!\S)(--?[a-z][a-z-]*)", match.group(2))
                found.append((match.group(1), options))
    return found


def shown_subcommands() -> list[str]:
    return sorted({command for command, _ in shown_lines()})


def test_the_readme_shows_the_main_commands() -> None:
    assert {"run", "loop-eval", "vpr-eval", "demo", "simulate", "optimize", "map"} <= set(shown_subcommands())


@pytest.mark.parametrize("command", shown_subcommands())
def test_each_subcommand_the_readme_shows_exists(command: str) -> None:
    result = invoke(command, "--help")
    assert result.exit_code == 0, result.output


def test_each_option_the_readme_shows_is_one_its_command_takes() -> None:
    helps = {command: invoke(command, "--help", env={"COLUMNS": "200"}).output for command in shown_subcommands()}
    for command, options in shown_lines():
        for option in options:
            assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", helps[command]), (command, option)


@pytest.mark.slow
def test_the_first_python_example_runs_as_written(shared_dir: Path) -> None:
    code = re.findall(r"```python\n(.*?)```", README, re.S)[0]
    code = code.replace("../shared", str(shared_dir))  # the README assumes the checkout beside shared/
    env = {k: v for k, v in os.environ.items() if not k.startswith("SSMVPR_")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=600, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert len(lines) == 10, done.stdout
    matches = [re.fullmatch(r"day (\d+) -> night (\d+) \((0\.\d\d)\)", line) for line in lines]
    assert all(matches), done.stdout
    # day to night, 10 places a few metres apart: the right place or its neighbour for most
    near = sum(abs(int(m.group(1)) - int(m.group(2))) <= 1 for m in matches if m)
    assert near >= 8, done.stdout


def test_the_docs_pages_the_readme_links_to_exist() -> None:
    links = re.findall(r"\]\((docs/[^)#]+)", README)
    assert links
    for link in links:
        assert (ROOT / link).is_file(), link


def test_ci_runs_the_readmes_test_command_and_then_the_end_to_end_tier() -> None:
    """The README's test command is the one `.ci/run` runs (lint, types, the package tier), and
    `.ci/run` then runs every test the README's command leaves out (the `slow` tier)."""
    ci = (ROOT / ".ci" / "run").read_text()
    tests_block = next(b for b in re.findall(r"```bash\n(.*?)```", README, re.S) if "pytest" in b)
    checks = tests_block.strip().split("&& ruff check", 1)[1]
    assert "ruff check" + checks in ci
    package_tier = re.search(r"python -m pytest[^\n&]*", checks)
    end_to_end = re.search(r"python -m pytest[^\n&]*-m slow[^\n&]*", ci)
    assert package_tier and end_to_end and ci.index(package_tier.group(0)) < ci.index(end_to_end.group(0))
