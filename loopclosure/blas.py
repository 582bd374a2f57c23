"""One BLAS thread around the method's many small matrix products, at almost no cost per call.

Right after a backbone pass torch's threads still hold the cores, and a second BLAS thread on
these small products fights them for the cores instead of helping. `threadpool_limits` looks up
the loaded libraries on every call, which costs more than the products it guards; a
`ThreadpoolController` looks once (docs/benchmarks.md, "Thread settings"). It is looked up again only after an import, which is how
a new BLAS (OpenCV's, scipy's) would arrive; in a steady stream there is none.

Only the main thread sets the limit; elsewhere the block runs as it is. OpenBLAS's limit is the
process's, not a thread's, and threadpoolctl supports setting it from the main thread only: a
keyframe encoded ahead in another thread while the main one recognises would otherwise restore
the main thread's limit under it, or leave BLAS on one thread for good.
"""

from __future__ import annotations

import sys
import threading
from contextlib import AbstractContextManager, nullcontext
from typing import Any

from threadpoolctl import ThreadpoolController

_found: tuple[int, ThreadpoolController] | None = None  # (len(sys.modules) when looked up, controller)


def one_blas_thread() -> AbstractContextManager[Any]:
    """``with one_blas_thread(): ...`` runs the block with every loaded BLAS library on one thread."""
    global _found
    if threading.current_thread() is not threading.main_thread():
        return nullcontext()
    if _found is None or _found[0] != len(sys.modules):
        import scipy.linalg  # noqa: F401  (scipy's own BLAS, which the PCA fit uses, must be loaded to be found)

        _found = (len(sys.modules), ThreadpoolController())
    return _found[1].limit(limits=1, user_api="blas")
