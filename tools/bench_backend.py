#!/usr/bin/env python3
"""Robust pose-graph optimisation against injected false loops (Suenderhauf & Protzel protocol).

Graphs (outlier-free originals with ground truth): manhattan (Olson M3500), ring, ringCity
from ``$SSMVPR_SHARED/data/posegraphs`` (default ../shared next to the repository); sphere2500
(``sphere2500.txt`` + ``sphere2500_groundtruth.txt``, ground truth = its noise-free odometry
chained) and city10000 (the shared ``city10000.g2o``, identical to gtsam's
``T1_city10000_04`` edges, with gtsam's ``ISAM2_GT_city10000`` poses) from gtsam's data
(``gtsam.findExampleDataFile``).

False loops as Vertigo's ``generateDataset.py`` makes them: ``random`` joins two uniformly drawn
vertices, ``local`` a vertex and one at most 20 ids later, ``grouped`` adds groups of 10
consecutive, mutually consistent false loops (i+k, j+k); the measurement is a small random
motion (translation N(0, 0.3 m) per axis, rotation N(0, 10 deg) per axis, 2-D: x, y, yaw) and
the information matrix is that of the graph's first true loop. The outlier rate is the share
of false loops among all loop candidates: rate r adds round(r / (1 - r) * true loops).

Each row: ATE (RMSE, SE(2)/SE(3) aligned) of the solution divided by the ATE of the outlier-free
optimum (plain least squares on the original graph), ``ate_to_optimum`` (ATE of the solution
against that optimum itself, in metres: the reference for sphere2500 and city10000, whose
gtsam pose files are a noise-free chain and an iSAM2 estimate rather than independent ground
truth), outlier precision / recall (without GNC: whitened residual^2 > chi2 0.99 quantile; with
GNC: `optimize`'s default classification, GNC weight < 0.5 then the leave-one-out check), and
runtime. GNC rows start GNC from the kernel solution of the kernel's own row; their runtime
includes it. The GNC rows are `optimize`'s default configuration when the kernel is dcs.
With ``--zero-init`` (vertices chained from odometry) and the default ``--solver auto`` there are
two kernel starts (batch and iSAM2 in vertex order): the kernel row keeps the one with the lower
TLS objective, the GNC row takes each start through GNC and the check and keeps the lower of
those, as `optimize` does (so the two rows may come from different starts).

    python tools/bench_backend.py                       # everything, JSON on stdout
    python tools/bench_backend.py --graphs ring --rates 0.2 --kernels cauchy --kinds random
    python tools/bench_backend.py --graphs ringCity --kinds random --kernels dcs --jobs 4 --output r.json
    python tools/bench_backend.py --graphs manhattan --rates 0.5 --kinds random --kernels dcs --gnc on --zero-init
    python tools/bench_backend.py --markdown results.json   # tables from a saved run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ssmvpr_slam.backend.g2o_io import GraphEdge, PoseGraphData, planar_pose, read_ground_truth, read_pose_graph  # noqa: E402
from ssmvpr_slam.backend.graph_optimizer import (  # noqa: E402
    DEFAULT_REFINE_SCALES,
    KERNEL_NAMES,
    SOLVERS,
    OptimizerSettings,
    kernel_solutions,
    optimize_graph,
    refine_and_choose,
)
from ssmvpr_slam.backend.se3 import make_pose  # noqa: E402
from ssmvpr_slam.evaluation.graph_metrics import loop_classification_scores, trajectory_ate  # noqa: E402

GRAPHS = ("ring", "ringCity", "manhattan", "sphere2500", "city10000")
RATES = (0.1, 0.2, 0.3, 0.5)
KINDS = ("random", "local", "grouped")
KERNELS = ("cauchy", "huber", "dcs", "gm", "tukey")
GROUP_SIZE = 10
LOCAL_SPAN = 20


def shared_dir() -> Path:
    return Path(os.environ.get("SSMVPR_SHARED", REPO.parent / "shared"))


@dataclass(frozen=True)
class Benchmark:
    name: str
    graph: PoseGraphData
    gt: np.ndarray


def load_benchmark(name: str) -> Benchmark:
    """One of GRAPHS with its ground-truth poses."""
    base = shared_dir() / "data" / "posegraphs"
    if name in ("ring", "ringCity"):
        graph = read_pose_graph(base / name / "originalDataset" / f"{name}.g2o")
        gt = read_ground_truth(base / name / "groundTruth" / f"{name}.g2o", graph)
    elif name == "manhattan":
        graph = read_pose_graph(base / "manhattan" / "originalDataset" / "g2o" / "manhattanOlson3500.g2o")
        gt = read_ground_truth(base / "manhattan" / "groundTruth" / "manhattanOlson3500_nodes_groundTruth.dat", graph)
    elif name == "sphere2500":
        import gtsam

        graph = read_pose_graph(gtsam.findExampleDataFile("sphere2500.txt"))
        gt = read_ground_truth(gtsam.findExampleDataFile("sphere2500_groundtruth.txt"), graph)
    elif name == "city10000":
        import gtsam

        graph = read_pose_graph(base / "city10000" / "originalDataset" / "city10000.g2o")
        gt = read_ground_truth(gtsam.findExampleDataFile("ISAM2_GT_city10000.txt"), graph)
    else:
        raise ValueError(f"unknown graph {name!r}; expected one of {', '.join(GRAPHS)}")
    return Benchmark(name, graph, gt)


def _false_measurement(rng: np.random.Generator, dim: int) -> np.ndarray:
    if dim == 2:
        return planar_pose(rng.normal(0, 0.3), rng.normal(0, 0.3), rng.normal(0, math.radians(10)))
    t = rng.normal(0, 0.3, 3)
    roll, pitch, yaw = rng.normal(0, math.radians(10), 3)
    cr, sr, cp, sp, cy, sy = (
        math.cos(roll),
        math.sin(roll),
        math.cos(pitch),
        math.sin(pitch),
        math.cos(yaw),
        math.sin(yaw),
    )
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return make_pose(rz @ ry @ rx, t)


def inject_false_loops(graph: PoseGraphData, rate: float, kind: str, seed: int) -> tuple[PoseGraphData, np.ndarray]:
    """`graph` plus false loops making up `rate` of all loops; returns (graph, is_false per edge)."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    if not 0 <= rate < 1:
        raise ValueError(f"rate: must be in [0, 1), got {rate}")
    rng = np.random.default_rng(seed)
    loops = graph.loops
    n_false = int(round(rate / (1 - rate) * len(loops)))
    information = loops[0].information if loops else graph.edges[0].information
    group = GROUP_SIZE if kind == "grouped" else 1
    n_vertices = len(graph.ids)
    false_edges: list[GraphEdge] = []
    while len(false_edges) < n_false:
        v1 = v2 = 0
        while v1 == v2:
            v1 = int(rng.integers(0, n_vertices - group))
            if kind == "local":
                v2 = int(rng.integers(v1, min(n_vertices - group, v1 + LOCAL_SPAN) + 1))
            else:
                v2 = int(rng.integers(0, n_vertices - group))
            v1, v2 = min(v1, v2), max(v1, v2)
            if v2 == v1 + 1:
                v2 = v1 + 2
            if v2 >= n_vertices:
                v1 = v2 = 0
        measured = _false_measurement(rng, graph.dim)
        for k in range(min(group, n_false - len(false_edges))):
            false_edges.append(GraphEdge(graph.ids[v1 + k], graph.ids[v2 + k], measured, information))
    edges = (*graph.edges, *false_edges)
    flags = np.array([False] * len(graph.edges) + [True] * len(false_edges))
    return graph.with_edges(edges, f"{graph.source}+{kind}{rate:g}"), flags


def _row(
    bench: Benchmark,
    kernel: str,
    gnc: bool,
    rate: float,
    kind: str,
    result,
    truth: np.ndarray,
    reference_ate: float,
    n_false: int,
    optimum: np.ndarray,
) -> dict:  # noqa: ANN001
    ate = trajectory_ate(bench.gt, result.poses, bench.graph.dim).stats.rmse
    scores = loop_classification_scores(~result.loop_inlier, truth[result.loop_indices])
    return {
        "graph": bench.name, "kernel": kernel, "gnc": gnc, "rate": rate, "kind": kind,
        "true_loops": len(bench.graph.loops), "false_loops": n_false,
        "ate_rmse": ate, "ate_reference": reference_ate, "ate_ratio": ate / reference_ate,
        "ate_to_optimum": trajectory_ate(optimum, result.poses, bench.graph.dim).stats.rmse,
        "outlier_precision": scores["outlier_precision"], "outlier_recall": scores["outlier_recall"],
        "flagged_outliers": scores["flagged_outliers"], "seconds": result.seconds,
        "check_removed": result.check_removed, "check_readmitted": result.check_readmitted,
        "from_kernel": result.from_kernel, "check_seconds": result.check_seconds,
        "initialised_from_odometry": result.initialised_from_odometry, "kernel_solve": result.solver,
        "start_tls": dict(result.start_tls),
    }  # fmt: skip


def _cell_seed(seed: int, name: str, rate: float, kind: str) -> int:
    return seed + 1000 * RATES_INDEX.get(rate, 9) + 100 * KINDS.index(kind) + GRAPHS.index(name)


def _solve_cell(
    name: str,
    rate: float,
    kind: str,
    kernel: str,
    gnc_modes: tuple[bool, ...],
    solver: str,
    seed: int,
    refine_scales: tuple[float, ...],
    reference: float,
    optimum: np.ndarray,
    zero_init: bool = False,
) -> list[dict]:
    """Rows of one (graph, rate, kind, kernel): the kernel solve, and GNC (with the leave-one-out
    check, the default) started from it, each the lower-TLS start where there are two. Runs in a
    worker process with --jobs."""
    bench = _load_cached(name)
    noisy, truth = inject_false_loops(bench.graph, rate, kind, _cell_seed(seed, name, rate, kind))
    if zero_init:  # as a front end without its own estimate writes it: optimize chains odometry
        noisy = noisy.without_estimate()
    n_false = int(truth.sum())
    settings = OptimizerSettings(kernel=kernel, gnc=False, solver=solver, refine_scales=tuple(refine_scales))
    starts = kernel_solutions(noisy, settings)  # one per start: two for 'auto' from odometry
    rows = []
    for gnc in (False, True):
        if gnc in gnc_modes:
            result = refine_and_choose(noisy, starts, replace(settings, gnc=gnc))
            rows.append(_row(bench, kernel, gnc, rate, kind, result, truth, reference, n_false, optimum))
    return rows


_LOADED: dict[str, Benchmark] = {}


def _load_cached(name: str) -> Benchmark:
    if name not in _LOADED:
        _LOADED[name] = load_benchmark(name)
    return _LOADED[name]


def run_benchmark(
    graphs,
    rates,
    kinds,
    kernels,
    gnc_modes=(False, True),
    solver="auto",
    seed=0,
    kernels_by_graph=None,
    log=None,
    refine_scales=DEFAULT_REFINE_SCALES,
    checkpoint=None,
    jobs=1,
    zero_init=False,
) -> dict:  # noqa: ANN001
    """Rows for every (graph, kernel, gnc, rate, kind); see the module docstring. `checkpoint`
    (a callable) gets the results so far after every finished cell, so a run cut short keeps its
    rows. `jobs` > 1 solves cells in that many worker processes (GTSAM solves on one core)."""
    rows, references = [], {}

    def results() -> dict:
        return {
            "protocol": {"rates": list(rates), "kinds": list(kinds), "kernels": list(kernels),
                         "kernels_by_graph": kernels_by_graph or {}, "gnc": list(gnc_modes),
                         "solver": solver, "refine_scales": list(refine_scales),
                         "seed": seed, "group_size": GROUP_SIZE, "local_span": LOCAL_SPAN,
                         "gnc_check": True, "zero_init": zero_init},
            "references": references,
            "rows": sorted(rows, key=_row_order),
        }  # fmt: skip

    cells, optima = [], {}
    for name in graphs:
        bench = _load_cached(name)
        clean = optimize_graph(bench.graph, OptimizerSettings(kernel="none", gnc=False, solver="batch"))
        reference = trajectory_ate(bench.gt, clean.poses, bench.graph.dim).stats.rmse
        references[name] = {"ate_rmse": reference, "vertices": len(bench.graph.ids),
                            "true_loops": len(bench.graph.loops), "seconds": clean.seconds}  # fmt: skip
        optima[name] = clean.poses
        for rate in rates:
            for kind in kinds:
                for kernel in (kernels_by_graph or {}).get(name, kernels):
                    cells.append((name, rate, kind, kernel, tuple(gnc_modes), solver, seed, tuple(refine_scales),
                                  reference, optima[name], zero_init))  # fmt: skip

    def done(cell_rows: list[dict]) -> None:
        rows.extend(cell_rows)
        if log and cell_rows:
            r0 = cell_rows[0]
            log(f"{r0['graph']} rate={r0['rate']} {r0['kind']} {r0['kernel']}: " + ", ".join(
                f"gnc={r['gnc']} ratio={r['ate_ratio']:.3f} s={r['seconds']:.1f}" for r in cell_rows))  # fmt: skip
        if checkpoint:
            checkpoint(results())

    if jobs <= 1:
        for cell in cells:
            done(_solve_cell(*cell))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("fork")) as pool:
            for future in as_completed([pool.submit(_solve_cell, *cell) for cell in cells]):
                done(future.result())
    return results()


def _row_order(r: dict) -> tuple:
    return (GRAPHS.index(r["graph"]), r["kernel"], r["rate"], KINDS.index(r["kind"]), r["gnc"])


RATES_INDEX = {r: k for k, r in enumerate(RATES)}


def _cell(value: float | None, fmt: str) -> str:
    return "–" if value is None else fmt.format(value)


def markdown_tables(results: dict) -> str:
    """One table per kernel: rows graph / kind / rate, columns without and with GNC."""
    rows = results["rows"]
    out: list[str] = []
    kernels = list(dict.fromkeys(r["kernel"] for r in rows))
    for kernel in kernels:
        out.append(f"### Kernel `{kernel}`\n")
        out.append(
            "| graph | outliers | rate | ATE/opt | prec | recall | s | ATE/opt GNC | prec GNC | recall GNC | s GNC |"
        )
        out.append("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        keyed: dict[tuple, dict[bool, dict]] = {}
        for r in rows:
            if r["kernel"] == kernel:
                keyed.setdefault((r["graph"], r["kind"], r["rate"]), {})[r["gnc"]] = r
        for (graph, kind, rate), pair in keyed.items():
            cells = []
            for gnc in (False, True):
                r = pair.get(gnc)
                if r is None:
                    cells += ["–"] * 4
                else:
                    cells += [_cell(r["ate_ratio"], "{:.3f}"), _cell(r["outlier_precision"], "{:.3f}"),
                              _cell(r["outlier_recall"], "{:.3f}"), _cell(r["seconds"], "{:.1f}")]  # fmt: skip
            out.append(f"| {graph} | {kind} | {rate:.0%} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def summary(results: dict, tolerance: float = 1.10) -> list[dict]:
    """Per (kernel, gnc): worst ATE ratio over all rows and whether every random-outlier row
    is within `tolerance`."""
    groups: dict[tuple[str, bool], list[dict]] = {}
    for r in results["rows"]:
        groups.setdefault((r["kernel"], r["gnc"]), []).append(r)
    out = []
    for (kernel, gnc), rows in groups.items():
        random_rows = [r for r in rows if r["kind"] == "random"]
        out.append({
            "kernel": kernel, "gnc": gnc,
            "worst_ratio_random": max((r["ate_ratio"] for r in random_rows), default=None),
            "worst_ratio_all": max(r["ate_ratio"] for r in rows),
            "random_within_tolerance": all(r["ate_ratio"] <= tolerance for r in random_rows),
            "all_within_tolerance": all(r["ate_ratio"] <= tolerance for r in rows),
            "seconds_total": sum(r["seconds"] for r in rows),
        })  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--graphs", nargs="+", default=list(GRAPHS), choices=GRAPHS)
    parser.add_argument("--rates", nargs="+", type=float, default=list(RATES))
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    parser.add_argument("--kernels", nargs="+", default=list(KERNELS), choices=[k for k in KERNEL_NAMES if k != "none"])
    parser.add_argument(
        "--graph-kernels",
        action="append",
        default=[],
        metavar="GRAPH=K1,K2",
        help="limit the kernels of one graph (e.g. city10000=cauchy,dcs)",
    )
    parser.add_argument("--gnc", choices=("both", "on", "off"), default="both")
    parser.add_argument(
        "--zero-init", action="store_true", help="drop the stored vertex poses (optimize then chains odometry)"
    )
    parser.add_argument(
        "--solver",
        choices=SOLVERS,
        default="auto",
        help="kernel solve: batch LM, iSAM2 in vertex order (slow), or optimize's default 'auto' (batch from "
        "stored vertices; both, lower TLS objective kept, from odometry)",
    )
    parser.add_argument(
        "--refine-scales",
        nargs="*",
        type=float,
        default=list(DEFAULT_REFINE_SCALES),
        help="batch re-solves after the kernel solve (optimize's default: 1); none = off",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1, help="cells solved in parallel worker processes")
    parser.add_argument("--output", type=Path, help="also write the JSON here")
    parser.add_argument(
        "--markdown",
        nargs="?",
        const="-",
        metavar="RESULTS_JSON",
        help="print markdown tables: of a saved JSON, or (no value) of this run instead of JSON",
    )
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.markdown not in (None, "-"):
        results = json.loads(Path(args.markdown).read_text())
        print(markdown_tables(results))
        return 0
    by_graph = {}
    for item in args.graph_kernels:
        name, _, ks = item.partition("=")
        by_graph[name] = [k for k in ks.split(",") if k]
    gnc_modes = {"both": (False, True), "on": (True,), "off": (False,)}[args.gnc]
    log = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    from ssmvpr_common.atomic import atomic_write_text

    checkpoint = None
    if args.output:
        checkpoint = lambda partial: atomic_write_text(args.output, json.dumps(partial, indent=1) + "\n")  # noqa: E731
    results = run_benchmark(args.graphs, args.rates, args.kinds, args.kernels, gnc_modes,
                            solver=args.solver, seed=args.seed, kernels_by_graph=by_graph, log=log,
                            refine_scales=args.refine_scales, checkpoint=checkpoint, jobs=args.jobs,
                            zero_init=args.zero_init)  # fmt: skip
    results["summary"] = summary(results)
    text = json.dumps(results, indent=1)
    if args.output:
        atomic_write_text(args.output, text + "\n")
    print(markdown_tables(results) if args.markdown == "-" else text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
