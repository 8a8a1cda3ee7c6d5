"""BLAS threading policy for the mapping and registration hot paths."""

from __future__ import annotations

import contextlib


def single_blas_thread() -> contextlib.AbstractContextManager:
    """Limit BLAS/LAPACK to one thread inside the ``with`` block (threadpoolctl).

    The hot paths make many small batched LAPACK calls (Fast-GPOM block GPs, 3×3 SVDs); on this
    2-core class of machine a multi-threaded OpenBLAS ran them ~30× slower than one thread
    (measured by the mapping benchmark), so the pipeline and ``slam map`` pin one thread.
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1)
