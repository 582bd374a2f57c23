"""The leaf all three packages share: atomic writes, image listing and the pose-file formats,
each written once. The last test guards the "once": a second copy in a package fails it."""

from __future__ import annotations

import ast
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from ssmvpr_common.atomic import atomic_write, atomic_write_bytes, atomic_write_text, default_file_mode
from ssmvpr_common.image_folders import IMAGE_SUFFIXES, image_files
from ssmvpr_common.poses import (
    data_lines,
    kitti_lines,
    matrix_to_quaternion,
    pose_from_kitti_row,
    pose_from_translation_quaternion,
    tum_lines,
)

ROOT = Path(__file__).resolve().parents[2]


def test_atomic_write_replaces_the_file_whole(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "out.txt"  # the folder is made
    atomic_write_text(target, "first\n")
    atomic_write_bytes(target, b"second\n")
    assert target.read_text() == "second\n"
    assert stat.S_IMODE(target.stat().st_mode) == default_file_mode()  # not mkstemp's 0600
    assert [p.name for p in target.parent.iterdir()] == ["out.txt"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path: Path) -> None:
    target = tmp_path / "out.bin"
    atomic_write_bytes(target, b"complete")

    def half_then_fail(handle: object) -> None:
        handle.write(b"half")  # type: ignore[attr-defined]
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, half_then_fail)
    assert target.read_bytes() == b"complete"
    assert os.listdir(tmp_path) == ["out.bin"]


def test_image_files_are_the_images_in_name_order(tmp_path: Path) -> None:
    for name in ["000010.png", "000002.JPG", "notes.txt", "000001.webp", ".hidden.tmp"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "000003.png").mkdir()  # a folder named like an image is not one
    assert [p.name for p in image_files(tmp_path)] == ["000001.webp", "000002.JPG", "000010.png"]
    assert all(s == s.lower() and s.startswith(".") for s in IMAGE_SUFFIXES)


def test_data_lines_skip_comments_and_take_commas() -> None:
    text = "# t x y z\n\n1, 2 3\n  # indented comment\n4\t5\n"
    assert data_lines(text) == [(3, ["1", "2", "3"]), (5, ["4", "5"])]


def test_tum_and_kitti_lines_read_back() -> None:
    pose = pose_from_translation_quaternion(np.array([1.0, -2.0, 3.5]), np.array([0.1, -0.2, 0.3, 0.9]))
    (tum,) = tum_lines(np.array([12.5]), pose[None], "{:.3f}", "{:.12g}")
    fields = tum.split()
    assert fields[0] == "12.500" and len(fields) == 8
    values = np.array(fields[1:], float)
    np.testing.assert_allclose(pose_from_translation_quaternion(values[:3], values[3:]), pose, atol=1e-10)
    assert values[6] >= 0  # qw >= 0, one of the two quaternions of a rotation
    np.testing.assert_allclose(values[3:], matrix_to_quaternion(pose[:3, :3]), atol=1e-10)
    (kitti,) = kitti_lines(pose[None], "{:.12g}")
    np.testing.assert_allclose(pose_from_kitti_row(np.array(kitti.split(), float)), pose, atol=1e-10)


def _definitions(package: str) -> list[tuple[str, str]]:
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef):
                found.append((node.name, str(path.relative_to(ROOT))))
            elif isinstance(node, ast.Assign):
                found += [(t.id, str(path.relative_to(ROOT))) for t in node.targets if isinstance(t, ast.Name)]
    return found


@pytest.mark.parametrize(
    "name",
    ["atomic_write", "atomic_write_text", "default_file_mode", "IMAGE_SUFFIXES", "image_files", "quaternion_to_matrix",
     "matrix_to_quaternion", "tum_lines", "kitti_lines", "TUM_COLUMNS", "KITTI_COLUMNS", "quoted", "shortened",
     "is_disk_full", "free_space"],
)  # fmt: skip
def test_each_shared_helper_is_defined_once_in_the_leaf(name: str) -> None:
    where = [path for package in ("frontend", "loopclosure", "ssmvpr_slam", "ssmvpr_common")
             for found, path in _definitions(package) if found == name]  # fmt: skip
    assert len(where) == 1 and where[0].startswith("ssmvpr_common/"), where
