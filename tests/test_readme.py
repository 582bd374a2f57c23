"""The README's commands: every `ssmvpr-slam` subcommand it shows exists (its --help exits 0), and
every docs page it links to is there."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def shown_subcommands() -> list[str]:
    found = set()
    for block in re.findall(r"```bash\n(.*?)```", README, re.S):
        for line in block.splitlines():
            match = re.search(r"\bssmvpr-slam ([a-z][a-z-]*)", line.split("#")[0])
            if match:
                found.add(match.group(1))
    return sorted(found)


def test_the_readme_shows_the_main_commands() -> None:
    assert {"run", "loop-eval", "vpr-eval", "demo", "simulate", "optimize"} <= set(shown_subcommands())


@pytest.mark.parametrize("command", shown_subcommands())
def test_each_subcommand_the_readme_shows_exists(command: str) -> None:
    result = invoke(command, "--help")
    assert result.exit_code == 0, result.output


def test_the_docs_pages_the_readme_links_to_exist() -> None:
    links = re.findall(r"\]\((docs/[^)#]+)", README)
    assert links
    for link in links:
        assert (ROOT / link).is_file(), link
