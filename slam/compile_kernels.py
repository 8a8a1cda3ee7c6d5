"""``python -m slam.compile_kernels``: every compiled (numba) kernel of the package into numba's on-disk cache
(``make install``), so the first ``slam run`` does not spend seconds compiling."""

from __future__ import annotations

import numpy as np

from registration.compile_kernels import compile_all as compile_registration
from slam.loops.uncertainty import sum_to_root

__all__ = ["compile_all"]


def compile_all() -> None:
    """The registration kernels, then the pipeline's own, for the argument types the package passes."""
    compile_registration()
    sum_to_root(np.zeros((2, 3)), np.zeros(2, np.int64), 0)


if __name__ == "__main__":
    compile_all()
