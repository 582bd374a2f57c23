"""Ground-truth loaders: the real Corridor file, CSV forms, and the errors a user sees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from loopclosure.benchmark_truth import (
    GroundTruth,
    correct_mask,
    frame_aligned,
    from_csv,
    from_vprbench_npy,
    is_correct,
    load_ground_truth,
)
from loopclosure.errors import LoopClosureInputError

REF = [f"ref/{i:07d}.jpg" for i in range(6)]
QUERY = [f"query/{i:07d}.jpg" for i in range(4)]


def _refs(gt: GroundTruth) -> list[list[int]]:
    return [r.tolist() for r in gt.refs]


# --------------------------------------------------------------------------- real data


def test_corridor_ground_truth_loads(corridor_dir: Path) -> None:
    ref = sorted((corridor_dir / "ref").glob("*.jpg"))
    query = sorted((corridor_dir / "query").glob("*.jpg"))
    assert len(ref) == len(query) == 111
    gt = load_ground_truth(corridor_dir / "ground_truth_new.npy", ref, query)
    assert (gt.n_ref, gt.n_query) == (111, 111)
    assert gt.has_truth.all()
    # The file is frame-aligned with a ±2-frame window already baked in.
    for q, r in enumerate(gt.refs):
        assert r.tolist() == list(range(max(0, q - 2), min(110, q + 2) + 1))


def test_corridor_truth_is_refused_for_smaller_folders(corridor_dir: Path) -> None:
    with pytest.raises(LoopClosureInputError, match=r"row 108 \(query 108\): reference index 110 exceeds"):
        from_vprbench_npy(corridor_dir / "ground_truth_new.npy", n_ref=110, n_query=111)


# --------------------------------------------------------------------------- frame aligned


def test_frame_aligned() -> None:
    gt = frame_aligned(REF[:4], QUERY)
    assert _refs(gt) == [[0], [1], [2], [3]]
    assert load_ground_truth(None, REF[:4], QUERY).refs[2].tolist() == [2]


def test_frame_aligned_needs_equal_counts() -> None:
    with pytest.raises(LoopClosureInputError, match=r"4 query and 6 reference.*\.npy.*\.csv"):
        frame_aligned(REF, QUERY)


# --------------------------------------------------------------------------- VPR-Bench npy


def test_npy_scalar_and_list_rows(tmp_path: Path) -> None:
    rows = np.empty((3, 2), dtype=object)
    rows[0] = [0, [2, 1]]
    rows[1] = [2, 5]
    rows[2] = [0, np.array([3], dtype=np.int64)]
    p = tmp_path / "gt.npy"
    np.save(p, rows, allow_pickle=True)
    gt = from_vprbench_npy(p, n_ref=6, n_query=4)
    assert _refs(gt) == [[1, 2, 3], [], [5], []]
    assert gt.has_truth.tolist() == [True, False, True, False]


def test_npy_plain_int_array(tmp_path: Path) -> None:
    p = tmp_path / "gt.npy"
    np.save(p, np.array([[0, 0], [1, 3]]))
    assert _refs(from_vprbench_npy(p, 6, 2)) == [[0], [3]]


def test_npy_out_of_range(tmp_path: Path) -> None:
    p = tmp_path / "gt.npy"
    np.save(p, np.array([[0, 0], [1, 7]]))
    with pytest.raises(LoopClosureInputError, match=r"row 1 .*reference index 7 exceeds.*6 images"):
        from_vprbench_npy(p, 6, 2)
    np.save(p, np.array([[0, 0], [4, 1]]))
    with pytest.raises(LoopClosureInputError, match=r"row 1: query index 4 exceeds.*2 images"):
        from_vprbench_npy(p, 6, 2)


class _Evil:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (print, ("this must never run",))


def test_npy_refuses_code_in_pickle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    arr = np.empty((1, 2), dtype=object)
    arr[0] = [0, _Evil()]
    p = tmp_path / "evil.npy"
    np.save(p, arr, allow_pickle=True)
    with pytest.raises(LoopClosureInputError, match="builtins.print is not allowed"):
        from_vprbench_npy(p, 6, 2)
    assert "must never run" not in capsys.readouterr().out


def test_npy_unreadable(tmp_path: Path) -> None:
    p = tmp_path / "gt.npy"
    p.write_text("not numpy")
    with pytest.raises(LoopClosureInputError, match="not a readable .npy"):
        load_ground_truth(p, REF, QUERY)


# --------------------------------------------------------------------------- CSV


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "gt.csv"
    p.write_text(text)
    return p


def test_csv_ssmvpr_indices(tmp_path: Path) -> None:
    p = _write(tmp_path, "Reference,Live\n0,0\n2,1\n3,3\n")
    assert _refs(load_ground_truth(p, REF, QUERY)) == [[0], [2], [], [3]]


def test_csv_ssmvpr_filenames(tmp_path: Path) -> None:
    text = "Live,Reference\n0000000.jpg,0000004.jpg\nquery/0000001.jpg,0000005\n0000001,0000002.jpg\n"
    assert _refs(from_csv(_write(tmp_path, text), REF, QUERY)) == [[4], [2, 5], [], []]


def test_csv_berlin_multi_ref(tmp_path: Path) -> None:
    text = (
        "Serial No,Query,Ref\n"
        "1,0000000.jpg,0000001.jpg;0000002.jpg\n"
        "2,0000001.jpg,0000003.jpg 0000004.jpg\n"
        "3,0000002.jpg,\n"
        "4,0000003.jpg,0000005.jpg,0000000.jpg\n"
    )
    gt = from_csv(_write(tmp_path, text), REF, QUERY)
    assert _refs(gt) == [[1, 2], [3, 4], [], [0, 5]]


def test_csv_berlin_indices_and_spacing(tmp_path: Path) -> None:
    text = "serial_no, query , ref\n1, 0, 1 ; 2\n2, 3, 5\n"
    assert _refs(from_csv(_write(tmp_path, text), REF, QUERY)) == [[1, 2], [], [], [5]]


def test_csv_unknown_filename(tmp_path: Path) -> None:
    p = _write(tmp_path, "Serial No,Query,Ref\n1,0000000.jpg,missing.jpg\n")
    with pytest.raises(LoopClosureInputError, match=r"'missing.jpg' is not a file in the reference folder"):
        from_csv(p, REF, QUERY)
    p = _write(tmp_path, "Reference,Live\n0000001.jpg,nope.png\n")
    with pytest.raises(LoopClosureInputError, match=r"'nope.png' is not a file in the query folder"):
        from_csv(p, REF, QUERY)


def test_csv_index_out_of_range(tmp_path: Path) -> None:
    p = _write(tmp_path, "Reference,Live\n9,0\n")
    with pytest.raises(LoopClosureInputError, match=r"Reference index 9 is outside the reference folder"):
        from_csv(p, REF, QUERY)


def test_csv_missing_columns(tmp_path: Path) -> None:
    p = _write(tmp_path, "a,b\n1,2\n")
    with pytest.raises(LoopClosureInputError, match="needs a query column"):
        from_csv(p, REF, QUERY)


def test_csv_errors_quote_a_huge_cell_or_header_in_a_few_hundred_characters(tmp_path: Path) -> None:
    p = _write(tmp_path, "a," + "b" * 100_000 + "\n1,2\n")
    with pytest.raises(LoopClosureInputError, match="needs a query column") as caught:
        from_csv(p, REF, QUERY)
    assert "characters)" in str(caught.value) and len(str(caught.value)) < 500
    p = _write(tmp_path, "Reference,Live\n0000001.jpg," + "n" * 100_000 + "\n")
    with pytest.raises(LoopClosureInputError, match=r"'nnn.*…' \(100,000 characters\) is not a file") as caught:
        from_csv(p, REF, QUERY)
    assert len(str(caught.value)) < 500
    p = _write(tmp_path, "Reference,Live\n0000001.jpg," + "n" * 1_000_000 + "\n")  # past the csv module's limit
    with pytest.raises(LoopClosureInputError, match="not a readable CSV file .row 2: field larger than") as caught:
        from_csv(p, REF, QUERY)


def test_load_ground_truth_dispatch_errors(tmp_path: Path) -> None:
    with pytest.raises(LoopClosureInputError, match="does not exist"):
        load_ground_truth(tmp_path / "nope.csv", REF, QUERY)
    p = tmp_path / "gt.txt"
    p.write_text("x")
    with pytest.raises(LoopClosureInputError, match="unknown suffix"):
        load_ground_truth(p, REF, QUERY)


# --------------------------------------------------------------------------- correctness


def test_is_correct_and_mask() -> None:
    gt = GroundTruth.from_sets([[3], [], [0, 9]], n_ref=10)
    assert is_correct(gt, 0, 5, 2) and not is_correct(gt, 0, 6, 2)
    assert not is_correct(gt, 1, 1, 5)
    matches = np.array([[5, 6, -1], [1, 1, 1], [2, 7, 8]])
    assert correct_mask(gt, matches, 2).tolist() == [
        [True, False, False],
        [False, False, False],
        [True, True, True],
    ]
    assert correct_mask(gt, matches[:, 0], 0).tolist() == [False, False, False]


def test_correct_mask_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    n_ref, n_query = 30, 25
    sets = [rng.choice(n_ref, size=rng.integers(0, 4), replace=False) for _ in range(n_query)]
    gt = GroundTruth.from_sets(sets, n_ref)
    matches = rng.integers(-1, n_ref, size=(n_query, 7))
    for tol in (0, 1, 2, 5):
        expected = [[is_correct(gt, q, int(m), tol) for m in row] for q, row in enumerate(matches)]
        assert correct_mask(gt, matches, tol).tolist() == expected


def test_correct_mask_bad_input() -> None:
    gt = GroundTruth.from_sets([[0], [1]], n_ref=3)
    with pytest.raises(LoopClosureInputError, match="exceeds the reference set"):
        correct_mask(gt, np.array([0, 3]), 0)
    with pytest.raises(LoopClosureInputError, match="expected shape"):
        correct_mask(gt, np.array([0, 1, 2]), 0)
    with pytest.raises(LoopClosureInputError, match="tolerance"):
        correct_mask(gt, np.array([0, 1]), -1)
