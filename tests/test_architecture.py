"""The layering (ARCHITECTURE.md) as import-linter contracts (pyproject.toml, `lint-imports`):
frontend and loopclosure independent of each other and of the application, ssmvpr_common the
leaf, no cycle between a package's modules; plus what the contracts do not state: no module at
all takes part in an import cycle (a package and one of its own modules included)."""

from __future__ import annotations

import logging
from pathlib import Path

import grimp
from importlinter.cli import lint_imports

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("frontend", "loopclosure", "ssmvpr_slam", "ssmvpr_common")


def test_the_import_contracts_hold() -> None:
    # import-linter configures logging with disable_existing_loggers: the loggers of the modules
    # imported so far would stay silent for every later test that reads their warnings (caplog)
    loggers = [lg for lg in logging.Logger.manager.loggerDict.values() if isinstance(lg, logging.Logger)]
    disabled = {lg.name: lg.disabled for lg in loggers}
    try:
        assert lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True, no_logo=True) == 0
    finally:
        for lg in loggers:
            lg.disabled = disabled[lg.name]


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan, iteratively)."""
    modules = sorted(m for m in graph.modules if m.split(".")[0] in PACKAGES)
    inside = set(modules)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []
    for root in modules:
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root) & inside)))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child) & inside))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.append(member)
                    if member == node:
                        break
                if len(group) > 1:
                    groups.append(sorted(group))
    return groups


def test_no_module_takes_part_in_an_import_cycle() -> None:
    assert _cycles(grimp.build_graph(*PACKAGES)) == []


def test_the_cycle_finder_finds_one() -> None:
    graph = grimp.ImportGraph()
    for module in ("frontend", "frontend.a", "frontend.b", "frontend.c"):
        graph.add_module(module)
    graph.add_import(importer="frontend.a", imported="frontend.b")
    graph.add_import(importer="frontend.b", imported="frontend.a")
    graph.add_import(importer="frontend.b", imported="frontend.c")
    assert _cycles(graph) == [["frontend.a", "frontend.b"]]


def test_a_long_module_says_why_and_the_core_reads_in_one_sitting() -> None:
    """A module of the application over 400 lines says at its top why it is one module; the SLAM
    core (`system.py`) holds the method's flow only, under 300 lines."""
    import ast

    unexplained = []
    for path in sorted((ROOT / "ssmvpr_slam").rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > 400 and "Over 400 lines" not in (ast.get_docstring(ast.parse(text)) or ""):
            unexplained.append(str(path.relative_to(ROOT)))
    assert unexplained == []
    assert (ROOT / "ssmvpr_slam" / "system.py").read_text(encoding="utf-8").count("\n") < 300


def test_the_slam_core_imports_no_reader_writer_or_simulator() -> None:
    """`ssmvpr_slam.system` is the method's flow: importing it loads no log reader or writer, no
    ROS or MCAP library and no simulator (the simulation's settings models aside). Checked in a
    fresh interpreter, where nothing else has imported them yet."""
    import subprocess
    import sys

    probe = ("import sys, ssmvpr_slam.system; print('\\n'.join(m for m in sys.modules if m.startswith("
             "('frontend.sources', 'frontend.simulation', 'rosbags', 'mcap', 'ssmvpr_slam.results.mcap_output'))))")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT)
    loaded = set(done.stdout.split())
    assert loaded <= {"frontend.simulation", "frontend.simulation.config"}, sorted(loaded)
    # the control: a reader's module does load them (the probe sees what it should)
    done = subprocess.run([sys.executable, "-c", probe.replace("ssmvpr_slam.system", "frontend.sources.mcap_source")],
                          capture_output=True, text=True, check=True, cwd=ROOT)  # fmt: skip
    assert "mcap" in done.stdout.split()
