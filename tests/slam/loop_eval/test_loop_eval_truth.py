"""loop-eval's ground truth and scoring on small synthetic inputs: two passes, poses, loop
matrices (.npy, .csv, .mat), the exclusion window, and precision / recall / max recall at 100 %
precision / false accepts by place."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from loopclosure.detector import LoopProposal
from ssmvpr_slam.loop_eval import revisit_truth as truth
from ssmvpr_slam.loop_eval import score
from ssmvpr_slam.loop_eval.revisit_truth import LoopTruthError
from ssmvpr_slam.loop_eval.stream import StreamOutcome, path_positions, travelled


def names(n: int, folder: str) -> list[Path]:
    return [Path(folder) / f"{i:04d}.png" for i in range(n)]


def proposal(q: int, m: int, z: float, accepted: bool) -> LoopProposal:
    return LoopProposal(q, m, m, 0.5, 0.5, 0, 0.0, accepted, "", "forward", sequence_score=0.1, decision_score=z)


def test_two_passes_revisit_frame_by_frame_and_judge_within_the_tolerance() -> None:
    loop_truth, _ = truth.two_passes(names(5, "a"), names(5, "b"), None, tolerance=1)
    assert loop_truth.has_truth.tolist() == [False] * 5 + [True] * 5
    assert loop_truth.passes.tolist() == [0] * 5 + [1] * 5
    assert loop_truth.correct(7, 2) and loop_truth.correct(7, 3) and not loop_truth.correct(7, 4)


def test_two_passes_with_a_pairs_file(tmp_path: Path) -> None:
    pairs = tmp_path / "gt.csv"
    pairs.write_text("Reference,Live\n0003.png,0000.png\n0000.png,0001.png\n")
    loop_truth, _ = truth.two_passes(names(4, "a"), names(2, "b"), pairs, tolerance=0)
    assert [m.tolist() for m in loop_truth.matches[4:]] == [[3], [0]]
    assert loop_truth.correct(4, 3) and not loop_truth.correct(4, 2)


def test_poses_make_revisits_outside_the_exclusion_window() -> None:
    # a 10 m square driven twice, a frame per metre: frame q revisits q - 40 (and nothing nearer
    # than the 30-keyframe / 15 m window)
    side = np.arange(10.0)
    lap = np.concatenate([np.c_[side, 0 * side], np.c_[10 + 0 * side, side], np.c_[10 - side, 10 + 0 * side],
                          np.c_[0 * side, 10 - side]])  # fmt: skip
    pos = np.c_[np.concatenate([lap, lap]), np.zeros(80)]
    loop_truth = truth.from_poses(pos, 0.5, travelled(pos), 30, 15.0)
    assert loop_truth.has_truth.tolist() == [False] * 40 + [True] * 40
    assert all(m.tolist() == [q - 40] for q, m in enumerate(loop_truth.matches) if q >= 40)
    assert loop_truth.correct(50, 10) and not loop_truth.correct(50, 13)  # judged by distance
    with pytest.raises(LoopTruthError, match="radius"):
        truth.from_poses(pos, 0.0, travelled(pos), 30, 15.0)


@pytest.mark.parametrize("suffix", [".npy", ".csv", ".mat"])
def test_a_loop_matrix_is_read_symmetrised_and_cut_by_the_exclusion_window(tmp_path: Path, suffix: str) -> None:
    n = 60
    matrix = np.zeros((n, n), np.uint8)
    matrix[45, 5] = 1  # lower triangle
    matrix[20, 50] = 1  # upper triangle: 50 revisits 20
    matrix[40, 35] = 1  # inside the 30-keyframe window: never a loop to find
    path = tmp_path / f"gt{suffix}"
    if suffix == ".npy":
        np.save(path, matrix)
    elif suffix == ".csv":
        np.savetxt(path, matrix, fmt="%d", delimiter=",")
    else:
        from scipy.io import savemat

        savemat(str(path), {"truth": matrix})
    loop_truth = truth.from_matrix(path, n, 2, travelled(path_positions(n, 1.0)), 30, 15.0)
    assert np.flatnonzero(loop_truth.has_truth).tolist() == [45, 50]
    assert loop_truth.matches[50].tolist() == [20] and loop_truth.correct(45, 7) and not loop_truth.correct(45, 8)


def test_loop_matrices_that_cannot_serve_are_named(tmp_path: Path) -> None:
    np.save(tmp_path / "rect.npy", np.zeros((3, 4)))
    with pytest.raises(LoopTruthError, match="square"):
        truth.read_matrix(tmp_path / "rect.npy")
    np.save(tmp_path / "five.npy", np.zeros((5, 5)))
    with pytest.raises(LoopTruthError, match="a 5x5 loop matrix for 6 images"):
        truth.from_matrix(tmp_path / "five.npy", 6, 2, np.arange(6.0), 30, 15.0)
    (tmp_path / "junk.csv").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(LoopTruthError, match="junk.csv: not a readable loop matrix"):
        truth.read_matrix(tmp_path / "junk.csv")
    (tmp_path / "m.xls").write_text("1")
    with pytest.raises(LoopTruthError, match="unknown loop-matrix format"):
        truth.read_matrix(tmp_path / "m.xls")
    with pytest.raises(LoopTruthError, match="no such ground-truth matrix"):
        truth.read_matrix(tmp_path / "none.npy")
    from scipy.io import savemat

    savemat(str(tmp_path / "two.mat"), {"a": np.eye(3), "b": np.eye(3)})
    with pytest.raises(LoopTruthError, match="one square matrix variable, found 2"):
        truth.read_matrix(tmp_path / "two.mat")


def _similarities(n: int) -> np.ndarray:
    """A similarity matrix as some benchmarks ship it: 0.05 .. 0.95, highest on the true loops."""
    rng = np.random.default_rng(0)
    matrix = rng.uniform(0.05, 0.5, (n, n))
    matrix[45, 5] = matrix[50, 20] = 0.95
    return matrix


@pytest.mark.parametrize("suffix", [".npy", ".csv", ".mat"])
def test_a_similarity_matrix_is_refused_naming_the_file_and_its_values(tmp_path: Path, suffix: str) -> None:
    """Before: every non-zero value was a loop, so a similarity matrix made every pair a revisit."""
    path = tmp_path / f"sim{suffix}"
    matrix = _similarities(60)
    if suffix == ".npy":
        np.save(path, matrix)
    elif suffix == ".csv":
        np.savetxt(path, matrix, fmt="%.4f", delimiter=",")
        matrix = np.loadtxt(path, delimiter=",")  # as rounded in the file
    else:
        from scipy.io import savemat

        savemat(str(path), {"similarity": matrix})
    with pytest.raises(LoopTruthError) as caught:
        truth.from_matrix(path, 60, 2, travelled(path_positions(60, 1.0)), 30, 15.0)
    message = str(caught.value)
    low, high = matrix.min(), matrix.max()
    assert message.startswith(f"{path}: 3,600 values between {low:.4g} and {high:.4g}, not 0/1"), message
    assert "--gt-threshold" in message and "\n" not in message


def test_with_a_threshold_values_at_or_above_it_are_loops(tmp_path: Path) -> None:
    path = tmp_path / "sim.npy"
    np.save(path, _similarities(60))
    loop_truth = truth.from_matrix(path, 60, 2, travelled(path_positions(60, 1.0)), 30, 15.0, threshold=0.95)
    assert np.flatnonzero(loop_truth.has_truth).tolist() == [45, 50]
    assert loop_truth.matches[50].tolist() == [20]


def test_0_1_and_boolean_matrices_need_no_threshold_and_other_integers_are_refused(tmp_path: Path) -> None:
    matrix = np.zeros((4, 4), bool)
    matrix[3, 0] = True
    np.save(tmp_path / "bool.npy", matrix)
    assert truth.read_matrix(tmp_path / "bool.npy").tolist() == matrix.tolist()
    counts = matrix.astype(np.int64) * 2  # a count of revisits, not a 0/1 flag
    np.save(tmp_path / "counts.npy", counts)
    with pytest.raises(LoopTruthError, match="counts.npy: 1 values of 2, not 0/1"):
        truth.read_matrix(tmp_path / "counts.npy")
    assert truth.read_matrix(tmp_path / "counts.npy", threshold=1).tolist() == matrix.tolist()


def test_scores_at_the_decision_and_over_the_decision_score() -> None:
    # two passes of 4: frames 4..7 revisit 0..3
    loop_truth, _ = truth.two_passes(names(4, "a"), names(4, "b"), None, tolerance=0)
    proposals = (
        None, None, proposal(2, 0, 1.0, False),  # a first-pass frame: within the pass, not accepted
        proposal(3, 1, 7.0, True),  # accepted within the first pass: a false accept
        proposal(4, 0, 9.0, True), proposal(5, 1, 8.0, True), proposal(6, 0, 6.5, True),  # 6 -> 0 is wrong
        proposal(7, 3, 5.0, False),  # right, not accepted
    )  # fmt: skip
    judged = score.judge(proposals, loop_truth)
    m = score.loop_metrics(judged, passes=2)
    assert (m["accepted"], m["correct"], m["with_truth"], m["false_accepts"]) == (4, 2, 4, 2)
    assert m["precision"] == 0.5 and m["recall"] == 0.5
    assert m["false_accepts_by_place"] == {"within_pass": 1, "across_passes": 1}
    assert m["max_recall_at_full_precision"] == 0.5  # 9 and 8 are right; 7 is wrong
    across = score.loop_metrics(score.only_across(judged), passes=2)
    assert (across["accepted"], across["false_accepts"], across["precision"]) == (3, 1, 2 / 3)
    outcome = StreamOutcome(proposals, np.zeros(8))
    assert len(outcome.proposals) == 8
