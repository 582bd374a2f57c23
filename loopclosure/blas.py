"""One BLAS thread around the method's many small matrix products, at almost no cost per call.

Right after a backbone pass torch's threads still hold the cores, and a second BLAS thread on
these small products fights them for the cores instead of helping. `threadpool_limits` looks up
the loaded libraries on every call, which costs more than the products it guards; a
`ThreadpoolController` looks once (docs/benchmarks.md, "Thread settings"). It is looked up again only after an import, which is how
a new BLAS (OpenCV's, scipy's) would arrive; in a steady stream there is none.
"""

from __future__ import annotations

import sys
from contextlib import AbstractContextManager
from typing import Any

from threadpoolctl import ThreadpoolController

_found: tuple[int, ThreadpoolController] | None = None  # (len(sys.modules) when looked up, controller)


def one_blas_thread() -> AbstractContextManager[Any]:
    """``with one_blas_thread(): ...`` runs the block with every loaded BLAS library on one thread."""
    global _found
    if _found is None or _found[0] != len(sys.modules):
        import scipy.linalg  # noqa: F401  (scipy's own BLAS, which the PCA fit uses, must be loaded to be found)

        _found = (len(sys.modules), ThreadpoolController())
    return _found[1].limit(limits=1, user_api="blas")
