"""`one_blas_thread`: every BLAS library on one thread inside, as it was outside."""

from __future__ import annotations

from threadpoolctl import threadpool_info

from loopclosure.blas import blas_limits_left_alone, one_blas_thread


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


def test_a_thread_that_leaves_limits_alone_leaves_the_main_threads_limit_on() -> None:
    """A keyframe encoded ahead projects its codes in a thread of its own (its limits left alone)
    while the main thread recognises another inside the limit: that thread leaving its block must
    not lift the main thread's limit, and the limits are as they were once the main thread leaves."""
    import threading

    with one_blas_thread():  # every library it limits loaded before `before` is read
        pass
    before = _blas()
    other_in, main_in, other_out = threading.Event(), threading.Event(), threading.Event()

    def other() -> None:
        with blas_limits_left_alone(), one_blas_thread():
            other_in.set()
            main_in.wait(10)
        other_out.set()

    thread = threading.Thread(target=other)
    thread.start()
    other_in.wait(10)
    with one_blas_thread():
        main_in.set()
        other_out.wait(10)
        inside = _blas()
    thread.join(10)
    assert set(inside.values()) == {1}  # the main thread's limit, still on after the other left
    assert _blas() == before
