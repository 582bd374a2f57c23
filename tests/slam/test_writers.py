"""The writers change nothing they did not create: a result written twice (or a checkpoint
written while the run goes on) leaves the result, its database and the loaded prior map as
they were, and the files come out the same."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
from run_metrics_examples import example_inputs

from loopclosure.database import PlaceDatabase, PlaceInfo
from loopclosure.detector import LoopProposal
from loopclosure.encoder import PlaceCodes
from loopclosure.pca import Codebooks, PCAProjection
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.evaluation.run_report import evaluate
from ssmvpr_slam.prior_map import PriorMap, save_map
from ssmvpr_slam.results.writers import write_results
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult


def _projection(dim_in: int, dim: int, seed: int) -> PCAProjection:
    rng = np.random.default_rng(seed)
    components = np.linalg.qr(rng.standard_normal((dim_in, dim)))[0].T.astype(np.float32)
    return PCAProjection(
        rng.standard_normal(dim_in).astype(np.float32), components, np.ones(dim, np.float32), False, True
    )


def _codes(n: int, seed: int) -> PlaceCodes:
    rng = np.random.default_rng(seed)
    return PlaceCodes(
        rng.standard_normal((n, 16, 8)).astype(np.float32), rng.standard_normal((n, 3, 4, 6)).astype(np.float32)
    )


def test_writing_twice_changes_neither_the_result_nor_the_prior_map(tmp_path: Path) -> None:
    config = load_config()
    config.results.plots = False
    codebooks = Codebooks(_projection(30, 8, 1), _projection(20, 6, 2))
    # a prior map of 3 places, as `--map` loads it
    prior_db = PlaceDatabase(codebooks, config.vpr.database)
    prior_db.add(_codes(3, 0), [PlaceInfo(frame_id=i, timestamp=float(i)) for i in range(3)])
    save_map(tmp_path / "prior", prior_db, config.vpr, {i: np.eye(4) for i in range(3)}, {}, {})
    prior = PriorMap.load(tmp_path / "prior", config.vpr)
    prior_places = copy.deepcopy(prior.database.places)
    # the session's database: a copy of the prior one grown by 5 keyframes
    database = prior.database.copy()
    database.add(
        _codes(5, 1), [PlaceInfo(frame_id=k, timestamp=float(k), extra={"session": "current"}) for k in range(5)]
    )
    session_places = copy.deepcopy(database.places)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 0, 3] = np.arange(5.0)
    kfs = tuple(Keyframe(k, k, float(k), poses[k], poses[k], None, None) for k in range(5))
    loops = (
        LoopRecord(LoopProposal(4, 0, 3, 0.9, 0.5, 0, 0.0, True, "accepted", "forward"), factor_handle=0, dropped=True),
    )
    anchor = np.eye(4)
    anchor[1, 3] = 2.0
    result = RunResult(kfs, loops, np.arange(5.0), poses, poses, in_map_frame=np.linalg.inv(anchor) @ poses,
                       database=database, session_places={k: 3 + k for k in range(5)}, prior_map=prior)  # fmt: skip
    report = evaluate(result, config.evaluation)

    first = write_results(tmp_path / "first", result, report, config, example_inputs())
    second = write_results(tmp_path / "second", result, report, config, example_inputs())

    assert first == second
    assert prior.database.places == prior_places and database.places == session_places  # no pose written into them
    assert len(prior.database) == 3 and not any("map_pose" in p.extra for p in database.places[3:])
    assert result.loops[0].factor_handle == 0 and not result.loops[0].in_graph  # the final status stays a field
    for name in ("loop_closures.csv", "optimised.tum", "database/places.json"):
        assert (tmp_path / "first" / name).read_bytes() == (tmp_path / "second" / name).read_bytes()
    grown = PriorMap.load(tmp_path / "first" / "database", config.vpr)
    assert len(grown) == 8 and np.allclose(grown.poses[7][:3, 3], [4.0, -2.0, 0.0])  # session places in the map frame
    assert json.loads((tmp_path / "first" / "metrics.json").read_text())["prior_map_loops"]["places"] == 3


def test_json_is_strict_a_non_finite_number_is_null(tmp_path: Path) -> None:
    """metrics.json never holds NaN or Infinity (most JSON readers refuse them): null instead."""
    import json as json_module

    import numpy as np

    from ssmvpr_slam.results.run_folder import write_json

    path = tmp_path / "m.json"
    write_json(path, {"ate": float("inf"), "ratio": np.float64("nan"), "rows": [1.5, np.array([np.inf, 2.0])]})
    assert json_module.loads(path.read_text()) == {"ate": None, "ratio": None, "rows": [1.5, [None, 2.0]]}


def test_rpe_all_pairs_is_read_by_the_report() -> None:
    """evaluation.trajectory.rpe_all_pairs: pairs from every pose (evo's all_pairs), not every delta-th."""
    config = load_config()
    config.evaluation.trajectory.rpe_delta = 3
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = np.arange(10.0)
    kfs = tuple(Keyframe(k, k, float(k), poses[k], poses[k], poses[k], None) for k in range(10))
    result = RunResult(kfs, (), np.arange(10.0), poses, poses)
    every_third = evaluate(result, config.evaluation).trajectory.rpe_odometry  # type: ignore[union-attr]
    config.evaluation.trajectory.rpe_all_pairs = True
    every_pose = evaluate(result, config.evaluation).trajectory.rpe_odometry  # type: ignore[union-attr]
    assert (len(every_third.pairs), len(every_pose.pairs)) == (3, 7)
