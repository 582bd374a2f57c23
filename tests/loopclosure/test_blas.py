"""`one_blas_thread`: every BLAS library on one thread inside, as it was outside."""

from __future__ import annotations

from threadpoolctl import threadpool_info

from loopclosure.blas import one_blas_thread


def _blas() -> dict[str, int]:
    return {lib["filepath"]: lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


def test_every_blas_library_runs_one_thread_inside_and_is_restored_after() -> None:
    with one_blas_thread():
        pass
    import cv2  # noqa: F401  (OpenCV brings a BLAS of its own: one loaded after the first call counts too)

    with one_blas_thread():
        inside = _blas()
    assert any("scipy.libs" in path for path in inside)  # scipy's own BLAS (the PCA fit's) is among them
    assert inside and set(inside.values()) == {1}
    after = _blas()
    with one_blas_thread():
        assert set(_blas().values()) == {1}
    assert _blas() == after
