"""The table a run prints at its end, read from its metrics (`RunMetrics`).

It says what a number means where the number alone misleads: recall n/a because the route
never comes back, a rear camera's share of the loops, a prior map's own error that a session
corrected onto it inherits."""

from __future__ import annotations

from rich.table import Table

from ssmvpr_slam.results.metrics import RunMetrics


def _three(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def summary_table(metrics: RunMetrics, title: str = "ssmvpr-slam run") -> Table:
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_row("frames / keyframes", f"{metrics.frames} / {metrics.keyframes}")
    loops = metrics.loops
    if loops is not None:
        table.add_row("loops proposed / gate-accepted / in graph",
                      f"{loops.proposed} / {loops.gate_accepted} / {loops.in_graph}")  # fmt: skip
        if loops.spaced:  # loop_spacing_keyframes: judged with the loops in the graph below
            table.add_row("loops spaced out (not registered)", str(loops.spaced))
        table.add_row("loop precision / recall", f"{_three(loops.precision)} / {_three(loops.recall)}")
        if loops.n_revisits == 0:  # say why recall is n/a: the route never comes back
            table.add_row("revisits in the ground truth", "none: no place is passed twice, no loop to find")
        else:  # what a camera could see: reverse revisits show the far side
            fwd, rev = loops.by_direction["forward"], loops.by_direction["reverse"]
            table.add_row("recall of visible / forward / reverse revisits",
                          f"{_three(loops.recall_visible)} / {_three(fwd.recall)} / {_three(rev.recall)}")  # fmt: skip
        if loops.rear_camera_keyframes:  # the rear camera is what recognises reverse revisits
            by_camera = loops.in_graph_by_camera
            table.add_row("loops in graph: front / rear camera", f"{by_camera['front']} / {by_camera['rear']}")
        if loops.first_sight.get("revisits"):  # loops that waited for earlier ones miss the revisit's start
            by_method = loops.in_graph_by_method
            verified = ", ".join(f"{n} {how}" for how, n in by_method.items()) or "none"
            table.add_row("loops in graph, verified by", verified)
            table.add_row("revisits with their first loop in the graph",
                          f"{loops.first_sight['first_loop_in_graph']} / {loops.first_sight['revisits']}")  # fmt: skip
    prior = metrics.prior_map_loops
    if prior is not None:  # `--map`: loops to the earlier sessions' places are counted apart from the session's own
        table.add_row("prior-map loops proposed / gate-accepted / in graph",
                      f"{prior.loops_proposed} / {prior.loops_gate_accepted} / {prior.loops_in_graph}")  # fmt: skip
        if prior.precision is not None:
            table.add_row("prior-map loop precision", f"{prior.precision:.3f}")
        if prior.ate_rmse is not None:  # a session corrected onto the map inherits the map's own error
            table.add_row("prior map's own ATE RMSE", f"{prior.ate_rmse:.2f} m")
    if metrics.ground_truth_coverage is not None:  # evaluated on the keyframes with ground truth only
        table.add_row("ground truth coverage", f"{metrics.ground_truth_keyframes} / {metrics.keyframes} keyframes "
                      f"({100 * metrics.ground_truth_coverage:.0f}%)")  # fmt: skip
    if metrics.ate_odometry is not None and metrics.ate_optimised is not None:
        table.add_row("ATE RMSE odometry", f"{metrics.ate_odometry.rmse:.2f} m")
        table.add_row("ATE RMSE optimised", f"{metrics.ate_optimised.rmse:.2f} m")
        # None when the odometry's ATE is 0 (it followed the ground truth)
        table.add_row("optimised / odometry", _three(metrics.ate_ratio))
    if metrics.stream_pr_auc is not None:
        table.add_row("stream PR-AUC", f"{metrics.stream_pr_auc:.3f}")
    total = metrics.latency_per_keyframe.get("total")
    if total is not None:
        table.add_row("latency per keyframe (median)", f"{1000 * total.median_s:.0f} ms")
    live = metrics.realtime
    if live is not None:  # `--realtime`: did the run keep pace with its log, and what did it leave out
        table.add_row(
            f"real time x{live.rate:g}: lag median / p99", f"{_ms(live.lag_median_s)} / {_ms(live.lag_p99_s)}"
        )
        table.add_row("keyframes without recognition (too late)", f"{live.keyframes_skipped} of {live.keyframes}"
                      + ("" if live.kept_up else f": lag over {live.max_lag_s:g} s"))  # fmt: skip
    return table


def _ms(seconds: float | None) -> str:
    return "n/a" if seconds is None else f"{1000 * seconds:.0f} ms"
