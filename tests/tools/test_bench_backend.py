"""tools/bench_backend.py in seconds: injection protocol, one tiny run, the markdown tables."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from tool_module import load_tool


@pytest.fixture(scope="module")
def bench():  # noqa: ANN201
    return load_tool("bench_backend")


@pytest.mark.parametrize("kind", ["random", "local", "grouped"])
def test_injection_follows_the_protocol(bench, kind: str, shared_dir: Path) -> None:  # noqa: ANN001
    graph = bench.load_benchmark("ring").graph
    noisy, truth = bench.inject_false_loops(graph, 0.5, kind, seed=4)
    false = [e for e, t in zip(noisy.edges, truth) if t]
    assert len(false) == len(graph.loops) == 26  # 50 % of all loops
    assert all(not e.is_odometry and e.i < e.j for e in false)
    if kind == "local":
        assert all(e.j - e.i <= bench.LOCAL_SPAN + 1 for e in false)
    if kind == "grouped":
        assert all(np.allclose(false[k].measured, false[0].measured) for k in range(10))
        assert [e.i - false[0].i for e in false[:10]] == list(range(10))
    again, _ = bench.inject_false_loops(graph, 0.5, kind, seed=4)
    assert [(e.i, e.j) for e in again.edges] == [(e.i, e.j) for e in noisy.edges]  # seeded


def test_tiny_run_json_and_markdown(bench, capsys, tmp_path: Path, shared_dir: Path) -> None:  # noqa: ANN001
    out = tmp_path / "r.json"
    assert bench.main(["--graphs", "ring", "--rates", "0.3", "--kinds", "random", "--kernels", "dcs",
                       "--output", str(out), "--quiet"]) == 0  # fmt: skip
    results = json.loads(capsys.readouterr().out)
    assert results == json.loads(out.read_text())
    rows = results["rows"]
    assert {(r["kernel"], r["gnc"]) for r in rows} == {("dcs", False), ("dcs", True)}
    gnc = next(r for r in rows if r["gnc"])
    assert gnc["ate_ratio"] <= 1.1 and gnc["outlier_recall"] == 1.0 and gnc["false_loops"] == 11
    assert bench.main(["--markdown", str(out)]) == 0
    table = capsys.readouterr().out
    assert "### Kernel `dcs`" in table and "| ring | random | 30% |" in table
    assert not gnc["initialised_from_odometry"] and not results["protocol"]["zero_init"]


def test_zero_init_starts_from_chained_odometry(bench, capsys, shared_dir: Path) -> None:  # noqa: ANN001
    """--zero-init drops the stored vertices, as a front end without its own estimate writes
    them; the default still holds from the chained odometry."""
    assert bench.main(["--graphs", "ring", "--rates", "0.3", "--kinds", "random", "--kernels", "dcs",
                       "--gnc", "on", "--zero-init", "--quiet"]) == 0  # fmt: skip
    results = json.loads(capsys.readouterr().out)
    (row,) = results["rows"]
    assert results["protocol"]["zero_init"] and row["initialised_from_odometry"]
    assert row["ate_ratio"] <= 1.1 and row["outlier_recall"] == 1.0
    assert set(row["start_tls"]) == {"batch", "isam2"}  # both kernel solves from odometry


@pytest.mark.slow
def test_from_odometry_the_start_with_lower_tls_holds_where_the_other_fails(bench, shared_dir: Path) -> None:  # noqa: ANN001
    """ringCity with 20 % grouped false loops, vertices chained from odometry (the bench's cell):
    iSAM2 in vertex order followed by GNC and the check keeps false groups, the batch start does
    not, and the TLS objective tells them apart, so the default holds."""
    from ssmvpr_slam.backend.graph_optimizer import (
        OptimizerSettings,
        kernel_solutions,
        optimize_graph,
        refine_and_choose,
        refine_with_gnc,
    )  # fmt: skip
    from ssmvpr_slam.evaluation.graph_metrics import trajectory_ate

    ring_city = bench.load_benchmark("ringCity")
    optimum = optimize_graph(ring_city.graph, OptimizerSettings(kernel="none", gnc=False, solver="batch"))
    reference = trajectory_ate(ring_city.gt, optimum.poses, 2).stats.rmse
    noisy, truth = bench.inject_false_loops(
        ring_city.graph, 0.2, "grouped", bench._cell_seed(0, "ringCity", 0.2, "grouped")
    )
    noisy = noisy.without_estimate()
    settings = OptimizerSettings()
    answers = {k.solver: refine_with_gnc(noisy, k, settings) for k in kernel_solutions(noisy, settings)}
    ratio = {name: trajectory_ate(ring_city.gt, r.poses, 2).stats.rmse / reference for name, r in answers.items()}
    assert ratio["isam2"] > 5.0 and ratio["batch"] <= 1.1, ratio
    chosen = refine_and_choose(noisy, list(answers.values()), replace(settings, gnc=False))  # refined: choose only
    assert chosen.solver == "batch" and dict(chosen.start_tls)["batch"] < dict(chosen.start_tls)["isam2"]
    assert np.array_equal(~chosen.loop_inlier, truth[chosen.loop_indices])  # every false loop, no true one
