"""``python -m slam.compile_kernels``: every compiled (numba) kernel of the package into numba's on-disk cache
(``make install``), so the first ``slam run`` does not spend seconds compiling."""

from __future__ import annotations

import numpy as np

from mapping.kernels import add_placed, resample_cells
from registration.compile_kernels import compile_all as compile_registration
from slam.loops.uncertainty import sum_to_root

__all__ = ["compile_all"]


def compile_all() -> None:
    """The registration kernels, the mapping stage's (open and sealed submaps: float64 and float32 grids),
    then the pipeline's own, for the argument types the package passes."""
    compile_registration()
    for dtype in (np.float64, np.float32):
        resample_cells(0, 0, 1, 1, 1, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, np.ones((1, 1), dtype))
        add_placed(np.zeros(1), np.zeros(1), np.zeros(1, np.int32), np.zeros(1, np.int32), np.ones(1, dtype),
                   np.ones(1, dtype), 1.0)
    sum_to_root(np.zeros((2, 3)), np.zeros(2, np.int64), 0)


if __name__ == "__main__":
    compile_all()
