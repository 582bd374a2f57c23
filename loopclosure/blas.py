"""One BLAS thread around the method's many small matrix products, at almost no cost per call.

Right after a backbone pass torch's threads still hold the cores, and a second BLAS thread on
these small products fights them for the cores instead of helping. `threadpool_limits` looks up
the loaded libraries on every call, which costs more than the products it guards; a
`ThreadpoolController` looks once (docs/benchmarks.md, "Thread settings"). It is looked up again only after an import, which is how
a new BLAS (OpenCV's, scipy's) would arrive; in a steady stream there is none.

A thread that runs beside the one recognising (a keyframe encoded ahead) sets no limit at all
(`blas_limits_left_alone`): OpenBLAS's limit is the process's, not a thread's, and such a thread
restoring its own would lift the other's under it, or leave BLAS on one thread for good.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Any

from threadpoolctl import ThreadpoolController

_found: tuple[int, ThreadpoolController] | None = None  # (len(sys.modules) when looked up, controller)


_this_thread = threading.local()


@contextmanager
def blas_limits_left_alone() -> Iterator[None]:
    """Inside it, `one_blas_thread` in this thread changes no limit (it runs beside another thread
    that may hold one)."""
    before = getattr(_this_thread, "left_alone", False)
    _this_thread.left_alone = True
    try:
        yield
    finally:
        _this_thread.left_alone = before


def one_blas_thread() -> AbstractContextManager[Any]:
    """``with one_blas_thread(): ...`` runs the block with every loaded BLAS library on one thread."""
    global _found
    if getattr(_this_thread, "left_alone", False):
        return nullcontext()
    if _found is None or _found[0] != len(sys.modules):
        import scipy.linalg  # noqa: F401  (scipy's own BLAS, which the PCA fit uses, must be loaded to be found)

        _found = (len(sys.modules), ThreadpoolController())
    return _found[1].limit(limits=1, user_api="blas")
