"""loopclosure.backbone_input: folder listing, decoding and conversion to the backbone's input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from loopclosure.backbone_input import as_rgb, list_images, read_image, resize_square
from loopclosure.errors import LoopClosureInputError


def _write(path, image_bgr) -> None:
    assert cv2.imwrite(str(path), image_bgr)


def test_list_images_sorted_and_filtered(tmp_path):
    img = np.zeros((4, 4, 3), np.uint8)
    for name in ("b.png", "a.jpg", "c.JPG", "0010.bmp"):
        _write(tmp_path / name, img)
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "d.jpg").mkdir()  # a folder with an image-like name is not an image
    files = list_images(tmp_path)
    assert [f.name for f in files] == ["0010.bmp", "a.jpg", "b.png", "c.JPG"]


def test_list_images_missing_and_empty_folder(tmp_path):
    with pytest.raises(LoopClosureInputError, match="image folder not found.*nowhere"):
        list_images(tmp_path / "nowhere")
    (tmp_path / "readme.md").write_text("no images here")
    with pytest.raises(LoopClosureInputError, match=f"no images .* in folder {tmp_path}"):
        list_images(tmp_path)
    file = tmp_path / "readme.md"
    with pytest.raises(LoopClosureInputError, match="image folder not found"):
        list_images(file)  # a file is not a folder


def test_list_real_benchmark_folder(gardens_dir):
    files = list_images(gardens_dir / "ref")
    assert [f.name for f in files] == [f"{i}.jpg" for i in range(10)]


def test_read_image_returns_rgb(tmp_path):
    bgr = np.zeros((5, 7, 3), np.uint8)
    bgr[..., 2] = 255  # pure red in OpenCV's BGR order
    bgr[0, 0] = (255, 0, 0)  # one pure blue pixel
    _write(tmp_path / "red.png", bgr)
    rgb = read_image(tmp_path / "red.png")
    assert rgb.shape == (5, 7, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[1, 1], [255, 0, 0])
    np.testing.assert_array_equal(rgb[0, 0], [0, 0, 255])


def test_read_grey_file_gives_three_channels(tmp_path):
    grey = np.arange(20, dtype=np.uint8).reshape(4, 5) * 10
    _write(tmp_path / "grey.png", grey)
    rgb = read_image(str(tmp_path / "grey.png"))  # str paths too
    assert rgb.shape == (4, 5, 3)
    for c in range(3):
        np.testing.assert_array_equal(rgb[..., c], grey)


def test_read_real_images(gardens_dir):
    query = read_image(gardens_dir / "query" / "0.jpg")
    ref = read_image(gardens_dir / "ref" / "0.jpg")
    assert query.shape == (540, 960, 3) and ref.shape == (360, 640, 3)
    assert query.dtype == ref.dtype == np.uint8


def test_corrupt_file_names_the_file(tmp_path):
    bad = tmp_path / "frame_0042.jpg"
    bad.write_bytes(b"\xff\xd8\xff\xe0 definitely not a JPEG " * 20)
    with pytest.raises(LoopClosureInputError, match="corrupt.*frame_0042.jpg"):
        read_image(bad)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(LoopClosureInputError, match="empty.png"):
        read_image(empty)


def test_truncated_real_jpeg_does_not_pass_silently_as_garbage(tmp_path, gardens_dir):
    data = (gardens_dir / "ref" / "0.jpg").read_bytes()
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[:40])  # only the header survives
    with pytest.raises(LoopClosureInputError, match="cut.jpg"):
        read_image(cut)


def test_missing_file_and_directory_named(tmp_path):
    with pytest.raises(LoopClosureInputError, match="image not found.*ghost.jpg"):
        read_image(tmp_path / "ghost.jpg")
    (tmp_path / "dir.jpg").mkdir()
    with pytest.raises(LoopClosureInputError, match="dir.jpg"):
        read_image(tmp_path / "dir.jpg")


def test_as_rgb_grey_rgb_rgba():
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    out = as_rgb(grey)
    assert out.shape == (3, 4, 3)
    assert all(np.array_equal(out[..., c], grey) for c in range(3))

    rgb = np.random.default_rng(0).integers(0, 256, (3, 4, 3), dtype=np.uint8)
    assert np.array_equal(as_rgb(rgb), rgb)

    rgba = np.concatenate([rgb, np.full((3, 4, 1), 7, np.uint8)], axis=2)
    out = as_rgb(rgba)
    assert out.shape == (3, 4, 3) and out.flags.c_contiguous
    np.testing.assert_array_equal(out, rgb)  # alpha dropped, colours untouched (no BGR swap)


@pytest.mark.parametrize(
    "image", [np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.float64), np.zeros((4, 4, 3), np.uint16)]
)
def test_as_rgb_rejects_non_uint8(image):
    with pytest.raises(LoopClosureInputError, match="cam7: expected a uint8"):
        as_rgb(image, "cam7")


def test_as_rgb_rejects_non_arrays_and_odd_shapes():
    with pytest.raises(LoopClosureInputError, match="uint8"):
        as_rgb([[0, 1], [2, 3]])
    for shape in ((4, 4, 2), (4, 4, 5), (2, 4, 4, 3), (4,)):
        with pytest.raises(LoopClosureInputError, match=r"got shape"):
            as_rgb(np.zeros(shape, np.uint8))


@pytest.mark.parametrize("shape", [(540, 960, 3), (10, 20, 3), (224, 224, 3), (300, 100, 3)])
def test_resize_square(shape):
    image = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    out = resize_square(image, 224)
    assert out.shape == (224, 224, 3) and out.dtype == np.uint8
    if shape == (224, 224, 3):
        np.testing.assert_array_equal(out, image)


def test_resize_square_preserves_a_constant_colour_and_layout():
    image = np.zeros((60, 120, 3), np.uint8)
    image[:, :60] = (10, 200, 30)  # left half
    out = resize_square(image, 32)
    np.testing.assert_array_equal(out[5, 3], [10, 200, 30])
    np.testing.assert_array_equal(out[5, 28], [0, 0, 0])


def test_resize_square_empty_image():
    with pytest.raises(LoopClosureInputError, match="empty image"):
        resize_square(np.zeros((0, 5, 3), np.uint8), 32)
